"""Did a refactoring change any number? Two captures of pbmdem's outputs, compared.

``pbmdem bench same-numbers capture OUT [--checkout DIR]`` runs a fixed set of pbmdem
commands on the shipped reference data, each as a subprocess of the checkout to be
measured (``python -m workflows.cli`` with that checkout as the working directory, so its
own ``workflows/``, ``dem/``, ``pbm/`` and ``coupling/`` are imported), and writes their
outputs into ``OUT``. ``pbmdem bench same-numbers compare BEFORE AFTER [--list-skipped]``
prints one line per difference between two such trees and a last line ``N files compared,
M differences``; exit status 0 when there is none, 1 otherwise. The check knows nothing of
what the product computes: it compares files by the rules below. ``pbmdem bench all``
does not run it (a capture takes minutes and needs an output directory).

The commands (:func:`capture_steps`), and where they write:

* ``config --preset P`` for every preset of :data:`PRESETS`: stdout -> ``config-P.toml``;
* ``dem deck --preset P --out OUT/decks/P``;
* ``compare --preset reduced`` -> ``runs/`` and ``results/reduced/``;
* ``validate`` -> ``validation/`` and ``runs-validation/``;
* the README's design example (``design --ca-within 0.04 ...``) -> ``design/``;
* each command's stdout -> ``stdout/<step>.txt``, its stderr -> ``_logs/<step>.stderr``;
* ``_capture.json``: the tree's root, the checkout's root, the entry point and each
  step's exit code and wall time.

No capture runs a DEM simulation: a guard directory is put first on ``PATH`` in which
``mpirun``, ``mpiexec`` and ``liggghts`` refuse to start anything (exit 97), except
``liggghts ... -h``, the version banner that enters the runs' keys, which is forwarded to
the real ``liggghts``. A command that would need the solver fails instead of running it.

How each file is compared (first matching rule; paths relative to the tree root):

* ``*.json``: parsed and compared by value, recursively. Dicts: keys as sets (a missing or
  extra key is one difference), then each common key. Lists: length, then item by item.
  Numbers must be exactly equal (NaN equals NaN); an int that became a float (or a bool
  that became a number) is reported even when numerically equal, because the file's text
  changed. A file that does not parse is compared as text.
* text, line by line (``in.*`` LIGGGHTS decks, ``*.toml``, ``*.stl`` (ASCII), ``*.csv``,
  ``*.html``, ``*.txt`` (the commands' stdout), the ParaView ``*.pvd`` and ``*.vt?``
  (XML; the arrays zlib-compressed and base64-encoded, so any changed value changes its
  line)): after the root substitution and the masks below; changed, missing and extra
  lines are reported with their line numbers (difflib alignment, so one inserted line is
  one difference).
* every other file: byte for byte.
* both sides: a file or an empty directory present on one side only.

Root substitution: every string (JSON string values and keys, text lines) has the
capture's own root replaced by ``<TREE>`` and the checkout it ran from by ``<SRC>`` (read
from the tree's ``_capture.json``; without it only the tree root is replaced). The outputs
name their own directory (``report: <TREE>/...``) and the shipped reference files by
absolute path (``dem_cache_file``, ``library_dir``), which differ between two checkouts
for no numerical reason.

Skipped (:data:`SKIPPED_FILES`, listed by ``--list-skipped``):

* ``_logs/**``: the commands' stderr (progress, warnings);
* ``_capture.json``: the roots themselves and the steps' wall times;
* ``*.png``: rendered figures. Their numbers are in summary.json / the CSVs / the HTML;
  the pixels also depend on the matplotlib version and fonts;
* ``*.h5``, ``*.hdf5``: HDF5 embeds creation times (none is written by the captured
  commands today; the shipped DEM inputs are read, not written).

Ignored values (:data:`IGNORED_JSON_KEYS`, :data:`IGNORED_TEXT`), each genuinely
different between two runs of the same code or by design between two commits; all found
in the compare step's ``results/reduced/`` (``validate``, ``design``, ``config``
and the decks have none) except the last:

* ``provenance.report_made`` (summary.json) and the ``report_made`` row (report.html):
  the time the report was written;
* ``provenance.commit`` and the ``commit`` row: the git commit of the code that ran
  (differs between before and after by construction; same within one checkout);
* ``provenance.studies_wall_time_s`` and its row: measured wall time of the studies;
* ``metrics.pbm_wall_time_s``, ``pbm_summary.wall_time_s``,
  ``pbm_modes.<mode>.wall_time_s`` and the PBM cell of the report's "Wall time [s]" row:
  measured wall time of each PBM run;
* ``vrr.pbm.<mode>.ensemble_check[i].ensemble_s``: measured wall time of the noise
  ensemble;
* ``metrics.speedup_pbm_over_dem`` and the report's "PBM speed-up over DEM (wall time)"
  cell: the shipped DEM wall time divided by the measured PBM wall time;
* ``Name="Array 0x..."`` in the ParaView ``*.vt?`` files: VTK (pyvista) names the
  unnamed coordinate arrays after their memory address.

The shipped DEM wall times (``dem_wall_time_s``, ``campaign_elapsed_s`` ...) and dates
(``dem_results_made``) are read from the reference data and must not change: they are
compared.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import fnmatch
import json
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coupling.errors import ConfigError
from coupling.jsonable import write_json

__all__ = [
    "CAPTURE_FILE",
    "GUARD_EXIT",
    "IGNORED_JSON_KEYS",
    "IGNORED_TEXT",
    "PRESETS",
    "SKIPPED_FILES",
    "TEXT_FILES",
    "Capture",
    "Difference",
    "Step",
    "StepResult",
    "capture",
    "capture_steps",
    "compare_trees",
    "skip_reason",
    "solver_guard",
    "walk_trees",
]

#: Written by :func:`capture`: {"tree_root": ..., "source_root": ..., "entry": ..., "steps": ...}.
CAPTURE_FILE = "_capture.json"

#: The presets whose config and deck are captured.
PRESETS = ("smoke", "reduced", "validation", "paper")

#: Exit code of the guard's ``liggghts``/``mpirun``/``mpiexec`` when they refuse to run.
GUARD_EXIT = 97

#: Glob (on the relative POSIX path, ``**`` allowed) -> why the file is not compared.
SKIPPED_FILES: tuple[tuple[str, str], ...] = (
    ("_logs/**", "the commands' stderr"),
    (CAPTURE_FILE, "the capture's roots (used for the substitution) and the steps' wall times"),
    ("**.png", "rendered figures (pixels depend on matplotlib/fonts; numbers compared elsewhere)"),
    ("**.h5", "HDF5 embeds creation times"),
    ("**.hdf5", "HDF5 embeds creation times"),
)

#: Globs of files compared line by line as text (all others, except JSON, byte for byte).
TEXT_FILES: tuple[str, ...] = (
    "**/in.*",
    "in.*",
    "**.toml",
    "**.stl",
    "**.csv",
    "**.html",
    "**.txt",
    "**.pvd",
    "**.vtr",
    "**.vtp",
    "**.vtu",
    "**.vts",
    "**.vti",
)

_SUMMARY = "results/*/summary.json"
#: (file glob, JSON key path pattern, reason). Key paths are dotted with list indices as
#: ``[i]``; ``*`` in a pattern matches one key, ``[*]`` one list index.
IGNORED_JSON_KEYS: tuple[tuple[str, str, str], ...] = (
    (_SUMMARY, "provenance.report_made", "time the report was written"),
    (_SUMMARY, "provenance.commit", "git commit of the code that ran"),
    (_SUMMARY, "provenance.studies_wall_time_s", "measured wall time"),
    (_SUMMARY, "metrics.pbm_wall_time_s", "measured wall time"),
    (_SUMMARY, "pbm_summary.wall_time_s", "measured wall time"),
    (_SUMMARY, "pbm_modes.*.wall_time_s", "measured wall time"),
    (_SUMMARY, "metrics.speedup_pbm_over_dem", "DEM wall time / measured PBM wall time"),
    (_SUMMARY, "vrr.pbm.*.ensemble_check[*].ensemble_s", "measured wall time"),
)

_REPORT = "results/*/report.html"
#: (file glob, regex, reason): every group of each match is replaced by ``<IGNORED>`` on
#: both sides before the lines are compared.
IGNORED_TEXT: tuple[tuple[str, str, str], ...] = (
    (_REPORT, r"<td>report_made</td><td>([^<]*)</td>", "time the report was written"),
    (_REPORT, r"<td>commit</td><td>([^<]*)</td>", "git commit of the code that ran"),
    (_REPORT, r"<td>studies_wall_time_s</td><td>([^<]*)</td>", "measured wall time"),
    (
        _REPORT,
        r"<td>Wall time \[s\]</td><td>[^<]*</td><td>([^<]*)</td>",
        "measured PBM wall time (the shipped DEM's is compared)",
    ),
    (
        _REPORT,
        r"PBM speed-up over DEM \(wall time\)</td><td[^>]*>([^<]*)</td>",
        "DEM wall time / measured PBM wall time",
    ),
    ("**.vt?", r'Name="Array (0x[0-9a-f]+)"', "VTK names an unnamed array by its memory address"),
)

_MISSING = "<absent>"


@dataclass(frozen=True)
class Difference:
    """One difference between the trees.

    ``path``: relative POSIX path of the file (or empty directory). ``where``: the JSON key
    path (``metrics.rsd[3]``), ``line N`` (N: the before file's line, or the after file's
    for an extra line), ``bytes`` or ``file``. ``before`` / ``after``: the values (after
    root substitution), ``"<absent>"`` for an absent key, line or file."""

    path: str
    where: str
    before: Any
    after: Any

    def __str__(self) -> str:
        before, after = _show_pair(self.before, self.after)
        return f"{self.path}: {self.where}: {before} -> {after}"


# ----------------------------------------------------------------------------- helpers
def _glob_regex(pattern: str) -> re.Pattern[str]:
    """``**`` any characters, ``*`` any but '/', ``?`` one but '/'; whole path."""
    out = []
    i = 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out.append("(?:.*/)?")
            i += 3
        elif pattern.startswith("**", i):
            out.append(".*")
            i += 2
        elif pattern[i] == "*":
            out.append("[^/]*")
            i += 1
        elif pattern[i] == "?":
            out.append("[^/]")
            i += 1
        else:
            out.append(re.escape(pattern[i]))
            i += 1
    return re.compile("".join(out) + r"\Z")


def _matches(rel: str, pattern: str) -> bool:
    return _glob_regex(pattern).match(rel) is not None


def _key_matches(key_path: str, pattern: str) -> bool:
    """Dotted key path against a pattern whose ``*`` stands for one key or index."""
    segments = _split_key_path(key_path)
    patterns = _split_key_path(pattern)
    return len(segments) == len(patterns) and all(
        s == p or (p == "[*]" and s.startswith("[")) or (not p.startswith("[") and fnmatch.fnmatchcase(s, p))
        for s, p in zip(segments, patterns)
    )


def _split_key_path(path: str) -> list[str]:
    return [part for part in re.split(r"\.|(?=\[)", path) if part]


def _join(prefix: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{prefix}[{key}]"
    return f"{prefix}.{key}" if prefix else key


def _show(value: Any, limit: int = 160) -> str:
    text = value if value is _MISSING else json.dumps(value, ensure_ascii=False, default=str)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _show_pair(before: Any, after: Any, context: int = 60) -> tuple[str, str]:
    """Both values; two long strings are cut to the region around their first difference."""
    if isinstance(before, str) and isinstance(after, str) and max(len(before), len(after)) > 2 * context + 40:
        start = next((i for i, (a, b) in enumerate(zip(before, after)) if a != b), min(len(before), len(after)))
        lo = max(0, start - context)

        def cut(text: str) -> str:
            piece = text[lo : start + context]
            return ("..." if lo else "") + piece + ("..." if start + context < len(text) else "")

        return json.dumps(cut(before), ensure_ascii=False), json.dumps(cut(after), ensure_ascii=False)
    return _show(before), _show(after)


@dataclass(frozen=True)
class _Roots:
    """Absolute prefixes of one tree and their placeholders, longest first."""

    pairs: tuple[tuple[str, str], ...]

    @classmethod
    def of(cls, tree: Path) -> _Roots:
        found: dict[str, str] = {str(tree.resolve()): "<TREE>"}
        try:
            meta = json.loads((tree / CAPTURE_FILE).read_text())
        except (OSError, ValueError):
            meta = {}
        if isinstance(meta, dict):
            if isinstance(meta.get("tree_root"), str) and meta["tree_root"]:
                found[meta["tree_root"].rstrip("/")] = "<TREE>"
            if isinstance(meta.get("source_root"), str) and meta["source_root"]:
                found.setdefault(meta["source_root"].rstrip("/"), "<SRC>")
        return cls(tuple(sorted(found.items(), key=lambda item: -len(item[0]))))

    def strip(self, text: str) -> str:
        for root, placeholder in self.pairs:
            text = text.replace(root, placeholder)
        return text


def _entries(tree: Path) -> tuple[set[str], set[str]]:
    """Relative POSIX paths of the files and of the empty directories under ``tree``."""
    files: set[str] = set()
    empty_dirs: set[str] = set()
    for path in tree.rglob("*"):
        rel = path.relative_to(tree).as_posix()
        if path.is_dir() and not path.is_symlink():
            if not any(path.iterdir()):
                empty_dirs.add(rel + "/")
        else:
            files.add(rel)
    return files, empty_dirs


def skip_reason(rel: str) -> str | None:
    """Why ``rel`` is not compared (:data:`SKIPPED_FILES`), or None."""
    for pattern, reason in SKIPPED_FILES:
        if _matches(rel, pattern):
            return reason
    return None


# ----------------------------------------------------------------------------- JSON
def _same_number(a: Any, b: Any) -> bool:
    if type(a) is not type(b):
        return False
    if isinstance(a, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


def _compare_values(rel: str, key: str, a: Any, b: Any, ignored: Sequence[str]) -> Iterator[Difference]:
    if key and any(_key_matches(key, pattern) for pattern in ignored):
        return
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(a.keys() - b.keys()):
            if not any(_key_matches(_join(key, k), p) for p in ignored):
                yield Difference(rel, _join(key, k), a[k], _MISSING)
        for k in sorted(b.keys() - a.keys()):
            if not any(_key_matches(_join(key, k), p) for p in ignored):
                yield Difference(rel, _join(key, k), _MISSING, b[k])
        for k in a.keys() & b.keys():
            yield from _compare_values(rel, _join(key, k), a[k], b[k], ignored)
    elif isinstance(a, list) and isinstance(b, list):
        for i, (x, y) in enumerate(zip(a, b)):
            yield from _compare_values(rel, _join(key, i), x, y, ignored)
        for i in range(len(b), len(a)):
            yield Difference(rel, _join(key, i), a[i], _MISSING)
        for i in range(len(a), len(b)):
            yield Difference(rel, _join(key, i), _MISSING, b[i])
    elif isinstance(a, (int, float)) or isinstance(b, (int, float)):  # bool is an int
        if not _same_number(a, b):
            yield Difference(rel, key or "$", a, b)
    elif a != b:
        yield Difference(rel, key or "$", a, b)


def _strip_json(value: Any, roots: _Roots) -> Any:
    """``value`` with the roots substituted in every string (keys included); a new object."""
    if isinstance(value, str):
        return roots.strip(value)
    if isinstance(value, list):
        return [_strip_json(item, roots) for item in value]
    if isinstance(value, dict):
        return {roots.strip(k): _strip_json(v, roots) for k, v in value.items()}
    return value


def _compare_json(rel: str, a: Path, b: Path, ra: _Roots, rb: _Roots) -> list[Difference] | None:
    """The differences of two JSON files, or None when either does not parse."""
    try:
        before = json.loads(a.read_text(encoding="utf-8"))
        after = json.loads(b.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, ValueError):
        return None
    ignored = [key for glob, key, _ in IGNORED_JSON_KEYS if _matches(rel, glob)]
    return list(_compare_values(rel, "", _strip_json(before, ra), _strip_json(after, rb), ignored))


# ----------------------------------------------------------------------------- text
def _text_lines(path: Path, rel: str, roots: _Roots) -> list[str] | None:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        return None
    masks = [re.compile(rx) for glob, rx, _ in IGNORED_TEXT if _matches(rel, glob)]
    lines = []
    for line in text.splitlines():
        line = roots.strip(line)
        for mask in masks:
            line = _mask(line, mask)
        lines.append(line)
    return lines


def _mask(line: str, mask: re.Pattern[str]) -> str:
    def replace(match: re.Match[str]) -> str:
        whole, start = match.group(0), match.start(0)
        pieces, pos = [], 0
        for g in range(1, (match.re.groups or 0) + 1):
            if match.start(g) < 0:
                continue
            pieces += [whole[pos : match.start(g) - start], "<IGNORED>"]
            pos = match.end(g) - start
        return "".join(pieces) + whole[pos:]

    return mask.sub(replace, line)


def _compare_text(rel: str, a: Path, b: Path, ra: _Roots, rb: _Roots) -> list[Difference] | None:
    before, after = _text_lines(a, rel, ra), _text_lines(b, rel, rb)
    if before is None or after is None:
        return None
    out: list[Difference] = []
    matcher = difflib.SequenceMatcher(None, before, after, autojunk=False)
    for tag, i1, i2, j1, j2 in matcher.get_opcodes():
        if tag == "equal":
            continue
        for k in range(max(i2 - i1, j2 - j1)):
            old = before[i1 + k] if i1 + k < i2 else _MISSING
            new = after[j1 + k] if j1 + k < j2 else _MISSING
            line = i1 + k + 1 if i1 + k < i2 else j1 + k + 1
            out.append(Difference(rel, f"line {line}", old, new))
    return out


def _compare_bytes(rel: str, a: Path, b: Path) -> list[Difference]:
    before, after = a.read_bytes(), b.read_bytes()
    if before == after:
        return []
    at = next((i for i, (x, y) in enumerate(zip(before, after)) if x != y), min(len(before), len(after)))
    return [Difference(rel, "bytes", f"{len(before)} bytes, first difference at byte {at}", f"{len(after)} bytes")]


# ----------------------------------------------------------------------------- the walk
def _compare_file(rel: str, a: Path, b: Path, ra: _Roots, rb: _Roots) -> list[Difference]:
    found: list[Difference] | None = None
    if rel.endswith(".json"):
        found = _compare_json(rel, a, b, ra, rb)
    if found is None and (rel.endswith(".json") or any(_matches(rel, glob) for glob in TEXT_FILES)):
        found = _compare_text(rel, a, b, ra, rb)
    return found if found is not None else _compare_bytes(rel, a, b)


def walk_trees(before: Path, after: Path) -> tuple[list[Difference], list[str], list[str]]:
    """:func:`compare_trees` with the lists of compared and skipped relative paths."""
    before, after = Path(before), Path(after)
    for tree in (before, after):
        if not tree.is_dir():
            raise ConfigError(f"same-numbers: {tree} is not a directory (a capture tree is)")
    ra, rb = _Roots.of(before), _Roots.of(after)
    files_a, dirs_a = _entries(before)
    files_b, dirs_b = _entries(after)
    diffs: list[Difference] = []
    compared: list[str] = []
    skipped: list[str] = []
    for rel in sorted(files_a | files_b | dirs_a | dirs_b):
        if skip_reason(rel.rstrip("/")) is not None:
            skipped.append(rel)
            continue
        in_a = rel in files_a or rel in dirs_a
        in_b = rel in files_b or rel in dirs_b
        if in_a and in_b:
            if rel.endswith("/"):
                continue  # empty on both sides
            compared.append(rel)
            diffs += _compare_file(rel, before / rel, after / rel, ra, rb)
        else:
            kind = "empty directory" if rel.endswith("/") else "file"
            diffs.append(Difference(rel, "file", kind if in_a else _MISSING, kind if in_b else _MISSING))
    return diffs, compared, skipped


def compare_trees(before: Path, after: Path) -> list[Difference]:
    """Every difference between the capture trees ``before`` and ``after`` (rules: module
    docstring), sorted by path. Reads both trees, writes nothing."""
    return walk_trees(before, after)[0]


# ----------------------------------------------------------------------------- the capture
@dataclass(frozen=True)
class Step:
    """One captured command: ``args`` after the entry point; its stdout goes to ``stdout``
    (relative to the tree)."""

    name: str
    args: tuple[str, ...]
    stdout: str


@dataclass(frozen=True)
class StepResult:
    """How one step ended: exit code and wall time [s]."""

    step: Step
    exit_code: int
    wall_s: float

    @property
    def ok(self) -> bool:
        return self.exit_code == 0


@dataclass(frozen=True)
class Capture:
    """A finished capture: its tree, the checkout it measured and every step's result."""

    out: Path
    checkout: Path
    steps: tuple[StepResult, ...]

    @property
    def failed(self) -> tuple[StepResult, ...]:
        return tuple(result for result in self.steps if not result.ok)


