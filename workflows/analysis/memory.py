"""Is the fitted transport Markov? The phase model of a DEM run checked against the DEM's
own particle sequences, beside the memoryless chain (K = 1) fitted to the same particles.

The model the post-processing fitted (:func:`dem.phases.table_with_phases`) lumps exactly
onto the axial slices, so it is tested there, on the particles that entered during the
steady period and the moves of those already inside then (the data it was fitted to):

* the Chapman-Kolmogorov test (:func:`dem.phases.chapman_kolmogorov`): from each slice,
  the observed fraction of particles in every slice, and discharged, after 1, 2, 5 and
  10 s against the model's probability; a Markov model of the data passes at every lag;
* the implied timescales of each chain;
* the log-likelihood per particle-step of each chain on those particles.

Out of sample (:func:`out_of_sample`): the pooled RTD's entry window split at its middle;
the phase model refitted to the particles that entered in the first half (and those inside
when it opened), followed as long as the run follows them, predicts the pooled RTD of the
other particles, those that entered in the second half, judged against the DEM's 95 %
intervals of that RTD (the same block bootstrap as the whole run's,
:func:`dem.steady.pooled_rtd`). The DEM's RTD of the first half's particles is reported
beside it: where the run itself moved between its halves, a stationary model fitted to the
first cannot follow.

The held-out choice of K (score of the second half under a fit on the first) and the grids
are the phase study's (``pbmdem study phases``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from coupling import phases as phase_model
from dem import phases
from dem.phases import CkTest
from dem.post import DemResults, sequence_diameters
from dem.steady import pooled_rtd as dem_pooled_rtd
from dem.summary import Estimate, PooledRtdSummary
from pbm.config import PbmConfig
from pbm.rtd import pooled_rtd

#: the CK lags [dumps at 0.1 s: 1, 2, 5 and 10 s]
LAG_SECONDS = (1.0, 2.0, 5.0, 10.0)


@dataclass(frozen=True)
class ChainCheck:
    """One chain on the slices: K phases, its CK test, its implied timescales [s] and its
    log-likelihood per particle-step [nats] on the fitted particles."""

    n_phases: int
    ck: CkTest
    timescales_s: tuple[float, ...]
    log_likelihood_per_step: float

    def record(self) -> dict[str, Any]:
        return {
            "n_phases": self.n_phases,
            "ck_lags_s": self.ck.lags_s.tolist(),
            "ck_max_z": self.ck.max_z(),
            "ck_max_abs_error": self.ck.max_abs_error(),
            "ck_passed": self.ck.passed,
            "ck_z_limit": self.ck.z_limit,
            "ck_observed": self.ck.observed.tolist(),
            "ck_predicted": self.ck.predicted.tolist(),
            "implied_timescales_s": list(self.timescales_s),
            "log_likelihood_per_step": self.log_likelihood_per_step,
        }


class _JudgedRtd:
    """The verdicts of a PBM's pooled RTD (``pbm_mean_s``, ``pbm_variance_s2``) against the
    DEM's intervals (``dem_mean_s``, ``dem_variance_s2``)."""

    @property
    def mean_inside(self) -> bool:
        return bool(self.dem_mean_s.low <= self.pbm_mean_s <= self.dem_mean_s.high)

    @property
    def variance_inside(self) -> bool:
        return bool(self.dem_variance_s2.low <= self.pbm_variance_s2 <= self.dem_variance_s2.high)

    def judged_record(self) -> dict[str, Any]:
        """Both sides' mean and variance and the verdicts, as the summary keeps them."""
        return {
            "dem_mean_s": self.dem_mean_s.record(),
            "dem_variance_s2": self.dem_variance_s2.record(),
            "pbm_mean_s": self.pbm_mean_s,
            "pbm_variance_s2": self.pbm_variance_s2,
            "mean_inside": self.mean_inside,
            "variance_inside": self.variance_inside,
        }


