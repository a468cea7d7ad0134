"""The covariates of an operating point that are the same along the whole blender: what
the library's law (:mod:`workflows.prediction.library`), its correction and the slices'
zone law (:mod:`workflows.prediction.profile`) read of a run, each as the log of its ratio
to the library's baseline."""

from __future__ import annotations

import math

from coupling.operating import OperatingPoint

#: the library's baseline: the validation preset's speed, slice length (0.33 m over 10
#: slices) and total feed [rpm, m, particles/s]
REFERENCE_RPM = 250.0
REFERENCE_SLICE_M = 0.033
REFERENCE_FEED_PER_S = 73.7
#: the baseline's gap from its last blade station to the weir [m]
REFERENCE_GAP_M = 0.03
#: the axial grid the law is fitted on (the product's phase model is axial)
AXIAL_SLICES = 10


#: each axis of the library's domain: the value its covariate 0 stands for, and the unit
#: a user gives it in
AXIS_REFERENCES = {
    "speed": (REFERENCE_RPM, "rpm"),
    "length": (REFERENCE_SLICE_M * AXIAL_SLICES, "m"),
    "feed": (REFERENCE_FEED_PER_S, "particles/s"),
}


def axis_value(axis: str, covariate: float) -> float:
    """The value of ``axis`` (:data:`AXIS_REFERENCES`) whose covariate is ``covariate``."""
    return AXIS_REFERENCES[axis][0] * math.exp(covariate)


def weir_gap_m(point: OperatingPoint) -> float:
    """The gap from ``point``'s last blade station to the weir [m] (the whole barrel
    without a station)."""
    return point.length_m - max(point.blade_x_m, default=0.0)


def run_covariates(point: OperatingPoint, nx: int = AXIAL_SLICES) -> dict[str, float]:
    """The covariates of a run that are the same in every slice (their meaning:
    :mod:`workflows.prediction.library`)."""
    speed = math.log(point.impeller_rpm / REFERENCE_RPM)
    return {
        "speed": speed,
        "length": math.log(point.length_m / nx / REFERENCE_SLICE_M),
        "feed": math.log(point.feed_rate_total_per_s / REFERENCE_FEED_PER_S),
        "speed2": speed**2,
        "gap": math.log(max(weir_gap_m(point), 1e-6) / REFERENCE_GAP_M),
    }
