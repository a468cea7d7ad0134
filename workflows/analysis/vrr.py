"""Feeder-noise filtering, PBM against DEM, with the DEM's interval: ``python -m workflows.analysis.vrr``.

For a stationary blender the outlet flux of one feeder's particles is that feeder's rate
convolved with their residence-time distribution E(t), so the DEM's pooled RTD predicts
the transfer function H(f) and the variance reduction ratio VRR(f) = 1 / |H(f)|^2 that
:mod:`pbm.frequency` computes from the PBM's generator (see that module for the
derivation). Here:

* :func:`dem_transfer` -- the DEM's H(f) for the particles of one feeder (component A or
  B of :func:`dem.post.particle_records`): the mean of exp(-i 2 pi f tau) over the
  particles of the pooled RTD (entered in the entry window, recovered within the horizon
  H, :func:`coupling.metrics.rtd_pooled`). It is conditional on recovery, as the pooled
  RTD is, so H(0) = 1 exactly; the reduced run recovers 99.8 %, and a tail beyond H
  (>= 5 mean residence times) moves H by at most the unrecovered share. The 95 % intervals
  of |H| and VRR (and of the noise VRRs) are a block bootstrap over entry time
  (:func:`coupling.intervals.block_bootstrap`, 5-s blocks, 2000 replicates, seeded, the
  ends expanded for the number of blocks), as for the pooled RTD's mean in :mod:`dem.steady`.
* the sampling floor: a mean of N unit phasors with unrelated phases has |H| ~ 1/sqrt(N)
  (E|H_hat|^2 = |H|^2 + (1 - |H|^2) / N for independent particles), so above a few times
  1 / mean residence time the DEM's |H| is noise, and its VRR saturates at ~N. Frequencies
  where the DEM's |H| is below :data:`RESOLVED_FACTOR` x 1/sqrt(N) are marked unresolved
  and not judged. At that threshold the floor still inflates |H|^2 by ~1/9 (VRR low by
  ~10 %), which the percentile interval does not remove: the judged points nearest the
  floor lean towards the PBM looking too filtering.
* :func:`vrr_comparison` -- a :class:`VrrComparison`: each PBM rate mode's stationary system over the steady windows
  (:func:`pbm.frequency.stationary_system`) against the DEM, per feeder and frequency, and
  for band-limited feeder noise (white and first order, :data:`NOISE_TAUS_S`), the DEM's
  noise VRR by the same quadrature of S(f) |H_DEM(f)|^2 (:func:`pbm.frequency.vrr_spectrum`),
  with |H_DEM|^2 corrected for the floor's expected (1 - |H|^2)/N: the band reaches the
  floor, and uncorrected the DEM's noise VRR reads low by ~f_max / (N int S|H|^2) (0.3 %
  for white noise on the reduced run; the plain value is kept as ``uncorrected``).
  The result is typed (:class:`PbmVrr` per rate mode, :class:`FeederVrr` per feeder,
  :class:`NoiseVrr` per noise, :class:`RatioPoint` per judged point, :class:`EnsembleCheck`
  per noise level); ``record()`` gives the nested dict that ``vrr.json`` and the
  comparison's ``summary.json`` hold, and only the file writers call it.

:func:`workflows.report.vrr.plot_vrr`, ``vrr_html`` and ``print_table`` render the result;
``pbmdem study vrr`` (:mod:`workflows.studies.vrr`) runs it on a DEM results file.

Time resolution: entry times are first sightings in the dumps (0.1 s apart on the reduced
run), which delays each entry by up to one dump interval: a phase shift and a magnitude
factor sinc(f dt) >= 0.98 at 1 Hz, where |H_DEM| is at its floor anyway.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd

from coupling.blas import single_threaded_blas
from coupling.errors import ConfigError
from coupling.intervals import (
    LEVEL,
    N_BOOT,
    SEED,
    Interval,
    block_draw_counts,
    expanded_interval,
    inside,
    percentile_interval,
    time_blocks,
)
from coupling.metrics import rtd_pooled
from coupling.tables import RATE_NAMES, VELOCITY_NAMES, VelocityTable
from dem.summary import DemSummary, PooledRtdSummary
from pbm.config import PbmConfig
from pbm.ensemble import noise_ensemble
from pbm.feed import resolve_feed
from pbm.frequency import (
    FEEDERS,
    NOISE_TAUS_S,
    noise_frequencies,
    noise_spectrum,
    sampled_ca_sd,
    stationary_system,
    system_response,
    vrr_sinusoid,
    vrr_spectrum,
)
from pbm.model import filled_table, supported_modes

#: particle_records' component codes of the two feeders (3, "other", feeds neither)
COMPONENT_CODES = {"A": 1, "B": 2}
#: entry-time blocks of the bootstrap: one velocity window, as every DEM interval
BLOCK_S = 5.0
#: a DEM |H| below this many sampling floors 1/sqrt(N) is unresolved and not judged
RESOLVED_FACTOR = 3.0
#: quadrature points of the noise VRR (as :func:`pbm.frequency.vrr_noise`)
QUADRATURE_POINTS = 2001
#: The time-domain cross-check: members (the superposition path's cost hardly depends on
#: them; the SD of an SD estimate is ~1.6 % at 2000) and the feeder noise levels.
ENSEMBLE_MEMBERS = 2000
ENSEMBLE_SIGMAS = (0.1,)
#: frequencies of the phasor sums evaluated at once: bounds the (N, chunk) cos/sin arrays
#: to ~20 MB for the ~8500 particles of a feeder of the reduced run
_CHUNK = 256


@dataclass(frozen=True)
class DemTransfer:
    """The DEM's transfer function of one feeder (:func:`dem_transfer`).

    ``H`` the complex estimate at ``frequency_hz``; ``abs_H`` and ``vrr`` :class:`Interval`
    (estimate, low, high) arrays; ``floor`` = 1/sqrt(n_recovered), the |H| of pure sampling
    noise; ``resolved`` where |H| >= RESOLVED_FACTOR x floor; ``noise``: per correlation
    time tau_s the noise VRR as an Interval, from |H|^2 with the floor's expected share
    removed (:func:`_floor_corrected`, in the estimate and in every replicate);
    ``noise_uncorrected`` the plain quadrature of |H_hat|^2 (how much the floor biases it).
    """

    component: str
    frequency_hz: np.ndarray
    H: np.ndarray
    abs_H: Interval
    vrr: Interval
    n_entered: int
    n_recovered: int
    n_blocks: int
    mean_residence_time_s: float
    floor: float
    resolved: np.ndarray
    noise_taus_s: tuple[float, ...] = ()
    noise_f_max_hz: float = math.nan
    noise: tuple[Interval, ...] = ()
    noise_uncorrected: tuple[float, ...] = field(default=())

    @property
    def recovered_fraction(self) -> float:
        """Recovered within the horizon / entered in the window (NaN when none entered)."""
        return self.n_recovered / self.n_entered if self.n_entered else math.nan

    def record(self) -> dict[str, Any]:
        """The feeder's entry of ``vrr.json``'s ``dem``: counts, floor, resolved mask,
        |H| and VRR as value/low/high, and the noise VRRs with their uncorrected values."""
        return {
            "n_entered": self.n_entered,
            "n_recovered": self.n_recovered,
            "n_blocks": self.n_blocks,
            "recovered_fraction": self.recovered_fraction,
            "mean_residence_time_s": self.mean_residence_time_s,
            "floor_abs_H": self.floor,
            "resolved": self.resolved,
            "abs_H": _interval_dict(self.abs_H),
            "vrr": _interval_dict(self.vrr),
            "noise": [
                {"tau_s": t, **_interval_dict(iv), "uncorrected": c}
                for t, iv, c in zip(self.noise_taus_s, self.noise, self.noise_uncorrected)
            ],
        }


@dataclass(frozen=True)
class NoiseVrr:
    """One PBM rate mode's VRR of band-limited first-order noise of correlation time
    ``tau_s`` (0 = white) for one feeder, against the DEM's interval ``dem``."""

    tau_s: float
    vrr: float
    dem: Interval

    @property
    def inside(self) -> bool:
        """Whether the PBM's noise VRR lies in the DEM's interval."""
        return bool(inside(self.vrr, self.dem.low, self.dem.high))

    @property
    def ratio_to_dem(self) -> float:
        """PBM / DEM estimate."""
        return self.vrr / self.dem.estimate

    def record(self) -> dict[str, Any]:
        return {
            "tau_s": self.tau_s,
            "vrr": self.vrr,
            "dem": _interval_dict(self.dem),
            "inside": self.inside,
            "ratio_to_dem": self.ratio_to_dem,
        }