def capture_steps(out: Path) -> tuple[Step, ...]:
    """The fixed command set, writing under the absolute directory ``out`` (module docstring)."""
    steps: list[Step] = []
    for preset in PRESETS:
        steps.append(Step(f"config-{preset}", ("config", "--preset", preset), f"config-{preset}.toml"))
        steps.append(
            Step(
                f"deck-{preset}",
                ("dem", "deck", "--preset", preset, "--out", str(out / "decks" / preset)),
                f"stdout/deck-{preset}.txt",
            )
        )
    steps.append(
        Step(
            "compare",
            (
                "compare",
                "--preset",
                "reduced",
                "--runs-dir",
                str(out / "runs"),
                "--out",
                str(out / "results" / "reduced"),
                "--no-progress",
            ),
            "stdout/compare.txt",
        )
    )
    steps.append(
        Step(
            "validate",
            ("validate", "--out", str(out / "validation"), "--runs-dir", str(out / "runs-validation")),
            "stdout/validate.txt",
        )
    )
    # README.md, "Design with the probability that the spec is met" (workflows/prediction/DESIGN-SEARCH.md)
    steps.append(
        Step(
            "design",
            (
                "design",
                "--ca-within",
                "0.04",
                "--noise-sigma",
                "0.1",
                "--noise-tau",
                "5",
                "--mrt-max",
                "25",
                "--out",
                str(out / "design"),
            ),
            "stdout/design.txt",
        )
    )
    return tuple(steps)


