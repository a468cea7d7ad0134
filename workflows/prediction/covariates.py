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


def run_covariates(point: OperatingPoint, nx: int = AXIAL_SLICES) -> dict[str, float]:
    """The covariates of a run that are the same in every slice (their meaning:
    :mod:`workflows.prediction.library`)."""
    speed = math.log(point.impeller_rpm / REFERENCE_RPM)
    last = max(point.blade_x_m, default=0.0)
    return {
        "speed": speed,
        "length": math.log(point.length_m / nx / REFERENCE_SLICE_M),
        "feed": math.log(point.feed_rate_total_per_s / REFERENCE_FEED_PER_S),
        "speed2": speed**2,
        "gap": math.log(max(point.length_m - last, 1e-6) / REFERENCE_GAP_M),
    }