@dataclass(frozen=True)
class FeederVrr:
    """One PBM rate mode's filtering of one feeder: |H| and the sinusoid VRR at the
    comparison's frequencies, whether each VRR lies in the DEM's interval (None where the
    DEM is unresolved: not judged), the noise VRRs, and the steady mean residence time [s]."""

    feeder: str
    mean_residence_time_s: float
    abs_H: np.ndarray
    vrr: np.ndarray
    inside: tuple[bool | None, ...]
    noise: tuple[NoiseVrr, ...] = ()

    def record(self) -> dict[str, Any]:
        return {
            "mean_residence_time_s": self.mean_residence_time_s,
            "abs_H": self.abs_H,
            "vrr": self.vrr,
            "inside": list(self.inside),
            "noise": [n.record() for n in self.noise],
        }


@dataclass(frozen=True)
class RatioPoint:
    """One judged (DEM-resolved) point: PBM / DEM VRR at ``frequency_hz`` [Hz] for
    ``feeder``, and whether the PBM's VRR lies in the DEM's interval."""

    ratio_pbm_to_dem: float
    feeder: str
    frequency_hz: float
    inside: bool

    def record(self) -> dict[str, Any]:
        return {"ratio_pbm_to_dem": self.ratio_pbm_to_dem, "feeder": self.feeder, "frequency_hz": self.frequency_hz}