_GUARD_LIGGGHTS = """#!/bin/sh
# pbmdem bench same-numbers: only the version banner (-h) may run
for a in "$@"; do
    if [ "$a" = "-h" ] && [ -n {real} ]; then exec {real} "$@"; fi
done
echo "same-numbers guard: refusing to run LIGGGHTS ($*)" >&2
exit {code}
"""
_GUARD_LAUNCHER = """#!/bin/sh
echo "same-numbers guard: refusing to run {name} $*" >&2
exit {code}
"""


@contextlib.contextmanager
def solver_guard(path: str) -> Iterator[str]:
    """A ``PATH`` value: a temporary guard directory, then ``path``. In it ``mpirun`` and
    ``mpiexec`` refuse to start anything and ``liggghts`` refuses everything but ``-h``
    (the version banner), which is forwarded to the ``liggghts`` found on ``path``
    (refused too when there is none). A refusal exits with :data:`GUARD_EXIT`. The
    directory is removed on exit."""
    real = shutil.which("liggghts", path=path) or ""
    with tempfile.TemporaryDirectory(prefix="same_numbers_guard_") as guard:
        scripts = {"liggghts": _GUARD_LIGGGHTS.format(real=shlex.quote(real), code=GUARD_EXIT)}
        scripts.update({name: _GUARD_LAUNCHER.format(name=name, code=GUARD_EXIT) for name in ("mpirun", "mpiexec")})
        for name, text in scripts.items():
            script = Path(guard) / name
            script.write_text(text)
            script.chmod(0o755)
        yield os.pathsep.join([guard, path]) if path else guard


