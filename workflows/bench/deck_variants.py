"""The per-fix variants of the resume deck that ``pbmdem bench dem-deck`` measures: each a
text edit of the deck :func:`dem.deck.build_deck` writes with ``resume_from``, which raises
:class:`DeckError` naming the variant when its line is missing, so that a change of the deck
cannot silently turn a variant into a copy of the blender run it is compared with."""

from __future__ import annotations

import re

from coupling.errors import DeckError

#: the deck's neighbour skin is 0.5 d; the ``skin_0.75d`` variant scales it by this
SKIN_FACTOR = 0.75 / 0.5


def _drop_lines(text: str, variant: str, patterns: list[str]) -> str:
    """``text`` without the lines matching each regex (from the line start); DeckError
    naming the variant and the pattern if one matches no line."""
    lines = text.splitlines(keepends=True)
    for pattern in patterns:
        regex = re.compile(pattern)
        kept = [line for line in lines if not regex.match(line)]
        if len(kept) == len(lines):
            raise DeckError(f"variant {variant}: no line matching {pattern!r} in the deck")
        lines = kept
    return "".join(lines)


def _drop_thermo_columns(text: str, variant: str, columns: list[str]) -> str:
    """``text`` with ``columns`` removed from its ``thermo_style`` line."""
    match = re.search(r"^thermo_style[ \t]+custom[ \t]+(.*)$", text, flags=re.M)
    if match is None:
        raise DeckError(f"variant {variant}: no 'thermo_style custom' line in the deck")
    tokens = match.group(1).split()
    missing = [c for c in columns if c not in tokens]
    if missing:
        raise DeckError(f"variant {variant}: thermo column(s) {missing} not in {tokens}")
    kept = " ".join(t for t in tokens if t not in columns)
    return text[: match.start(1)] + kept + text[match.end(1) :]


def _replace_once(text: str, variant: str, old: str, new: str) -> str:
    if text.count(old) != 1:
        raise DeckError(f"variant {variant}: {old!r} occurs {text.count(old)} times in the deck, not once")
    return text.replace(old, new)


def no_dump(text: str) -> str:
    return _drop_lines(text, "nodump", [r"dump\s"])


def no_massflow(text: str) -> str:
    text = _drop_lines(
        text, "no_massflow", [r"fix\s+outA\s", r"fix\s+outB\s", r"variable\s+outA\s", r"variable\s+outB\s"]
    )
    return _drop_thermo_columns(text, "no_massflow", ["v_outA", "v_outB"])


def no_insertion(text: str) -> str:
    # the insA/insB thermo variables read the insertion fixes: they go with them
    text = _drop_lines(
        text, "no_insertion", [r"fix\s+insA\s", r"fix\s+insB\s", r"variable\s+insA\s", r"variable\s+insB\s"]
    )
    return _drop_thermo_columns(text, "no_insertion", ["v_insA", "v_insB"])


def no_timestep_check(text: str) -> str:
    text = _drop_lines(text, "no_timestep_check", [r"fix\s+ts\s"])
    return _drop_thermo_columns(text, "no_timestep_check", ["f_ts[1]", "f_ts[2]"])


def no_weir(text: str) -> str:
    return _replace_once(text, "no_weir", "mesh n_meshes 2 meshes impeller weir", "mesh n_meshes 1 meshes impeller")


def static_impeller(text: str) -> str:
    return _drop_lines(text, "static_impeller", [r"fix\s+rotor\s"])


def wider_skin(text: str) -> str:
    match = re.search(r"^neighbor[ \t]+(\S+)[ \t]+bin[ \t]*$", text, flags=re.M)
    if match is None:
        raise DeckError("variant skin_0.75d: no 'neighbor <skin> bin' line in the deck")
    skin = float(match.group(1)) * SKIN_FACTOR
    return text[: match.start(1)] + f"{skin:.10g}" + text[match.end(1) :]


#: name -> edit of the resume deck's text, in the order they are run
VARIANTS = {
    "nodump": no_dump,
    "no_massflow": no_massflow,
    "no_insertion": no_insertion,
    "no_timestep_check": no_timestep_check,
    "no_weir": no_weir,
    "static_impeller": static_impeller,
    "skin_0.75d": wider_skin,
}
#: variants that change the number of particles during the run (cost per particle-step too)
COUNT_CHANGING = ("no_massflow", "no_insertion", "no_weir")
#: variants also measured on more than one rank
MULTI_RANK_VARIANTS = ("nodump",)