@dataclass(frozen=True)
class OutOfSample(_JudgedRtd):
    """The pooled RTD of the particles that entered in ``entry_window_s`` (the second half
    of the steady period): the DEM's, with its intervals, and the PBM's (mode "phases")
    on a model fitted to the particles of ``fit_window_s`` alone."""

    fit_window_s: tuple[float, float]
    entry_window_s: tuple[float, float]
    horizon_s: float
    n_entered: int
    dem_mean_s: Estimate
    dem_variance_s2: Estimate
    pbm_mean_s: float
    pbm_variance_s2: float
    # the DEM's pooled RTD of the particles that entered in the fit window, followed for the
    # same horizon: how far the run itself moved between its halves, which a stationary
    # model fitted to the first cannot follow
    dem_fit_half_mean_s: Estimate | None = None
    dem_fit_half_variance_s2: Estimate | None = None
    #: phases of each kind of the refit: the same structure as the run's own model
    refit_phases_per_kind: int | None = None

    @property
    def mean_within_halves_noise(self) -> bool | None:
        return _within_halves_noise(self.pbm_mean_s, self.dem_mean_s, self.dem_fit_half_mean_s)

    @property
    def variance_within_halves_noise(self) -> bool | None:
        return _within_halves_noise(self.pbm_variance_s2, self.dem_variance_s2, self.dem_fit_half_variance_s2)

    def record(self) -> dict[str, Any]:
        fit_half = {}
        if self.dem_fit_half_mean_s is not None and self.dem_fit_half_variance_s2 is not None:
            fit_half = {
                "dem_fit_half_mean_s": self.dem_fit_half_mean_s.record(),
                "dem_fit_half_variance_s2": self.dem_fit_half_variance_s2.record(),
            }
        return {
            "fit_window_s": list(self.fit_window_s),
            "entry_window_s": list(self.entry_window_s),
            "horizon_s": self.horizon_s,
            "n_entered": self.n_entered,
            "refit_phases_per_kind": self.refit_phases_per_kind,
            "mean_within_halves_noise": self.mean_within_halves_noise,
            "variance_within_halves_noise": self.variance_within_halves_noise,
            **self.judged_record(),
            **fit_half,
        }


def _within_halves_noise(pbm: float, second: Estimate, first: Estimate | None) -> bool | None:
    """Whether a refit on the first half misses the second half's value by no more than the
    two halves' 95 % half-widths combined (the refit carries the first half's sampling
    noise, the DEM's value the second's); None without the first half's estimate. Beside
    the verdict, not instead of it: it says whether a miss is one the DEM can resolve."""
    if first is None:
        return None
    half = [(e.high - e.low) / 2 for e in (first, second)]
    return bool(abs(pbm - second.value) <= math.hypot(*half))


@dataclass(frozen=True)
class SizeRtd(_JudgedRtd):
    """One size class of a chain per size class: its particles' mean diameter [m], their
    share of the pooled RTD's tracers, the DEM's pooled RTD of them (mean [s], variance
    [s²], the share still inside at the horizon) and the class's own chain's."""

    diameter_m: float
    share: float
    n_entered: int
    dem_mean_s: Estimate
    dem_variance_s2: Estimate
    dem_beyond: float
    pbm_mean_s: float
    pbm_variance_s2: float
    pbm_beyond: float

    def record(self) -> dict[str, Any]:
        return {
            "diameter_m": self.diameter_m,
            "share": self.share,
            "n_entered": self.n_entered,
            "dem_beyond_horizon": self.dem_beyond,
            "pbm_beyond_horizon": self.pbm_beyond,
            **self.judged_record(),
        }


def rtd_by_size(results: DemResults, table, pbm_config: PbmConfig, diameters: np.ndarray) -> tuple[SizeRtd, ...]:
    """:class:`SizeRtd` of every size class of ``table``'s chain per size class (fitted by
    :func:`dem.phases.table_with_phases` with ``diameters``, one per sequence): the classes
    as that fit made them, the DEM's pooled RTD of each class's particles over the run's
    entry window and horizon, the class's chain fed alone. () for a table of one chain."""
    model = table.phases
    if model is None or not model.attrs.get("diameters_m"):
        return ()
    summary, sequences, records = results.summary, results.sequences, results.particles
    spec = summary.pooled_rtd
    t_ss, t_end = float(summary.steady_time), float(sequences.snapshot_t[-1])
    little = float(summary.steady["little_mean_residence_time_s"]["value"])
    window = phases.steady_window(sequences, t_ss)
    members = phases.kinds_by_size(sequences, diameters, window)
    entry_t = records["entry_t_s"].to_numpy(float)
    tracers = (entry_t > spec.entry_window_s[0]) & (entry_t <= spec.entry_window_s[1])
    config = pbm_config.model_copy(update={"rates": "phases", "rtd_pulse_s": None})
    out = []
    for rows, kind in zip(members, phase_model.kinds(model)):
        mine = records["id"].isin(sequences.ids[rows]).to_numpy()
        dem = dem_pooled_rtd(records[mine], t_ss, t_end, little, float(table.window_s))
        pbm = pooled_rtd(table.replace(phases=kind), config, tuple(spec.entry_window_s), spec.horizon_s)
        out.append(
            SizeRtd(
                float(np.nanmean(diameters[rows])),
                float((mine & tracers).sum() / max(tracers.sum(), 1)),
                int(dem["n_entered"]),
                Estimate.from_record(dem["mean_residence_time_s"]),
                Estimate.from_record(dem["rtd_variance_s2"]),
                1.0 - float(dem["recovered_fraction"]["value"]),
                float(pbm.mean_s),
                float(pbm.variance_s2),
                1.0 - float(pbm.recovered_fraction),
            )
        )
    return tuple(out)


