"""The configuration reference: every key of :class:`workflows.config.Config` with its type,
unit, default, valid range and description, read from the models themselves.

Nothing here is written by hand twice: the description is the field's own, the default and
the range come from its ``Field`` bounds (``gt``/``ge``/``lt``/``le``, a pattern, the
``Literal`` choices), and the unit from its name's suffix (the project names units in field
names: ``length_m``, ``duration_s``, ``feed_rate_total_per_s``). The steady-state rule is a
plain dataclass checked in ``__post_init__``; its fields carry the same facts in their
``metadata``. :func:`config_reference` returns typed sections; :func:`reference_text` and
:func:`reference_markdown` render them (``pbmdem config --describe [KEY] [--markdown]``),
and ``workflows/CONFIG.md`` is the Markdown page, checked by a test to be current.
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import json
import textwrap
import types
import typing
from dataclasses import dataclass
from typing import Any, Literal

import annotated_types
from pydantic import BaseModel

from coupling.errors import ConfigError
from workflows.config import Config

#: The command that writes the reference page, named in the page and in the staleness test.
PAGE_COMMAND = "pbmdem config --describe --markdown > workflows/CONFIG.md"

#: Unit of a field by its name's suffix, the longer suffix first (``_per_s`` before ``_s``).
UNIT_SUFFIXES = (
    ("_per_s", "1/s"),
    ("_kg_m3", "kg/m^3"),
    ("_pa", "Pa"),
    ("_rpm", "rpm"),
    ("_deg", "deg"),
    ("_s", "s"),
    ("_m", "m"),
)

#: Columns of :func:`reference_text`'s wrapped descriptions.
TEXT_WIDTH = 96

#: Shown for a field without a unit: a ratio, a coefficient, a count, a choice or text.
NO_UNIT = "-"


@dataclass(frozen=True)
class FieldReference:
    """One configuration key: ``key`` dotted (``dem.geometry.length_m``), and as text its
    ``type``, ``unit``, ``default`` (as TOML writes it; ``unset`` for None: leave the key
    out), ``valid`` (range, pattern or choices) and ``description``."""

    key: str
    type: str
    unit: str
    default: str
    valid: str
    description: str


@dataclass(frozen=True)
class SectionReference:
    """A TOML table of the configuration (``dem.geometry``; ``""`` for the top level), the
    first paragraph of its model's docstring and its scalar fields."""

    key: str
    summary: str
    fields: tuple[FieldReference, ...]


def config_reference(model: type = Config) -> tuple[SectionReference, ...]:
    """Every section of ``model``, depth first in the models' field order."""
    sections: list[SectionReference] = []
    _collect(model, "", sections)
    return tuple(sections)


def all_fields(sections: tuple[SectionReference, ...] | None = None) -> tuple[FieldReference, ...]:
    sections = config_reference() if sections is None else sections
    return tuple(f for section in sections for f in section.fields)


def describe(key: str | None = None) -> tuple[SectionReference, ...]:
    """The sections to print for ``key``: all for None or ``""``; a section (``dem.geometry``)
    with its subsections; a field (``dem.geometry.length_m``) alone in its section. Raises
    ConfigError naming the nearest valid keys for an unknown one."""
    sections = config_reference()
    if not key:
        return sections
    for section in sections:
        for f in section.fields:
            if f.key == key:
                return (dataclasses.replace(section, fields=(f,)),)
    chosen = tuple(s for s in sections if s.key == key or s.key.startswith(key + "."))
    if chosen:
        return chosen
    raise ConfigError(_unknown_key(key, sections))


def reference_text(sections: tuple[SectionReference, ...]) -> str:
    """Plain text for a terminal: per field, its key with type and unit, its default and
    valid range, and its description."""
    lines = []
    for section in sections:
        for f in section.fields:
            unit = "" if f.unit == NO_UNIT else f", {f.unit}"
            lines += [
                f"{f.key} ({f.type}{unit})",
                f"    default {f.default}; valid {f.valid}",
                textwrap.fill(f.description, width=TEXT_WIDTH, initial_indent="    ", subsequent_indent="    "),
            ]
    return "\n".join(lines) + "\n"


def reference_markdown(sections: tuple[SectionReference, ...] | None = None) -> str:
    """The reference page: one table per section."""
    sections = config_reference() if sections is None else sections
    lines = [
        "# Configuration reference",
        "",
        "Generated from the configuration models; do not edit by hand. Regenerate with",
        f"`{PAGE_COMMAND}`",
        "(`tests/workflows/test_config_reference.py` fails when this page differs from what the",
        "code generates). `pbmdem config --describe KEY` prints one key or one section.",
        "",
        "A configuration is one TOML file; each section below is a TOML table and each key a",
        "line in it. Start from a preset (`pbmdem config --preset reduced > my.toml`) and pass",
        "it with `--config my.toml`. Units are those the code computes in: SI lengths, times,",
        "pressures and densities, angles in degrees, the impeller speed in rpm; `1/s` is",
        "particles per second for a feed rate; `-`: no unit. `unset`: leave the key out (None",
        "in Python). Checks that involve several keys (blade tips clear of the wall by more than",
        "the largest particle, feed zones inside the barrel, the timestep's stable limit) run",
        "when the configuration is loaded, and refuse a value naming it and what is valid.",
    ]
    for section in sections:
        if not section.fields:
            continue
        title = section.key or "top level"
        lines += ["", f"## `{title}`" if section.key else f"## {title}", ""]
        if section.summary:
            lines += [section.summary, ""]
        lines += ["| key | type | unit | default | valid | description |", "| --- | --- | --- | --- | --- | --- |"]
        for f in section.fields:
            cells = (f"`{f.key}`", f.type, f.unit, f"`{f.default}`", f"`{f.valid}`", f.description)
            lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- reading the models
