"""The phase fit's settings: one frozen :class:`PhaseSettings` with one default per knob,
the product's (the post-processing's :func:`dem.phases.table_with_phases`); a study varies
them with :func:`dataclasses.replace`, and every value is checked when the object is made.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

from coupling.errors import ConfigError

#: The number of hidden phases the post-processing fits (:func:`dem.phases.table_with_phases`). On the
#: validation run's steady particles (10 axial slices, ``pbmdem study phases``) the held-out
#: log-likelihood per particle-step rose from -0.672 (K = 1) to -0.607 (K = 2) and -0.601
#: (K = 3), and the PBM's RTD variance from 172 to 238 and 258 s^2 against the DEM's 261
#: [244, 277]: K = 3 is the first inside the interval. K = 4 adds nothing (on the whole
#: validation baseline at a 0.2-s lag: 262.9 s^2 against K = 3's 262.4, K = 2's 231).
#: A fourth phase that is a dead zone (``stagnant_exit_max_per_s``, left at most
#: once per 2 Little's-law residence times; ``pbmdem study phases --ks 4 --stagnant 2``)
#: brings the pooled means of the reduced run, the validation baseline, feeds x0.5, x1.5,
#: x2 and 150 rpm inside, but holds 1-4 % too much at five of them (up to +20 % in a
#: slice): 13 of their 18 mean, variance and hold-up intervals against K = 3's 12. Not
#: adopted for one chain for every size; a chain per size class has one
#: (:data:`ZONE_RESIDENCES`).
PHASES = 3

#: The interval [s] between the observations the phases are fitted to: every 4th dump at
#: 0.1 s. Between consecutive dumps the particles flicker across slice boundaries with the
#: blades' stroke (a blade passes every 0.12 s at 250 rpm); a chain fitted to that flicker
#: reads it as fast exchange, which mixes the phases and takes dispersion away. Measured on
#: the whole validation baseline (K = 3, residents included; DEM: 21.27 s [20.72, 21.86],
#: 278 s^2 [259, 295], hold-up 1588 [1568, 1609]): fitted every 1, 2, 3, 4, 5, 10 dumps the
#: RTD variance is 250, 262, 265, 269, 266, 291 s^2 and the steady hold-up 1595, 1581, 1581,
#: 1586, 1596, 1784 (with the memoryless fit's bound on rate x interval, 2: at 1 s, 2 /s no
#: longer holds the fast lane); 0.4 s is inside all three intervals, every slice within 1.6 %, and the E-step,
#: which costs as the observations, is 4x cheaper than at every dump.
PHASE_LAG_S = 0.4

#: The phase fit's bound on rate x interval (the memoryless fit's is
#: :data:`dem.rates.MAX_RATE_X_INTERVAL` = 2: beyond it its likelihood is flat). A fast
#: phase does cross a compartment within the observation interval, and the bound then
#: holds the fast lane back, the more the finer the grid: on the validation baseline at
#: 0.4 s, K = 3, 20 slices gave a mean residence time of 26.5 s at a bound of 2, 22.3 s at
#: 6 and 22.1 s at 12, against 21.4-21.5 s on 10 slices at every bound (DEM 21.27 s). On
#: the shipped reduced run's 20-slice file (``pbmdem study phases --results
#: workflows/reference/dem-ac547c3f930c80c8.h5 --grids 20x1 --ks 3 --max-rate-x-interval B``):
#: 21.2 s and a hold-up of 2712 at B = 2, 18.3 s and 2331 at B = 12 (DEM 17.2 s, 2250).
PHASE_MAX_RATE_X_INTERVAL = 12.0

#: The post-processing's EM stops when an iteration gains less than this per particle-step
#: [nats]: fitted on to 1e-7, the K = 3 chain's pooled RTD moves by < 0.1 % in the mean
#: and < 1 % in the variance (17.53 s, 167 -> 166 s^2 on the shipped reduced run,
#: ``pbmdem study phases --grids 10x1 --ks 3 --starts 1 --tol 1e-7``). A stagnant phase
#: develops more slowly and needs the tighter stop (:attr:`PhaseSettings.stagnant_exit_max_per_s`).
PHASE_TOL = 1e-5


#: A chain per size class adds, beside its PHASES moving phases, a dead zone (the
#: stagnant phase 0) left at most once per this many Little's-law residence times of the
#: run (:func:`dem.phases.little_residence_time`), its size then held to the class's own Little's law
#: (:func:`dem.phases.zone_held_to_little`). Inside a class the zone no longer has to stand for the
#: small particles' whole slowness, as it did for one chain (above); it holds a class's
#: longest stays, which its moving phases leave too short (middle class of the reduced
#: run: 0.12 % of its tracers beyond the horizon against the DEM's 0.22 %). Pooled mean /
#: variance / steady hold-up against the DEM's 95 % intervals, per class without the zone
#: -> with it (``pbmdem study sizes``; the fresh baseline and the 300-rpm, feed x1.25 run
#: are not shipped): reduced run 17.49 -> 17.36 s [17.05, 17.39] / 169 -> 168 s^2 [160,
#: 171] / 2251 -> 2251 [2238, 2263]; feed x1.5 15.83 -> 15.65 s [15.32, 15.87] / 134 ->
#: 131 s^2 [119, 131] / 1766; 350 rpm 16.53 -> 16.46 s [16.09, 16.68] / 157 -> 158 s^2
#: [152, 170] / 1232 [1224, 1238]; a fresh validation baseline 21.25 -> 21.07 s [20.74,
#: 22.01] / 273 -> 270 s^2 [263, 309] / 1587 [1581, 1602]; 300 rpm x1.25 16.25 -> 16.09 s
#: [15.78, 16.26] / 144 -> 144 s^2 [136, 148] / 1509 [1494, 1521]: 15 of 15 inside
#: against 13. A zone left at most once per 2 residence times parks too long: more beyond
#: the horizon, and once held to Little's law too little inside it (the fresh baseline's
#: variance 258 s^2, out); once per half a residence time, the reduced mean is 17.42 s
#: (out). Without the hold, the zone came out 0.6 % too full (reduced hold-up 2265 at 2).
ZONE_RESIDENCES = 1.0


#: EM starts per fit: start 0 from the one-phase rates, the others drawn at random
#: (:class:`dem.phases.PhaseEstimator`); the post-processing's fit keeps the best of two.
PHASE_STARTS = 2
#: EM iterations at most per start (each one forward-backward and one M-step)
PHASE_MAX_ITERATIONS = 200
#: updates of the rates per M-step (:func:`dem.phases.estimator.ctmc_em_steps`, or L-BFGS
#: iterations with ``m_step = "lbfgs"``)
PHASE_M_STEP_ITERATIONS = 20
M_STEPS = ("em", "lbfgs")


def _whole(name: str, value, least: int) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < least:
        raise ConfigError(f"PhaseSettings.{name} = {value!r}: expected a whole number >= {least}")


def _positive(name: str, value, what: str, none_ok: bool = False) -> None:
    if value is None and none_ok:
        return
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (math.isfinite(value) and value > 0):
        raise ConfigError(
            f"PhaseSettings.{name} = {value!r}: expected {what}, finite and > 0" + (", or None" if none_ok else "")
        )


@dataclass(frozen=True)
class PhaseSettings:
    """Everything the phase fit takes besides its data, one default each (the product's).

    ``n_phases``: K, the hidden phases of the chain (with a stagnant phase, it is one of
    them); ``starts``: EM starts, the best kept; ``seed``: of the random starts;
    ``max_iterations``: EM iterations per start; ``tol`` [nats per particle-step]: stop
    when an iteration gains less; ``m_step``: ``"em"`` (a few EM updates of the
    continuous-time chain) or ``"lbfgs"`` (:func:`dem.rates.fit_pattern`);
    ``m_step_iterations``: updates (or L-BFGS iterations) per M-step;
    ``max_rate_x_interval``: the bound on every rate x the observation interval;
    ``refine``: model slices per observed slice (axial data, the sub-slice hidden beside
    the phase); ``stagnant_exit_max_per_s`` [1/s]: phase 0 is a dead zone left at this
    rate at most (None: every phase moves); ``lag_s`` [s]: the interval between the
    observations the data are prepared at (:meth:`lag_dumps`; the estimator fits the data
    it is given); ``zone_residences``: a chain per size class gets a dead zone left at
    most once per this many Little's-law residence times (None: no zone;
    :func:`dem.phases.table_with_phases`).

    Raises ConfigError naming the field, its value and the valid range."""

    n_phases: int = PHASES
    starts: int = PHASE_STARTS
    seed: int = 0
    max_iterations: int = PHASE_MAX_ITERATIONS
    tol: float = PHASE_TOL
    m_step: str = "em"
    m_step_iterations: int = PHASE_M_STEP_ITERATIONS
    max_rate_x_interval: float = PHASE_MAX_RATE_X_INTERVAL
    refine: int = 1
    stagnant_exit_max_per_s: float | None = None
    lag_s: float = PHASE_LAG_S
    zone_residences: float | None = ZONE_RESIDENCES

    def __post_init__(self) -> None:
        _whole("n_phases", self.n_phases, 1)
        _whole("starts", self.starts, 1)
        _whole("seed", self.seed, 0)
        _whole("max_iterations", self.max_iterations, 1)
        _positive("tol", self.tol, "a gain in nats per particle-step")
        if self.m_step not in M_STEPS:
            raise ConfigError(f"PhaseSettings.m_step = {self.m_step!r}: expected one of {', '.join(M_STEPS)}")
        _whole("m_step_iterations", self.m_step_iterations, 1)
        _positive("max_rate_x_interval", self.max_rate_x_interval, "a bound on rate x interval")
        _whole("refine", self.refine, 1)
        if self.refine > 1 and self.m_step != "em":
            raise ConfigError(f"PhaseSettings.refine = {self.refine}: expected 1 with m_step {self.m_step!r}")
        _positive("stagnant_exit_max_per_s", self.stagnant_exit_max_per_s, "a rate [1/s]", none_ok=True)
        if self.stagnant_exit_max_per_s is not None and (self.n_phases < 2 or self.refine > 1 or self.m_step != "em"):
            raise ConfigError(
                f"PhaseSettings.stagnant_exit_max_per_s = {self.stagnant_exit_max_per_s!r} with n_phases "
                f"{self.n_phases}, refine {self.refine}, m_step {self.m_step!r}: expected n_phases >= 2 (the "
                "stagnant phase and at least one that moves), refine 1 and m_step 'em'"
            )
        _positive("lag_s", self.lag_s, "an interval [s]")
        _positive("zone_residences", self.zone_residences, "a number of residence times", none_ok=True)

    @property
    def moving_phases(self) -> int:
        """The phases that move: all but a stagnant phase 0."""
        return self.n_phases - (self.stagnant_exit_max_per_s is not None)

    def lag_dumps(self, interval_s: float) -> int:
        """The observation interval :attr:`lag_s` in dumps of ``interval_s`` [s], at least one."""
        return max(1, round(self.lag_s / interval_s))