def _worst(points: Sequence[RatioPoint]) -> RatioPoint | None:
    """The point farthest from 1 on a log scale: a factor 2 too high is as bad as a factor 2
    too low (the first of equals; None for no points)."""
    return max(points, key=lambda p: abs(math.log(p.ratio_pbm_to_dem)), default=None)


@dataclass(frozen=True)
class EnsembleCheck:
    """The time-domain noise ensemble against the frequency domain at one noise level
    (:func:`ensemble_check`): SDs of the outlet C_A, ``from_s`` the start of the averaged
    outputs [s], ``ensemble_s`` the ensemble's wall time [s]."""

    sigma: float
    members: int
    from_s: float
    sd_time_domain: float
    sd_frequency_domain: float
    ensemble_s: float

    @property
    def relative_difference(self) -> float:
        """time domain / frequency domain - 1."""
        return self.sd_time_domain / self.sd_frequency_domain - 1

    def record(self) -> dict[str, Any]:
        return {
            "sigma": self.sigma,
            "members": self.members,
            "from_s": self.from_s,
            "sd_time_domain": self.sd_time_domain,
            "sd_frequency_domain": self.sd_frequency_domain,
            "relative_difference": self.relative_difference,
            "ensemble_s": self.ensemble_s,
        }


@dataclass(frozen=True)
class PbmVrr:
    """One PBM rate mode against the DEM (:func:`vrr_comparison`): per feeder
    (:class:`FeederVrr`), the first and last table window averaged, every judged point
    (:class:`RatioPoint`, feeders in :data:`pbm.frequency.FEEDERS` order, frequencies
    ascending) and the time-domain cross-check."""

    mode: str
    feeders: Mapping[str, FeederVrr]
    windows_averaged: tuple[int, int]
    points: tuple[RatioPoint, ...] = ()
    ensemble_check: tuple[EnsembleCheck, ...] = ()

    @property
    def n_judged(self) -> int:
        """Points where the DEM is resolved."""
        return len(self.points)

    @property
    def n_inside(self) -> int:
        """Judged points whose PBM VRR lies in the DEM's interval."""
        return sum(p.inside for p in self.points)

    @property
    def inside_fraction(self) -> float:
        return self.n_inside / self.n_judged if self.n_judged else math.nan

    @property
    def worst(self) -> RatioPoint | None:
        """The judged point farthest from the DEM (log scale). Near the floor the DEM's
        interval spans a factor of ~5, so this is often an inside point."""
        return _worst(self.points)

    @property
    def worst_outside(self) -> RatioPoint | None:
        """The worst point outside the DEM's interval: how far a miss is."""
        return _worst([p for p in self.points if not p.inside])

    def record(self) -> dict[str, Any]:
        worst, worst_outside = self.worst, self.worst_outside
        return {
            "feeders": {f: fv.record() for f, fv in self.feeders.items()},
            "windows_averaged": list(self.windows_averaged),
            "n_judged": self.n_judged,
            "n_inside": self.n_inside,
            "inside_fraction": self.inside_fraction,
            "worst": None if worst is None else worst.record(),
            "worst_outside": None if worst_outside is None else worst_outside.record(),
            "ensemble_check": [row.record() for row in self.ensemble_check],
        }


