"""The DEM results' scalars as typed objects: :class:`DemSummary`, with the pooled RTD
(:class:`PooledRtdSummary`) and every estimate with its 95 % interval (:class:`Estimate`).

Post-processing builds the record (a dict, the form the cache and ``summary.json`` hold);
:meth:`DemSummary.from_record` reads it once, and every reader uses the fields. A record
round-trips exactly (:meth:`DemSummary.record`): keys this version does not know -- from
a newer post-processing, or added by the pipeline such as ``wall_time_s`` -- are kept in
``extra`` and written back.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from coupling.summary import ProcessSummary


@dataclass(frozen=True)
class Estimate:
    """A DEM estimate with its 95 % interval (scalars, or lists per slice)."""

    value: Any
    low: Any
    high: Any

    @classmethod
    def from_record(cls, record: Mapping[str, Any] | None) -> Estimate | None:
        if not record:
            return None
        return cls(record.get("value", math.nan), record.get("low", math.nan), record.get("high", math.nan))

    def record(self) -> dict[str, Any]:
        return {"value": self.value, "low": self.low, "high": self.high}


@dataclass(frozen=True)
class PooledRtdSummary:
    """The DEM's pooled RTD (:func:`dem.steady.pooled_rtd`): every particle that entered in
    ``entry_window_s`` after the steady state, followed for ``horizon_s``. A run too short
    for an entry window has ``n_entered`` = 0 and a ``note`` saying why."""

    horizon_s: float
    entry_window_s: tuple[float, float]
    n_entered: int
    n_recovered: int = 0
    recovered_ok: bool = False
    mean_residence_time_s: Estimate | None = None
    rtd_variance_s2: Estimate | None = None
    recovered_fraction: Estimate | None = None
    bin_s: float | None = None
    note: str | None = None
    #: the 5-s blocks of entry time the intervals resample (their expansion's n)
    n_blocks: int | None = None

    @property
    def has_tracers(self) -> bool:
        return self.n_entered > 0

    @classmethod
    def from_record(cls, record: Mapping[str, Any] | None) -> PooledRtdSummary | None:
        if not record or "horizon_s" not in record:
            return None
        return cls(
            float(record["horizon_s"]),
            tuple(record["entry_window_s"]),
            int(record.get("n_entered", 0)),
            int(record.get("n_recovered", 0)),
            bool(record.get("recovered_ok", False)),
            Estimate.from_record(record.get("mean_residence_time_s")),
            Estimate.from_record(record.get("rtd_variance_s2")),
            Estimate.from_record(record.get("recovered_fraction")),
            record.get("bin_s"),
            record.get("note"),
            None if record.get("n_blocks") is None else int(record["n_blocks"]),
        )

    def record(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "horizon_s": self.horizon_s,
            "entry_window_s": list(self.entry_window_s),
            "n_entered": self.n_entered,
        }
        if self.note is not None:
            out["note"] = self.note
        if self.has_tracers:
            out.update(
                {
                    "n_recovered": self.n_recovered,
                    "recovered_ok": self.recovered_ok,
                    "mean_residence_time_s": self.mean_residence_time_s.record(),
                    "rtd_variance_s2": self.rtd_variance_s2.record(),
                    "recovered_fraction": self.recovered_fraction.record(),
                    "bin_s": self.bin_s,
                }
            )
            if self.n_blocks is not None:
                out["n_blocks"] = self.n_blocks
        return out


#: the particle accounting's keys (:func:`dem.post.accounting`), kept together in ``accounting``:
#: these, and every key with one of :data:`ACCOUNTING_PREFIXES` (the solver's counters and
#: their differences, the discharge files', the dumps')
ACCOUNTING_KEYS = (
    "inserted",
    "held",
    "discharged",
    "lost",
    "accounting_mismatch",
    "discharged_pending_deletion",
    "discharge_crosscheck_diff",
)
ACCOUNTING_PREFIXES = ("solver_", "massflow_", "exits_", "dumps_")


def is_accounting(key: str) -> bool:
    return key in ACCOUNTING_KEYS or key.startswith(ACCOUNTING_PREFIXES)


@dataclass(frozen=True, kw_only=True)
class DemSummary(ProcessSummary):
    """The scalars of one DEM run's post-processing (units in the names). ``steady``: the
    steady-state statistics by quantity (:func:`dem.steady.steady_quantities`: an
    :class:`Estimate` record per quantity, the hold-up per slice, the outlet's particle
    numbers); ``pooled_rtd``: None for a run with no steady state; ``accounting``: the
    particle balance of dumps, discharge files and solver; ``rtd_*`` without ``pooled``:
    the paper's 1-s tag window.

    The quantities the PBM reports too are the fields of
    :class:`coupling.summary.ProcessSummary`, inherited rather than held in a member: a
    reader asks ``summary.steady_C_A`` of either side's summary alike, and a function that
    compares the sides takes two :class:`~coupling.summary.ProcessSummary`. The DEM's own
    fields add what only a finite sample has (the random-mixture floors, the tag window,
    the particle accounting, the intervals of ``steady`` and ``pooled_rtd``). Here
    ``steady_state_time_s`` is NaN, not None, when no steady state was found (as
    post-processing has always written it); :attr:`steady_time` reads both."""

    rtd_recovered_ok: bool = False
    rtd_tagged: int = 0
    rtd_tag_time_s: float | None = None
    rtd_tag_window_s: float | None = None
    steady_state_reached: bool = False
    final_rsd_outlet_floor: float = math.nan
    final_rsd_blender_floor: float = math.nan
    t_end_s: float = math.nan
    last_dump_step: int | None = None
    n_snapshots: int = 0
    steady: Mapping[str, Any] = field(default_factory=dict)
    pooled_rtd: PooledRtdSummary | None = None
    warnings: tuple[str, ...] = ()
    accounting: Mapping[str, Any] = field(default_factory=dict)
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def has_pooled_rtd(self) -> bool:
        return self.pooled_rtd is not None and self.pooled_rtd.has_tracers

    @classmethod
    def from_record(cls, record: Mapping[str, Any]) -> DemSummary:
        known = set(RECORD_SCALARS)
        scalars = {k: record[k] for k in known if k in record}
        return cls(
            **scalars,
            steady=dict(record.get("steady") or {}),
            pooled_rtd=PooledRtdSummary.from_record(record.get("pooled_rtd")),
            warnings=tuple(record.get("warnings") or ()),
            accounting={k: v for k, v in record.items() if k not in known and is_accounting(k)},
            extra={
                k: v
                for k, v in record.items()
                if k not in known and not is_accounting(k) and k not in ("steady", "pooled_rtd", "warnings")
            },
        )

    def record(self) -> dict[str, Any]:
        """The dict the cache and ``summary.json`` hold (keys as post-processing writes them)."""
        out = {name: getattr(self, name) for name in RECORD_SCALARS}
        out.update(self.accounting)
        out.update(
            {
                "steady": dict(self.steady),
                "pooled_rtd": None if self.pooled_rtd is None else self.pooled_rtd.record(),
                "warnings": list(self.warnings),
            }
        )
        out.update(self.extra)
        return out


#: the scalar keys of a DEM record, in the order post-processing writes them (the shared
#: fields among the DEM's own): :meth:`DemSummary.record` keeps it, so a record read and
#: written back is the same dict, key order included
RECORD_SCALARS: tuple[str, ...] = (
    "mean_residence_time_s",
    "rtd_variance_s2",
    "rtd_recovered_fraction",
    "rtd_recovered_ok",
    "rtd_tagged",
    "rtd_tag_time_s",
    "rtd_tag_window_s",
    "steady_state_time_s",
    "steady_state_reached",
    "steady_outflow_per_s",
    "steady_C_A",
    "final_rsd_outlet",
    "final_rsd_outlet_floor",
    "final_rsd_blender",
    "final_rsd_blender_floor",
    "holdup_final",
    "t_end_s",
    "last_dump_step",
    "n_snapshots",
)
