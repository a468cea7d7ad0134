"""The PBM run's scalars as a typed object: :class:`PbmSummary`.

:func:`pbm.simulate.simulate` builds it and every reader uses its fields;
:meth:`PbmSummary.record` is the dict written at the file edge (``pbm/summary.json``, the
comparison's ``summary.json``), with the keys, order and value types the PBM has always
written.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from coupling.summary import ProcessSummary


@dataclass(frozen=True, kw_only=True)
class PbmSummary(ProcessSummary):
    """The scalars of one PBM run (:func:`pbm.simulate.simulate`), units in the names.

    The shared fields (:class:`coupling.summary.ProcessSummary`) are inherited, as the
    DEM's summary inherits them, so the two sides are read alike. On this side: the RTD
    moments are exact over the tracer recovered by the end; ``steady_state_time_s`` is None
    when no steady state is detected, and then ``steady_outflow_per_s`` and ``steady_C_A``
    are the means over the last steady window.

    PBM-only: ``final_rsd_by_slice`` (NX,) the RSD across each axial slice at the end,
    inlet -> outlet, NaN where undefined; ``holdup_final_A``, ``holdup_final_B``
    [particles]; ``rtd_pulse_s`` [s] the tracer pulse time and ``rtd_pulse_rule`` why it
    was fed then; ``filled_compartment_windows``: compartment-windows of the fields
    ``config.rates`` reads that were filled; ``nx``, ``ny`` the grid; ``duration_s`` [s]
    the simulated time; ``method`` (the solver), ``rate_law``, and under the fill law its
    ``fill_law_form`` and ``fill_exponents`` (None otherwise); ``wall_time_s`` [s] the
    run's wall time.
    """

    final_rsd_by_slice: tuple[float, ...]
    holdup_final_A: float
    holdup_final_B: float
    rtd_pulse_s: float
    rtd_pulse_rule: str
    filled_compartment_windows: int
    nx: int
    ny: int
    duration_s: float
    method: str
    rate_law: str
    fill_law_form: str | None = None
    fill_exponents: tuple | None = None
    wall_time_s: float = 0.0

    def record(self) -> dict[str, Any]:
        """The JSON-ready dict: :data:`RECORD_KEYS` in order, lists where the fields hold
        tuples."""
        out = {name: getattr(self, name) for name in RECORD_KEYS}
        out["final_rsd_by_slice"] = list(self.final_rsd_by_slice)
        out["fill_exponents"] = None if self.fill_exponents is None else _lists(self.fill_exponents)
        return out


def nested_tuples(value: Any) -> Any:
    """A nested list (``numpy.ndarray.tolist()``) as nested tuples, for a frozen field."""
    return tuple(nested_tuples(v) for v in value) if isinstance(value, list | tuple) else value


def _lists(value: Any) -> Any:
    return [_lists(v) for v in value] if isinstance(value, tuple) else value


#: the keys of :meth:`PbmSummary.record`, in the order the PBM writes them
RECORD_KEYS: tuple[str, ...] = (
    "mean_residence_time_s",
    "rtd_variance_s2",
    "rtd_recovered_fraction",
    "steady_outflow_per_s",
    "steady_C_A",
    "final_rsd_outlet",
    "final_rsd_blender",
    "final_rsd_by_slice",
    "holdup_final",
    "holdup_final_A",
    "holdup_final_B",
    "steady_state_time_s",
    "rtd_pulse_s",
    "rtd_pulse_rule",
    "filled_compartment_windows",
    "nx",
    "ny",
    "duration_s",
    "method",
    "rate_law",
    "fill_law_form",
    "fill_exponents",
    "wall_time_s",
)