def _collect(model: type, prefix: str, sections: list[SectionReference]) -> None:
    fields: list[FieldReference] = []
    nested: list[tuple[type, str]] = []
    for name, spec in _field_specs(model):
        key = f"{prefix}.{name}" if prefix else name
        if _is_section(spec.annotation):
            nested.append((spec.annotation, key))
        else:
            fields.append(_reference(key, name, spec))
    sections.append(SectionReference(prefix, _summary(model), tuple(fields)))
    for child, key in nested:
        _collect(child, key, sections)


@dataclass(frozen=True)
class _Spec:
    """What the reference needs of a field, from pydantic or from a dataclass."""

    annotation: Any
    default: Any
    description: str
    bounds: dict[str, Any]
    pattern: str | None


def _field_specs(model: type) -> list[tuple[str, _Spec]]:
    if issubclass(model, BaseModel):
        specs = []
        for name, info in model.model_fields.items():
            bounds, pattern = {}, None
            for item in info.metadata:
                for attr in ("gt", "ge", "lt", "le"):
                    if isinstance(item, getattr(annotated_types, attr.capitalize())):
                        bounds[attr] = getattr(item, attr)
                pattern = getattr(item, "pattern", None) or pattern
            specs.append((name, _Spec(info.annotation, info.default, info.description or "", bounds, pattern)))
        return specs
    hints = typing.get_type_hints(model)
    return [
        (
            f.name,
            _Spec(
                hints[f.name], f.default, f.metadata.get("description", ""), dict(f.metadata.get("bounds", {})), None
            ),
        )
        for f in dataclasses.fields(model)
    ]


def _is_section(annotation: Any) -> bool:
    return isinstance(annotation, type) and (issubclass(annotation, BaseModel) or dataclasses.is_dataclass(annotation))


def _summary(model: type) -> str:
    doc = inspect.getdoc(model) if model.__doc__ else ""
    return " ".join((doc or "").split("\n\n")[0].split())


def _reference(key: str, name: str, spec: _Spec) -> FieldReference:
    base, optional = _without_none(spec.annotation)
    return FieldReference(
        key=key,
        type=_type_name(base) + (" or unset" if optional else ""),
        unit=_unit(name),
        default="unset" if spec.default is None else _toml(spec.default),
        valid=_valid(base, spec),
        description=spec.description,
    )


def _without_none(annotation: Any) -> tuple[Any, bool]:
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return (args[0] if len(args) == 1 else annotation), len(args) < len(typing.get_args(annotation))
    return annotation, False


def _type_name(annotation: Any) -> str:
    if typing.get_origin(annotation) is Literal:
        return "choice"
    if typing.get_origin(annotation) is list:
        return f"list[{_type_name(typing.get_args(annotation)[0])}]"
    return getattr(annotation, "__name__", str(annotation))


def _unit(name: str) -> str:
    return next((unit for suffix, unit in UNIT_SUFFIXES if name.endswith(suffix)), NO_UNIT)


def _valid(annotation: Any, spec: _Spec) -> str:
    if typing.get_origin(annotation) is Literal:
        return "one of " + ", ".join(json.dumps(c) for c in typing.get_args(annotation))
    if spec.pattern:
        return f"matches {spec.pattern}"
    b = spec.bounds
    low = ("(", b["gt"]) if "gt" in b else ("[", b["ge"]) if "ge" in b else None
    high = (")", b["lt"]) if "lt" in b else ("]", b["le"]) if "le" in b else None
    if low and high:
        return f"{low[0]}{_toml(low[1])}, {_toml(high[1])}{high[0]}"
    if low:
        return f"{'>' if low[0] == '(' else '>='} {_toml(low[1])}"
    if high:
        return f"{'<' if high[0] == ')' else '<='} {_toml(high[1])}"
    # a list or a text may still be checked by a validator: its description says how
    return "any" if annotation in (int, float) else NO_UNIT


def _toml(value: Any) -> str:
    """A value as a TOML file writes it (``pbmdem config --preset`` prints the same)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return json.dumps(str(value))


def _cell(text: str) -> str:
    """A table cell: a pipe would end the cell (GitHub's tables read ``\\|`` as ``|``, in
    code spans too)."""
    return text.replace("|", "\\|")


def _unknown_key(key: str, sections: tuple[SectionReference, ...]) -> str:
    keys = [f.key for s in sections for f in s.fields] + [s.key for s in sections if s.key]
    leaf = key.rsplit(".", 1)[-1]
    # a bare field name (``length_m``) is most likely meant as the key that ends in it
    same_leaf = [k for k in keys if k.rsplit(".", 1)[-1] == leaf]
    close = difflib.get_close_matches(key, keys, n=3, cutoff=0.6)
    by_leaf = difflib.get_close_matches(leaf, sorted({k.rsplit(".", 1)[-1] for k in keys}), n=2, cutoff=0.75)
    nearest = list(dict.fromkeys([*same_leaf, *close, *(k for k in keys if k.rsplit(".", 1)[-1] in by_leaf)]))[:3]
    if nearest:
        return f"unknown configuration key {key!r}; nearest valid keys: {', '.join(nearest)}"
    return (
        f"unknown configuration key {key!r}; valid sections: "
        f"{', '.join(s.key for s in sections if s.key)} (`pbmdem config --describe` lists every key)"
    )
