"""The scalars both sides report, defined once: :class:`ProcessSummary`.

The DEM's post-processing (:class:`dem.summary.DemSummary`) and the PBM's run
(:class:`pbm.summary.PbmSummary`) each report these quantities of one blender run, under
these names and in these units; each side's summary type extends this one with what only
it knows. A comparison reads the fields named here, so it can only ever compare a
quantity with itself. ``coupling/DEFINITIONS.md`` ("Shared summary") says what each field
means and which function computes it on each side.

This module imports neither side: it is where they meet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields


@dataclass(frozen=True, kw_only=True)
class ProcessSummary:
    """One run's scalars that the DEM and the PBM both compute (units in the names).

    Keyword-only, so that a side's summary adds its own fields in any order; a field not
    computed is NaN (``steady_state_time_s``: NaN or None).

    ``mean_residence_time_s`` [s], ``rtd_variance_s2`` [s^2], ``rtd_recovered_fraction``
    [-]: the tagged RTD's mean and population variance over the tracer recovered by the
    end, and that tracer's share of the tracer fed. ``steady_state_time_s`` [s]: the first
    time the hold-up is steady by :class:`coupling.metrics.SteadyStateRule`, None or NaN
    when it never is. ``steady_outflow_per_s`` [particles/s] and ``steady_C_A`` [-]: the
    outflow and its flux-weighted A fraction from the steady state to the end.
    ``final_rsd_outlet``, ``final_rsd_blender`` [-]: :func:`coupling.metrics.rsd` at the
    end, across the last slice and across every compartment. ``holdup_final``
    [particles]: particles in the blender at the end.
    """

    mean_residence_time_s: float = math.nan
    rtd_variance_s2: float = math.nan
    rtd_recovered_fraction: float = math.nan
    steady_state_time_s: float | None = None
    steady_outflow_per_s: float = math.nan
    steady_C_A: float = math.nan
    final_rsd_outlet: float = math.nan
    final_rsd_blender: float = math.nan
    holdup_final: float = math.nan

    @property
    def steady_time(self) -> float | None:
        """The steady-state time [s] when the run reached one (finite), else None: the one
        reading of ``steady_state_time_s`` whichever way a side marks "never steady"."""
        t = self.steady_state_time_s
        return float(t) if t is not None and math.isfinite(t) else None

    def shared(self) -> ProcessSummary:
        """These fields alone, as a :class:`ProcessSummary` (what a comparison needs)."""
        return ProcessSummary(**{name: getattr(self, name) for name in SHARED_FIELDS})


#: the names of the shared fields, in their order
SHARED_FIELDS: tuple[str, ...] = tuple(f.name for f in fields(ProcessSummary))