@dataclass(frozen=True)
class VrrComparison:
    """PBM against DEM feeder-noise filtering (:func:`vrr_comparison`): the frequencies
    [Hz], the steady time [s] from which the PBM's windows are averaged, the noise band and
    the DEM's bootstrap settings, the DEM per feeder (:class:`DemTransfer`) and each PBM
    rate mode (:class:`PbmVrr`). :meth:`record` is the JSON edge."""

    frequency_hz: np.ndarray
    steady_time_s: float
    dem: Mapping[str, DemTransfer]
    pbm: Mapping[str, PbmVrr]
    noise_taus_s: tuple[float, ...] = ()
    noise_f_max_hz: float = math.nan
    quadrature_points: int = QUADRATURE_POINTS
    block_s: float = BLOCK_S
    n_boot: int = N_BOOT
    level: float = LEVEL
    seed: int = SEED
    resolved_factor: float = RESOLVED_FACTOR

    @property
    def note(self) -> str:
        return (
            "DEM H(f) is the mean of exp(-i 2 pi f tau) over the pooled RTD's recovered particles of each "
            "feeder (conditional on recovery within the horizon); frequencies where the DEM's |H| is below "
            f"{self.resolved_factor:g} x 1/sqrt(N) are unresolved (sampling floor) and not judged."
        )

    def record(self) -> dict[str, Any]:
        """The comparison as ``vrr.json`` and ``summary.json``'s ``vrr`` hold it (numpy
        arrays left for the JSON writer)."""
        return {
            "frequency_hz": self.frequency_hz,
            "steady_time_s": self.steady_time_s,
            "noise": {
                "taus_s": list(self.noise_taus_s),
                "f_max_hz": self.noise_f_max_hz,
                "quadrature_points": self.quadrature_points,
                "spectrum": "1 / (1 + (2 pi f tau)^2) on [0, f_max]; white for tau = 0",
            },
            "interval": {
                "block_s": self.block_s,
                "n_boot": self.n_boot,
                "level": self.level,
                "seed": self.seed,
                "method": "block bootstrap over entry time (coupling.intervals.block_bootstrap)",
            },
            "resolved_factor": self.resolved_factor,
            "dem": {f: d.record() for f, d in self.dem.items()},
            "pbm": {mode: m.record() for mode, m in self.pbm.items()},
            "note": self.note,
        }


def _feeder(component) -> str:
    """ "A"/"B" from a feeder name or particle_records' component code (1, 2)."""
    for name, code in COMPONENT_CODES.items():
        if component == name or (not isinstance(component, (bool, str)) and component == code):
            return name
    raise ConfigError(
        f"component must be one of {list(COMPONENT_CODES)} or their codes "
        f"{list(COMPONENT_CODES.values())} in particle_records' 'component' column, got {component!r}"
    )


def _pooled_window(pooled_spec: PooledRtdSummary) -> tuple[tuple[float, float], float]:
    try:
        t0, t1 = (float(v) for v in pooled_spec.entry_window_s)
        horizon = float(pooled_spec.horizon_s)
    except (AttributeError, TypeError, ValueError):
        raise ConfigError(
            "pooled_spec must be the DEM summary's pooled RTD (dem.summary.PooledRtdSummary) with an "
            f"entry window (t0, t1] and a horizon; got {pooled_spec!r}"
        ) from None
    if not (math.isfinite(t0) and math.isfinite(t1) and t0 < t1 and math.isfinite(horizon) and horizon > 0):
        raise ConfigError(
            f"pooled_spec needs a finite entry window t0 < t1 and horizon > 0 s, got ({t0}, {t1}] and {horizon}"
        )
    return (t0, t1), horizon


