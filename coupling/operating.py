"""The operating point of a DEM run: what a velocity table was measured at.

A table's velocities and rates mean something only at the speed, feed and blender they
were measured at. :class:`OperatingPoint` carries those with the table (the HDF5 attribute
:data:`ATTR`, ``coupling/DEFINITIONS.md``), so that the PBM's feed and feed zones, a table
library's speeds and a fit over many runs read them from the data instead of rebuilding
them from a configuration. The builder from a DEM configuration lives where that
configuration is known (:func:`dem.operating.operating_point`); this module knows only the
type and its record.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from coupling.errors import TableError

#: Attribute of the velocity-table group holding :meth:`OperatingPoint.record` as JSON.
ATTR = "operating_point"
#: Version of the record's layout (written as ``record["version"]``).
RECORD_VERSION = 1
FEEDERS = ("A", "B")


@dataclass(frozen=True)
class FeedZone:
    """A feeder's insertion zone projected on the compartment plane [m]: x axial from the
    inlet wall, y transverse from the impeller axis."""

    x_min_m: float
    x_max_m: float
    y_min_m: float
    y_max_m: float

    def __post_init__(self) -> None:
        for f in fields(self):
            object.__setattr__(self, f.name, _number(f"feed zone {f.name}", getattr(self, f.name)))
        if not (self.x_min_m < self.x_max_m and self.y_min_m < self.y_max_m):
            raise TableError(
                f"feed zone x [{self.x_min_m}, {self.x_max_m}] m, y [{self.y_min_m}, {self.y_max_m}] m: "
                "each range needs its minimum below its maximum"
            )

    @property
    def x_range_m(self) -> tuple[float, float]:
        return (self.x_min_m, self.x_max_m)

    @property
    def y_range_m(self) -> tuple[float, float]:
        return (self.y_min_m, self.y_max_m)


@dataclass(frozen=True)
class OperatingPoint:
    """Speed, feed, blender and particles of one DEM run (SI units; validated on
    construction, raises TableError naming the bad value).

    ``feed_rate_a_per_s`` / ``feed_rate_b_per_s``: each feeder's rate before any step
    [particles/s]; ``length_m`` / ``diameter_m``: the barrel [m]; ``blade_x_m``: the axial
    position of every blade station [m] (their count is ``blade_stations``);
    ``particle_diameter_m`` / ``particle_diameter_sd_m``: the normal size distribution
    [m], discretised into ``size_class_diameters_m`` [m] with number shares
    ``size_class_weights``; ``feed_zones``: feeder name ("A", "B") -> its zone.
    """

    impeller_rpm: float
    feed_rate_a_per_s: float
    feed_rate_b_per_s: float
    length_m: float
    diameter_m: float
    blade_x_m: tuple[float, ...]
    particle_diameter_m: float
    particle_diameter_sd_m: float
    size_class_diameters_m: tuple[float, ...]
    size_class_weights: tuple[float, ...]
    feed_zones: dict[str, FeedZone]

    def __post_init__(self) -> None:
        for name in ("impeller_rpm", "length_m", "diameter_m", "particle_diameter_m"):
            value = _number(name, getattr(self, name))
            if value <= 0:
                raise TableError(f"operating point {name} = {value}: must be > 0")
            object.__setattr__(self, name, value)
        for name in ("feed_rate_a_per_s", "feed_rate_b_per_s", "particle_diameter_sd_m"):
            value = _number(name, getattr(self, name))
            if value < 0:
                raise TableError(f"operating point {name} = {value}: must be >= 0")
            object.__setattr__(self, name, value)
        blades = tuple(_number("blade_x_m", x) for x in self.blade_x_m)
        if not blades or any(not 0 < x < self.length_m for x in blades) or list(blades) != sorted(blades):
            raise TableError(
                f"operating point blade_x_m = {list(blades)}: at least one station, increasing, "
                f"each inside (0, length_m = {self.length_m}) m"
            )
        object.__setattr__(self, "blade_x_m", blades)
        diameters = tuple(_number("size_class_diameters_m", d) for d in self.size_class_diameters_m)
        weights = tuple(_number("size_class_weights", w) for w in self.size_class_weights)
        if not diameters or len(weights) != len(diameters) or any(d <= 0 for d in diameters):
            raise TableError(
                f"operating point size classes: {len(diameters)} diameters {list(diameters)} m and "
                f"{len(weights)} weights; one weight per class and every diameter > 0 are needed"
            )
        if any(w < 0 for w in weights) or not math.isclose(sum(weights), 1.0, rel_tol=1e-9):
            raise TableError(f"operating point size_class_weights = {list(weights)}: shares >= 0 summing to 1")
        object.__setattr__(self, "size_class_diameters_m", diameters)
        object.__setattr__(self, "size_class_weights", weights)
        if set(self.feed_zones) != set(FEEDERS):
            raise TableError(
                f"operating point feed_zones name {sorted(self.feed_zones)}; one zone per feeder {FEEDERS}"
            )

    @property
    def blade_stations(self) -> int:
        """Number of blade stations on the impeller."""
        return len(self.blade_x_m)

    @property
    def size_classes(self) -> int:
        """Number of particle size classes."""
        return len(self.size_class_diameters_m)

    @property
    def feed_rate_total_per_s(self) -> float:
        """Both feeders together [particles/s]."""
        return self.feed_rate_a_per_s + self.feed_rate_b_per_s

    def feed_rate_per_s(self, feeder: str) -> float:
        """Feeder ``feeder``'s rate ("A" or "B") [particles/s]."""
        if feeder not in FEEDERS:
            raise TableError(f"unknown feeder {feeder!r}; feeders: {FEEDERS}")
        return self.feed_rate_a_per_s if feeder == "A" else self.feed_rate_b_per_s

    def differences(self, other: OperatingPoint) -> tuple[str, ...]:
        """The names of the fields in which ``other`` differs from this point."""
        return tuple(f.name for f in fields(self) if getattr(self, f.name) != getattr(other, f.name))

    def replace(self, **changes: Any) -> OperatingPoint:
        """A copy with some fields changed, validated again."""
        return replace(self, **changes)

    def scaled(self, length_factor: float = 1.0, diameter_factor: float = 1.0) -> OperatingPoint:
        """The same blender stretched ``length_factor`` x along x and ``diameter_factor`` x
        across (blade stations and feed zones with it): the point of a table whose
        compartments were scaled so (:func:`pbm.studies.scale_blender`)."""
        lf, df = float(length_factor), float(diameter_factor)
        zones = {
            name: FeedZone(z.x_min_m * lf, z.x_max_m * lf, z.y_min_m * df, z.y_max_m * df)
            for name, z in self.feed_zones.items()
        }
        return replace(
            self,
            length_m=self.length_m * lf,
            diameter_m=self.diameter_m * df,
            blade_x_m=tuple(x * lf for x in self.blade_x_m),
            feed_zones=zones,
        )

    def record(self) -> dict[str, Any]:
        """The JSON-ready record (lists for tuples), with its layout's version."""
        data = asdict(self)
        for name in ("blade_x_m", "size_class_diameters_m", "size_class_weights"):
            data[name] = list(data[name])
        return {"version": RECORD_VERSION, **data}

    @classmethod
    def from_record(cls, record: dict[str, Any], source: str = "") -> OperatingPoint:
        """The point a :meth:`record` describes; raises TableError naming a missing or bad entry."""
        where = f" in {source}" if source else ""
        if not isinstance(record, dict):
            raise TableError(f"the operating point{where} is {type(record).__name__}, not a record (a JSON object)")
        version = record.get("version")
        if version != RECORD_VERSION:
            raise TableError(f"operating point record version {version!r}{where}; this version reads {RECORD_VERSION}")
        names = [f.name for f in fields(cls)]
        missing = [name for name in names if name not in record]
        unknown = sorted(set(record) - {*names, "version"})
        if missing or unknown:
            raise TableError(f"operating point record{where}: missing {missing}, unknown {unknown}; it holds {names}")
        zones = record["feed_zones"]
        try:
            return cls(
                **{name: record[name] for name in names if name != "feed_zones"},
                feed_zones={name: FeedZone(**zone) for name, zone in dict(zones).items()},
            )
        except TableError as exc:
            raise TableError(f"{exc}{where}") from None
        except (TypeError, ValueError) as exc:
            raise TableError(f"operating point record{where} is malformed: {exc}") from None

    def to_json(self) -> str:
        """The record as JSON text (the HDF5 attribute :data:`ATTR`)."""
        return json.dumps(self.record(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str, source: str = "") -> OperatingPoint:
        """The point stored as :meth:`to_json` text; raises TableError on text that is no record."""
        try:
            record = json.loads(text)
        except (TypeError, json.JSONDecodeError) as exc:
            raise TableError(f"the operating point{' in ' + source if source else ''} is not JSON: {exc}") from None
        return cls.from_record(record, source)


def _number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise TableError(f"operating point {name} = {value!r}: a finite number is needed")
    return float(value)