@dataclass(frozen=True)
class MemoryCheck:
    """The memoryless chain and the phase model, each checked (module docstring), and the
    out-of-sample prediction (None when the run is too short for one)."""

    chains: tuple[ChainCheck, ...]
    fit_window_s: tuple[float, float]
    n_particles: int
    n_steps: int
    out_of_sample: OutOfSample | None = None
    out_of_sample_note: str = ""
    by_size: tuple[SizeRtd, ...] = ()

    def record(self) -> dict[str, Any]:
        return {
            "fit_window_s": list(self.fit_window_s),
            "n_particles": self.n_particles,
            "n_steps": self.n_steps,
            "chains": [c.record() for c in self.chains],
            "out_of_sample": None if self.out_of_sample is None else self.out_of_sample.record(),
            "out_of_sample_note": self.out_of_sample_note,
            "by_size": [s.record() for s in self.by_size],
        }


def memory_check(results: DemResults, pbm_config: PbmConfig) -> MemoryCheck | None:
    """:class:`MemoryCheck` of the DEM results' phase model (``pbm_config``: the PBM of the
    same process, for the out-of-sample RTD); None when the table carries none (no steady
    state, or results made before the compartment sequences)."""
    table, sequences = results.table, results.sequences
    if not table.has_phases or sequences is None:
        return None
    window = phases.steady_window(sequences, results.summary.steady_time)
    grid = (sequences.nx, 1)
    data = phases.prepare(sequences, window, grid=grid, residents=True)
    lags = tuple(max(1, round(s / data.interval_s)) for s in LAG_SECONDS)
    fit_lag = max(1, round(phases.PHASE_LAG_S / data.interval_s))  # the phase model's observations
    memoryless = phases.one_phase(phases.prepare(sequences, window, grid=grid, lag=fit_lag, residents=True))
    chains = []
    for model in (memoryless, phases.axial_part(table.phases)):
        fit = phases.PhaseFit(model, float("nan"), data.n_particles, data.n_steps, 0, True)
        chains.append(
            ChainCheck(
                model.n_phases,
                fit.chapman_kolmogorov(data, lags),
                tuple(float(t) for t in fit.implied_timescales(3)),
                fit.score(data) / max(data.n_steps, 1),
            )
        )
    try:
        held_out, note = out_of_sample(results, pbm_config), ""
    except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:  # too few particles in a half
        held_out, note = None, f"no out-of-sample check: {exc}"
    diameters = sequence_diameters(sequences, results.particles)
    sizes = () if diameters is None else rtd_by_size(results, table, pbm_config, diameters)
    return MemoryCheck(tuple(chains), window, data.n_particles, data.n_steps, held_out, note, sizes)


def out_of_sample(results: DemResults, pbm_config: PbmConfig) -> OutOfSample:
    """:class:`OutOfSample` (module docstring). Raises ValueError when the second half of
    the steady period leaves no entry window for the pooled RTD's horizon, or the first
    half holds too few particles to fit."""
    summary, table = results.summary, results.table
    spec: PooledRtdSummary | None = summary.pooled_rtd
    t_ss, t_end = summary.steady_time, float(results.sequences.snapshot_t[-1])
    if t_ss is None or spec is None or not summary.has_pooled_rtd:
        raise ValueError("the run has no pooled RTD to split")
    mid = 0.5 * (t_ss + spec.entry_window_s[1])  # the halves of the whole run's entry window
    little = float(summary.steady["little_mean_residence_time_s"]["value"])
    dem = dem_pooled_rtd(results.particles, mid, t_end, little, float(table.window_s))
    if not dem.get("n_entered"):
        raise ValueError(dem.get("note", "no particle entered in the second half"))
    refit, _fits = phases.table_with_phases(
        table,
        results.sequences,
        t_ss,
        phases.moving_phases(table.phases),
        entered_s=(float(t_ss), float(mid)),
        diameters=sequence_diameters(results.sequences, results.particles),
    )
    config = pbm_config.model_copy(update={"rates": "phases", "rtd_pulse_s": None})
    pbm = pooled_rtd(refit, config, tuple(dem["entry_window_s"]), dem["horizon_s"])
    if not (math.isfinite(pbm.mean_s) and math.isfinite(pbm.variance_s2)):
        raise ValueError("the PBM recovered no tracer within the horizon")
    fit_half = dem_pooled_rtd(results.particles, t_ss, mid + float(dem["horizon_s"]), little, float(table.window_s))
    has_fit_half = bool(fit_half.get("n_entered"))
    return OutOfSample(
        (float(t_ss), float(mid)),
        tuple(float(v) for v in dem["entry_window_s"]),
        float(dem["horizon_s"]),
        int(dem["n_entered"]),
        Estimate.from_record(dem["mean_residence_time_s"]),
        Estimate.from_record(dem["rtd_variance_s2"]),
        float(pbm.mean_s),
        float(pbm.variance_s2),
        Estimate.from_record(fit_half["mean_residence_time_s"]) if has_fit_half else None,
        Estimate.from_record(fit_half["rtd_variance_s2"]) if has_fit_half else None,
        phases.phases_per_kind(refit.phases),
    )