def dem_transfer(
    particles: pd.DataFrame,
    pooled_spec: PooledRtdSummary,
    frequencies,
    component,
    *,
    noise_taus_s: Sequence[float] = (),
    noise_f_max_hz: float = 0.5,
    quadrature_points: int = QUADRATURE_POINTS,
    block_s: float = BLOCK_S,
    n_boot: int = N_BOOT,
    level: float = LEVEL,
    seed: int = SEED,
) -> DemTransfer:
    """The DEM's H(f) = mean over the recovered particles of ``component`` of
    exp(-i 2 pi f tau), conditional on recovery within the horizon (module docstring).

    ``particles``: :func:`dem.post.particle_records` (columns component, entry_t_s,
    exit_t_s); ``pooled_spec``: the DEM summary's ``pooled_rtd`` (entry_window_s,
    horizon_s); ``frequencies`` [Hz, >= 0]; ``component``: "A"/"B" or the codes 1/2.
    With ``noise_taus_s``, also the VRR of first-order noise of each correlation time,
    band-limited to [0, ``noise_f_max_hz``], on the quadrature grid of
    :func:`pbm.frequency.noise_frequencies`. Intervals: ``block_s`` blocks of entry time,
    ``n_boot`` replicates (one bootstrap for everything, so the intervals are of the same
    replicates). Raises ConfigError for missing columns, a bad spec or component, and when
    the feeder has fewer than two blocks of entries with recovered particles.
    """
    feeder = _feeder(component)
    missing = [c for c in ("component", "entry_t_s", "exit_t_s") if c not in particles.columns]
    if missing:
        raise ConfigError(f"particles lacks columns {missing}; expected dem.post.particle_records' columns")
    window, horizon = _pooled_window(pooled_spec)
    freqs = np.asarray(frequencies, dtype=float)
    if freqs.ndim != 1 or freqs.size == 0 or not np.all(np.isfinite(freqs) & (freqs >= 0)):
        raise ConfigError(f"frequencies must be a non-empty 1-D array of finite values >= 0 Hz, got {frequencies!r}")
    taus = tuple(float(t) for t in noise_taus_s)

    pooled, tau, block_of, counts = _recovered_by_block(particles, feeder, window, horizon, block_s)
    n_blocks = counts.size

    # Per block, the sum of exp(-i w tau) over its recovered particles: a bootstrap
    # replicate of the mean phasor is then (draws per block) @ sums / (draws @ counts),
    # the same number as resampling the particles block by block, at a fraction of the cost.
    grid = noise_frequencies(noise_f_max_hz, quadrature_points) if taus else np.empty(0)
    all_freqs = np.concatenate([freqs, grid])
    sums = _block_phasor_sums(tau, block_of, n_blocks, all_freqs)
    spectra = [noise_spectrum(grid, t) for t in taus]
    n_f = freqs.size
    est, low, high = _bootstrap_intervals(sums, counts, n_f, grid, spectra, n_boot, seed, level)
    h = sums[:, :n_f].sum(axis=0) / counts.sum()
    n_rec = int(counts.sum())
    floor = 1.0 / math.sqrt(n_rec)
    abs_h = Interval(est[:n_f], low[:n_f], high[:n_f])
    # 1/|H|^2 is decreasing, so the percentile interval of VRR is that of |H|, ends swapped.
    vrr = Interval(vrr_sinusoid(abs_h.estimate), vrr_sinusoid(abs_h.high), vrr_sinusoid(abs_h.low))
    uncorrected = ()
    if taus:
        h_grid = sums[:, n_f:].sum(axis=0) / counts.sum()
        uncorrected = tuple(vrr_spectrum(grid, h_grid, s) for s in spectra)
    return DemTransfer(
        component=feeder,
        frequency_hz=freqs,
        H=h,
        abs_H=abs_h,
        vrr=vrr,
        n_entered=pooled.n_entered,
        n_recovered=n_rec,
        n_blocks=int(n_blocks),
        mean_residence_time_s=pooled.mean_s,
        floor=floor,
        resolved=abs_h.estimate >= RESOLVED_FACTOR * floor,
        noise_taus_s=taus,
        noise_f_max_hz=float(noise_f_max_hz) if taus else math.nan,
        noise=tuple(Interval(float(est[n_f + i]), float(low[n_f + i]), float(high[n_f + i])) for i in range(len(taus))),
        noise_uncorrected=uncorrected,
    )