def _check_empty(out: Path) -> None:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(
            f"same-numbers capture: {out} exists and is not an empty directory; refusing to mix two captures"
        )


def capture(
    out: Path,
    entry: Sequence[str] | None = None,
    checkout: Path | None = None,
    progress: Callable[[StepResult], None] | None = None,
) -> Capture:
    """Run :func:`capture_steps` into the new or empty directory ``out``, each step as
    ``[*entry, *step.args]`` in the directory ``checkout`` (default: the current one) under
    :func:`solver_guard`. ``entry`` defaults to ``[sys.executable, "-m", "workflows.cli"]``,
    which imports the checkout's own packages. Writes each step's stdout and stderr and
    ``_capture.json`` (rewritten after every step, so an interrupted capture still has its
    roots); calls ``progress`` after each step. A failed step is recorded and the next one
    runs. Raises :class:`ConfigError` for a non-empty ``out`` or a ``checkout`` without
    ``workflows/cli``, before anything is written."""
    out = Path(out).absolute()
    checkout = Path(checkout if checkout is not None else Path.cwd()).absolute()
    entry = list(entry) if entry is not None else [sys.executable, "-m", "workflows.cli"]
    _check_empty(out)
    if not (checkout / "workflows" / "cli").is_dir():
        raise ConfigError(
            f"same-numbers capture: --checkout {checkout} has no workflows/cli; give the root of a pbmdem checkout"
        )
    (out / "stdout").mkdir(parents=True, exist_ok=True)
    (out / "_logs").mkdir()
    results: list[StepResult] = []

    def record() -> None:
        write_json(
            out / CAPTURE_FILE,
            {
                "tree_root": str(out),
                "source_root": str(checkout),
                "entry": entry,
                "steps": [
                    {
                        "name": r.step.name,
                        "command": [*entry, *r.step.args],
                        "exit": r.exit_code,
                        "wall_s": round(r.wall_s, 1),
                    }
                    for r in results
                ],
            },
        )

    record()
    with solver_guard(os.environ.get("PATH", os.defpath)) as guarded_path:
        env = {**os.environ, "PATH": guarded_path}
        for step in capture_steps(out):
            start = time.perf_counter()
            with open(out / step.stdout, "wb") as stdout, open(out / "_logs" / f"{step.name}.stderr", "wb") as stderr:
                code = subprocess.run(
                    [*entry, *step.args],
                    cwd=checkout,
                    env=env,
                    stdin=subprocess.DEVNULL,
                    stdout=stdout,
                    stderr=stderr,
                    check=False,
                ).returncode
            results.append(StepResult(step, code, time.perf_counter() - start))
            record()
            if progress is not None:
                progress(results[-1])
    return Capture(out, checkout, tuple(results))


