"""Reading what LIGGGHTS 3.8.0 prints: thermo rows as they stream (:class:`ThermoParser`),
and the runs and timings of a finished log (:func:`parse_runs`, :func:`parse_loop_time`,
:func:`loop_details`). Pure: text in, numbers out.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

__all__ = ["LoopTime", "RunSegment", "ThermoParser", "loop_details", "parse_loop_time", "parse_runs"]


class ThermoParser:
    """Follows LIGGGHTS thermo lines as they stream: a header line starting with ``Step``,
    then rows of numbers with as many fields. ``latest`` maps column name to value.

    ``discharged_columns`` / ``inserted_columns``: names whose sum is the solver's count of
    discharged / inserted particles; ``columns``: the deck's declared thermo columns."""

    def __init__(self, discharged_columns=(), inserted_columns=(), columns=()) -> None:
        self.header: list[str] | None = None
        self.latest: dict[str, float] = {}
        self.discharged_columns = tuple(discharged_columns)
        self.inserted_columns = tuple(inserted_columns)
        self.columns = tuple(columns)

    def feed(self, line: str) -> bool:
        """Consume one line; True if it was a thermo data row."""
        tokens = line.split()
        if not tokens:
            return False
        if tokens[0] == "Step":
            self.header = self._names(tokens)
            return False
        if self.header is None or len(tokens) != len(self.header):
            return False
        try:
            values = [float(v) for v in tokens]
        except ValueError:
            return False
        self.latest = dict(zip(self.header, values))
        return True

    def _names(self, printed: list[str]) -> list[str]:
        """LIGGGHTS 3.8.0 prints thermo names without their ``v_``/``f_`` prefix and cut to a
        few characters (``f_tscheck[1]`` -> ``tscheck[``): when the printed header matches the
        declared columns that way, the declared names are used."""
        if len(printed) != len(self.columns):
            return printed
        for shown, declared in zip(printed, self.columns):
            bare = declared[2:] if declared[:2] in ("v_", "f_", "c_") else declared
            if not (bare.startswith(shown) or declared == shown):
                return printed
        return list(self.columns)

    @property
    def step(self) -> int | None:
        return int(self.latest["Step"]) if "Step" in self.latest else None

    @property
    def atoms(self) -> int | None:
        return int(self.latest["Atoms"]) if "Atoms" in self.latest else None

    def _sum(self, names) -> float | None:
        present = [self.latest[n] for n in names if n in self.latest]
        return float(sum(present)) if present else None

    @property
    def discharged(self) -> float | None:
        return self._sum(self.discharged_columns)

    @property
    def inserted(self) -> float | None:
        return self._sum(self.inserted_columns)

    def counters(self) -> dict[str, float]:
        """The latest discharged, inserted, atoms and step, those known."""
        values = {"discharged": self.discharged, "inserted": self.inserted, "atoms": self.atoms, "step": self.step}
        return {name: value for name, value in values.items() if value is not None}


_LOOP_RE = re.compile(
    r"Loop time of\s+(?P<time>[-+0-9.eE]+)\s+on\s+(?P<procs>\d+)\s+procs\s+"
    r"(?:\(\d+\s+MPI\s+x\s+\d+\s+OpenMP\)\s+)?for\s+(?P<steps>\d+)\s+steps\s+with\s+(?P<atoms>\d+)\s+atoms"
)
_SECTION_RE = re.compile(r"^\s*(\w+)\s+time\s+\(%\)\s+=\s+([-+0-9.eE]+)")


@dataclass
class LoopTime:
    """One ``Loop time of ...`` line: wall seconds of a run's time-stepping loop."""

    seconds: float
    procs: int
    steps: int
    atoms: int


def parse_loop_time(line: str) -> LoopTime | None:
    """``Loop time of X on P procs for S steps with N atoms`` -> LoopTime, else None."""
    match = _LOOP_RE.search(line)
    if match is None:
        return None
    return LoopTime(float(match["time"]), int(match["procs"]), int(match["steps"]), int(match["atoms"]))


@dataclass
class RunSegment:
    """One ``run`` command of a LIGGGHTS log: its thermo rows and its loop time."""

    header: list[str] = field(default_factory=list)
    rows: list[list[float]] = field(default_factory=list)
    loop: LoopTime | None = None

    def column(self, name: str) -> list[float]:
        if name not in self.header:
            return []
        k = self.header.index(name)
        return [row[k] for row in self.rows]


def parse_runs(text: str) -> list[RunSegment]:
    """Split a LIGGGHTS log into its runs (one per ``Loop time`` line), with thermo rows."""
    runs: list[RunSegment] = []
    current = RunSegment()
    for line in text.splitlines():
        loop = parse_loop_time(line)
        if loop is not None:
            current.loop = loop
            runs.append(current)
            current = RunSegment()
            continue
        tokens = line.split()
        if tokens[:1] == ["Step"]:
            current.header, current.rows = tokens, []
        elif current.header and len(tokens) == len(current.header):
            try:
                current.rows.append([float(t) for t in tokens])
            except ValueError:
                pass
    return runs


def loop_details(text: str) -> dict:
    """What LIGGGHTS prints after the last ``Loop time`` line: seconds per section (Pair,
    Neigh, Comm, Outpt, Other -- fixes such as walls, meshes and insertion count as Other),
    neighbours per particle and neighbour-list builds."""
    starts = [m.start() for m in re.finditer(r"Loop time of", text)]
    if not starts:
        return {}
    out: dict = {"sections_s": {}}
    for line in text[starts[-1] :].splitlines()[1:]:
        if line.startswith("Loop time of") or line.split()[:1] == ["Step"]:
            break
        section = _SECTION_RE.match(line)
        if section:
            out["sections_s"][section.group(1)] = float(section.group(2))
        for key, label in (
            ("neighbours_per_particle", "Ave neighs/atom ="),
            ("neighbour_builds", "Neighbor list builds ="),
            ("dangerous_builds", "Dangerous builds ="),
        ):
            if line.startswith(label):
                out[key] = float(line.split("=")[1])
    return out