def _recovered_by_block(
    particles: pd.DataFrame, feeder: str, window: tuple[float, float], horizon: float, block_s: float
) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray]:
    """The pooled RTD of ``feeder``'s particles (:func:`coupling.metrics.rtd_pooled`), the
    residence times [s] of its recovered particles with each one's block of entry time,
    and the recovered particles per block (float). ConfigError when fewer than two blocks
    hold recovered particles: no interval can be had from them."""
    mine = particles["component"].to_numpy() == COMPONENT_CODES[feeder]
    entry = particles["entry_t_s"].to_numpy(float)[mine]
    exit_ = particles["exit_t_s"].to_numpy(float)[mine]
    try:
        pooled = rtd_pooled(entry, exit_, window, horizon)
    except ValueError as exc:  # the shared definition's checks, as this module's error type
        raise ConfigError(f"feeder {feeder}: {exc}") from None
    entered = (entry > window[0]) & (entry <= window[1])
    tau = exit_[entered] - entry[entered]
    recovered = tau <= horizon  # NaN (still inside) is never recovered
    # Every entered particle's block counts, even one whose particles all stayed beyond
    # H: resampling it is resampling what the entry window held, as dem.steady does.
    block_ids, block_of = np.unique(time_blocks(entry[entered], block_s, origin=window[0]), return_inverse=True)
    counts = np.bincount(block_of[recovered], minlength=block_ids.size).astype(float)
    if pooled.residence_s.size == 0 or np.count_nonzero(counts) < 2:
        raise ConfigError(
            f"feeder {feeder} has {pooled.residence_s.size} recovered particle(s) in "
            f"{np.count_nonzero(counts)} {block_s:g}-s block(s) of the entry window ({window[0]:g}, "
            f"{window[1]:g}] s; an interval needs at least two blocks with recovered particles"
        )
    return pooled, tau[recovered], block_of[recovered], counts