# ----------------------------------------------------------------------------- command line
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``capture OUT [--checkout DIR]`` and ``compare BEFORE AFTER [--list-skipped]``."""
    sub = parser.add_subparsers(dest="same_numbers", required=True, metavar="ACTION")
    take = sub.add_parser(
        "capture",
        help="run the fixed command set into OUT (several minutes)",
        description="Run the fixed command set of the shipped data into the new or empty OUT.",
    )
    take.add_argument("out", type=Path, metavar="OUT")
    take.add_argument(
        "--checkout", type=Path, default=None, help="root of the checkout to measure (default: the current directory)"
    )
    compare = sub.add_parser(
        "compare",
        help="every difference between two captures; exit 1 if any",
        description="Every difference between two capture trees; exit 0 when none, 1 otherwise.",
    )
    compare.add_argument("before", type=Path, metavar="BEFORE")
    compare.add_argument("after", type=Path, metavar="AFTER")
    compare.add_argument("--list-skipped", action="store_true", help="also print every skipped file and why")


def _print_step(result: StepResult) -> None:
    if result.ok:
        print(f"ok ({result.wall_s:.1f}s): {result.step.name}", flush=True)
    else:
        print(
            f"FAILED (exit {result.exit_code}, {result.wall_s:.1f}s): {result.step.name}  "
            f"(see _logs/{result.step.name}.stderr)",
            flush=True,
        )


def run(args: argparse.Namespace) -> int:
    if args.same_numbers == "capture":
        done = capture(args.out, checkout=args.checkout, progress=_print_step)
        for result in done.failed:
            tail = (done.out / "_logs" / f"{result.step.name}.stderr").read_text(errors="replace").splitlines()[-20:]
            print(f"--- {result.step.name}: last lines of its stderr ---", *tail, sep="\n")
        print(f"{len(done.steps)} steps, {len(done.failed)} failed; capture of {done.checkout} in {done.out}")
        return 1 if done.failed else 0
    diffs, compared, skipped = walk_trees(args.before, args.after)
    for diff in diffs:
        print(diff)
    if args.list_skipped:
        for rel in skipped:
            print(f"skipped: {rel} ({skip_reason(rel.rstrip('/'))})")
    elif skipped:
        print(f"{len(skipped)} files skipped (--list-skipped names them)")
    print(f"{len(compared)} files compared, {len(diffs)} differences")
    return 1 if diffs else 0