def _bootstrap_intervals(
    sums: np.ndarray,
    counts: np.ndarray,
    n_f: int,
    grid: np.ndarray,
    spectra: list[np.ndarray],
    n_boot: int,
    seed: int,
    level: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(estimate, low, high), each (n_f + noise spectra,): |H| at the first ``n_f`` of the
    phasor sums' frequencies, then the floor-corrected VRR of each noise spectrum on
    ``grid``; the block bootstrap's percentile interval, expanded for its number of
    blocks (:func:`coupling.intervals.expanded_interval`)."""
    # real and imaginary parts apart: float products, no complex cast per replicate
    sums_re, sums_im = np.ascontiguousarray(sums.real), np.ascontiguousarray(sums.imag)
    n_blocks = counts.size

    def statistic(draws: np.ndarray) -> np.ndarray:
        """(R, n_f + taus) for (R, blocks) draw counts: |H| at ``freqs``, then each
        noise VRR; NaN for a draw without a recovered particle."""
        n = draws @ counts
        with np.errstate(invalid="ignore", divide="ignore"):
            abs2 = ((draws @ sums_re) ** 2 + (draws @ sums_im) ** 2) / (n**2)[:, None]
        corrected = _floor_corrected(abs2[:, n_f:], n[:, None])
        noise = [vrr_spectrum(grid, corrected, s) for s in spectra]
        out = np.column_stack([np.sqrt(abs2[:, :n_f]), *noise])
        out[n == 0] = np.nan
        return out

    # a replicate's mean phasor is (draws per block) @ sums / (draws @ counts): every
    # replicate of block_bootstrap's at once
    draws = block_draw_counts(n_blocks, n_boot, seed)
    est, low, high = expanded_interval(
        percentile_interval(statistic(np.ones((1, n_blocks)))[0], statistic(draws), level), n_blocks, level
    )
    est, low, high = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (est, low, high))
    return est, low, high


def _block_phasor_sums(tau: np.ndarray, block_of: np.ndarray, n_blocks: int, freqs: np.ndarray) -> np.ndarray:
    """(n_blocks, F) sums of exp(-i 2 pi f tau) over each block's particles."""
    onehot = np.zeros((n_blocks, tau.size))
    onehot[block_of, np.arange(tau.size)] = 1.0
    out = np.empty((n_blocks, freqs.size), dtype=complex)
    for start in range(0, freqs.size, _CHUNK):
        phase = np.outer(tau, 2 * np.pi * freqs[start : start + _CHUNK])
        out[:, start : start + _CHUNK] = onehot @ np.cos(phase) - 1j * (onehot @ np.sin(phase))
    return out


def _floor_corrected(abs2: np.ndarray, n) -> np.ndarray:
    """|H| from a measured |h|^2 over n particles: sqrt((n |h|^2 - 1) / (n - 1)), clipped
    at 0. For n independent particles E|h|^2 = |H|^2 + (1 - |H|^2) / n, so this is
    unbiased. The noise VRR integrates |H|^2 over a band that reaches the floor, where the
    raw |h|^2 would add ~ f_max / n to the output variance (0.3 % of the white-noise VRR on
    the reduced run) and twice that inside every bootstrap replicate, shifting the
    percentile interval. ``n`` broadcasts against ``abs2`` (one count per replicate);
    where n <= 1, |h| as it is."""
    n = np.asarray(n, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        corrected = np.clip((n * abs2 - 1) / (n - 1), 0.0, None)
    return np.sqrt(np.where(n > 1, corrected, abs2))


def default_frequencies(mean_residence_time_s: float, points: int = 25, f_max_hz: float = 1.0) -> np.ndarray:
    """Log-spaced from 1 / (10 mean residence time), where |H| ~ 1, to ``f_max_hz``."""
    if not (math.isfinite(mean_residence_time_s) and mean_residence_time_s > 0):
        raise ConfigError(f"mean_residence_time_s must be a finite time > 0 s, got {mean_residence_time_s}")
    f_min = 0.1 / mean_residence_time_s
    if not f_min < f_max_hz:
        raise ConfigError(f"f_max_hz = {f_max_hz} Hz must exceed 1 / (10 mean residence time) = {f_min:.3g} Hz")
    return np.geomspace(f_min, f_max_hz, int(points))


def _interval_dict(iv: Interval) -> dict[str, Any]:
    return {"value": iv.estimate, "low": iv.low, "high": iv.high}


def _pbm_mode(
    table: VelocityTable,
    pbm_config: PbmConfig,
    mode: str,
    steady_time_s: float,
    freqs: np.ndarray,
    grid: np.ndarray,
    taus: tuple[float, ...],
    spectra: list[np.ndarray],
    dem: Mapping[str, DemTransfer],
) -> PbmVrr:
    """One PBM rate mode of :func:`vrr_comparison`, judged against ``dem`` per feeder."""
    system = stationary_system(table, pbm_config.model_copy(update={"rates": mode}), t_start_s=steady_time_s)
    feeders: dict[str, FeederVrr] = {}
    points: list[RatioPoint] = []
    for f in FEEDERS:
        d = dem[f]
        h = system_response(system, freqs, f)
        vrr = vrr_sinusoid(h)
        ok = np.atleast_1d(inside(vrr, d.vrr.low, d.vrr.high))
        grid_h = system_response(system, grid, f)
        feeders[f] = FeederVrr(
            feeder=f,
            # Little's law at one particle/s: the steady hold-up is the mean residence time
            mean_residence_time_s=float(np.linalg.solve(system.generator, -system.feed_column(f)).sum()),
            abs_H=np.abs(h),
            vrr=vrr,
            # unresolved DEM points are not judged: None rather than a verdict
            inside=tuple(bool(v) if r else None for v, r in zip(ok, d.resolved)),
            noise=tuple(NoiseVrr(tau, vrr_spectrum(grid, grid_h, s), iv) for tau, s, iv in zip(taus, spectra, d.noise)),
        )
        points += [
            RatioPoint(float(vrr[i] / d.vrr.estimate[i]), f, float(freqs[i]), bool(ok[i]))
            for i in np.flatnonzero(d.resolved)
        ]
    return PbmVrr(
        mode=mode,
        feeders=feeders,
        windows_averaged=(int(system.windows[0]), int(system.windows[-1])),
        points=tuple(points),
    )


def steady_table(table: VelocityTable, rates: str, t_start_s: float) -> VelocityTable:
    """A table whose every window holds the mean of ``table``'s windows from ``t_start_s``
    on (after the rate mode's fill rule): the blender of :func:`pbm.frequency.stationary_system`,
    whose mean generator is the generator of these mean fields (it is linear in them)."""
    filled, _ = filled_table(table, rates)
    windows = filled.t >= t_start_s
    names = VELOCITY_NAMES + (RATE_NAMES if filled.has_rates else ())
    return filled.replace(
        **{
            name: np.broadcast_to(getattr(filled, name)[windows].mean(axis=0), getattr(filled, name).shape).copy()
            for name in names
        }
    )


def ensemble_check(
    table: VelocityTable,
    config: PbmConfig,
    t_start_s: float,
    members: int = ENSEMBLE_MEMBERS,
    sigmas: Sequence[float] = ENSEMBLE_SIGMAS,
) -> list[EnsembleCheck]:
    """The time-domain noise ensemble against the frequency domain, per sigma: the SD of
    the outlet C_A across ``members`` (both feeders redrawn every noise interval; the root
    of the variance over members, averaged over the outputs once the blender has filled)
    and :func:`pbm.frequency.sampled_ca_sd`, both on :func:`steady_table`, so that the
    ensemble's blender is the transfer function's. One :class:`EnsembleCheck` per sigma."""
    config, _ = resolve_feed(config, table)  # the rates weigh the two feeders' responses below
    steady = steady_table(table, config.rates, t_start_s)
    system = stationary_system(steady, config)
    rates = [config.feed_rate_a_per_s, config.feed_rate_b_per_s]
    weights = np.array(rates) / sum(rates)
    mrt = float(np.linalg.solve(system.generator, -system.feed).sum(axis=0) @ weights)
    # from an empty blender: five mean residence times fill it (to e^-5), within the run
    t_from = min(5 * mrt, 0.5 * steady.t_end)
    rows = []
    for sigma in sigmas:
        predicted = sampled_ca_sd(system, rates, sigma, config.noise_interval_s, config.output_interval_s)
        t0 = time.perf_counter()
        ens = noise_ensemble(steady, config, sigma=sigma, members=members)
        elapsed = time.perf_counter() - t0
        after = ens.times >= t_from
        measured = float(np.sqrt(np.mean(np.nanvar(ens.C_A_members[:, after], axis=0, ddof=1))))
        rows.append(
            EnsembleCheck(
                sigma=sigma,
                members=members,
                from_s=t_from,
                sd_time_domain=measured,
                sd_frequency_domain=predicted,
                ensemble_s=elapsed,
            )
        )
    return rows


def vrr_comparison(
    table: VelocityTable,
    pbm_config: PbmConfig,
    steady_time_s: float,
    dem_summary: DemSummary,
    particles: pd.DataFrame,
    frequencies=None,
    *,
    noise_taus_s: Sequence[float] = NOISE_TAUS_S,
    n_boot: int = N_BOOT,
    seed: int = SEED,
) -> VrrComparison:
    """PBM (each rate mode the table supports) against DEM: |H|, VRR per feeder and
    frequency, whether each PBM VRR lies in the DEM's interval (None where the DEM is
    unresolved), the worst PBM / DEM ratio, and the VRR of band-limited noise, as a
    :class:`VrrComparison` (its ``record()`` is the JSON).

    The PBM's system is the mean generator of the windows from ``steady_time_s``; the
    noise band is [0, 1 / (2 pbm_config.noise_interval_s)] for both sides. ``frequencies``
    default to :func:`default_frequencies` of the DEM's pooled mean residence time.
    Raises ConfigError when the DEM summary has no pooled RTD, or (from pbm.frequency) for
    a steady time after the table's last window.
    """
    pooled_spec = dem_summary.pooled_rtd
    if not dem_summary.has_pooled_rtd:
        raise ConfigError(
            "the DEM summary has no pooled RTD ('pooled_rtd' with particles entered): the run has no "
            "entry window after its steady state, so the DEM predicts no H(f)"
        )
    if not (isinstance(steady_time_s, (int, float)) and math.isfinite(steady_time_s)):
        raise ConfigError(f"steady_time_s must be a finite time [s], got {steady_time_s!r}")
    if frequencies is None:
        frequencies = default_frequencies(float(pooled_spec.mean_residence_time_s.value))
    freqs = np.asarray(frequencies, dtype=float)
    f_max = 0.5 / pbm_config.noise_interval_s
    grid = noise_frequencies(f_max, QUADRATURE_POINTS)
    taus = tuple(float(t) for t in noise_taus_s)
    spectra = [noise_spectrum(grid, t) for t in taus]

    # Small matrices in loops, next to a LIGGGHTS campaign: threads only slow them down.
    with single_threaded_blas():
        dem = {
            f: dem_transfer(
                particles, pooled_spec, freqs, f, noise_taus_s=taus, noise_f_max_hz=f_max, n_boot=n_boot, seed=seed
            )
            for f in FEEDERS
        }
        pbm = {
            mode: _pbm_mode(table, pbm_config, mode, steady_time_s, freqs, grid, taus, spectra, dem)
            for mode in supported_modes(table)
        }
        pbm = {
            mode: replace(
                m,
                # under the fill law members do not superpose: the linearised response stands alone
                ensemble_check=()
                if pbm_config.rate_law == "fill"
                else tuple(ensemble_check(table, pbm_config.model_copy(update={"rates": mode}), steady_time_s)),
            )
            for mode, m in pbm.items()
        }
    return VrrComparison(
        frequency_hz=freqs,
        steady_time_s=float(steady_time_s),
        dem=dem,
        pbm=pbm,
        noise_taus_s=taus,
        noise_f_max_hz=f_max,
        quadrature_points=QUADRATURE_POINTS,
        block_s=BLOCK_S,
        n_boot=n_boot,
        level=LEVEL,
        seed=seed,
        resolved_factor=RESOLVED_FACTOR,
    )
