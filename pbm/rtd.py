"""The PBM's pooled residence-time distribution, defined like the DEM's.

The DEM pools every particle that entered during an entry window (t0, t1]: its residence
time is tau = exit - entry, and it counts as recovered only if tau <= H (the horizon,
t1 = t_end - H). Moments are over the recovered particles, reported with the recovered
fraction (``coupling/DEFINITIONS.md``, "RTD").

The PBM's like-for-like quantity follows from linearity: tracer entering uniformly over
(t0, t1] is the average over entry times s of the pulse responses E_s(tau), each pulse
spread over the inlet like the total feed (A and B weighted by their feed rates). The
average is taken at the centres of equal sub-intervals of (t0, t1] (midpoint rule), one
pulse per centre, every pulse a column of an exact propagation through the table's own
windows: for a time-varying table each pulse sees the windows in force after its entry.
(The outlet flux of a rectangular feed would instead mix the entry times into one curve.)
Pulses that all see one generator have one response, so a time-invariant model propagates
a single column; a comb too large for the uniformization kernel's memory bound is
propagated in groups of pulses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from coupling.blas import single_threaded_blas
from coupling.errors import ConfigError
from coupling.metrics import residence_moments
from coupling.tables import VelocityTable
from pbm.config import PbmConfig
from pbm.feed import resolve_feed
from pbm.fill import config_schedule
from pbm.model import feed_distribution, filled_table, n_populations
from pbm.simulate import (
    BDF_ATOL_PARTICLES,
    check_run,
    feed_factors,
    noise_intervals,
    recovered_moments,
    tracer_pulse,
)
from pbm.solver import ACTION_MAX_BYTES, TIME_TOLERANCE_S, Propagators, Schedule, breakpoints, march, multiples


@dataclass(frozen=True)
class PooledRtd:
    """The pooled RTD over an entry window, truncated at the horizon.

    ``bin_edges`` [s]: residence-time bin edges over [0, H] (width ``rtd_bin_s``; the last
    bin is shorter when H is not a multiple of it); ``density_per_s`` [1/s]: tracer
    discharged in each bin / tracer fed / bin width, averaged over the pulses, so that its
    integral over [0, H] is ``recovered_fraction``; ``mean_s`` [s] and ``variance_s2``
    [s^2]: moments of tau over the tracer recovered within H (exact, not from the bins; NaN
    if none is recovered); ``entry_times_s`` [s]: the pulse times, ``n_pulses`` of them.
    """

    bin_edges: np.ndarray
    density_per_s: np.ndarray
    recovered_fraction: float
    mean_s: float
    variance_s2: float
    n_pulses: int
    entry_times_s: np.ndarray

    @property
    def bin_centres(self) -> np.ndarray:
        return 0.5 * (self.bin_edges[:-1] + self.bin_edges[1:])

    @property
    def recovered_density_per_s(self) -> np.ndarray:
        """E over the recovered tracer only (integral 1 over [0, H]): the DEM's pooled E is
        normalised the same way, so the two compare in shape."""
        return self.density_per_s / self.recovered_fraction


@single_threaded_blas()
def pooled_rtd(
    table: VelocityTable,
    config: PbmConfig | None = None,
    entry_window: tuple[float, float] = (0.0, 1.0),
    horizon_s: float = 60.0,
    pulse_interval_s: float | None = None,
    schedule: Schedule | None = None,
) -> PooledRtd:
    """The PBM's RTD of tracer entering uniformly during ``entry_window`` = (t0, t1] [s],
    recovered within ``horizon_s`` = H [s] of entry: the DEM's pooled RTD, like for like.

    n = round((t1 - t0) / s) pulses (at least one), s = ``pulse_interval_s`` (default
    ``config.rtd_bin_s``), spaced exactly s apart and centred in (t0, t1]: the centres of n
    equal sub-intervals when t1 - t0 is a multiple of s, and otherwise a comb that misses or
    overhangs the window by less than s / 2 in all. Exactly s apart so that, with 1-s bins,
    every pulse is read on one grid of times: an uneven spacing made each pulse's bin edges
    breakpoints of their own, and the march 44 times longer (11 381 steps instead of 256 on
    the reduced reference's 126 pulses). Uses ``config``'s feed rates and
    weights (the tracer's inlet distribution), ``rates``, ``method``, ``rtd_bin_s`` and
    ``duration_s``; the A and B populations themselves do not enter (the system is linear).
    Raises ConfigError unless 0 <= t0 < t1, H > 0, pulse_interval_s > 0 and t1 + H lies
    within the run (``duration_s``, or the table's end): a pulse must be followed for all
    of H. ``schedule``: the generators of the run the tracer joins, when that run has been
    simulated under the fill law (:attr:`pbm.simulate.PbmResult.schedule`: its bulk is
    not solved again, and the tracer sees that run's fill); default the one ``config``
    gives (:func:`pbm.fill.config_schedule`).
    """
    config, _ = resolve_feed(config, table)  # the run's simulate() names any override
    t_end = check_run(table, config)
    t0, t1 = (float(v) for v in entry_window)
    horizon = float(horizon_s)
    spacing = config.rtd_bin_s if pulse_interval_s is None else float(pulse_interval_s)
    if not (math.isfinite(t0) and math.isfinite(t1) and 0.0 <= t0 < t1):
        raise ConfigError(f"entry_window must satisfy 0 <= t0 < t1 (finite) [s], got ({t0}, {t1})")
    if not (math.isfinite(horizon) and horizon > 0):
        raise ConfigError(f"horizon_s must be a finite number > 0 s, got {horizon_s}")
    if not (math.isfinite(spacing) and spacing > 0):
        raise ConfigError(f"pulse_interval_s must be a finite number > 0 s, got {pulse_interval_s}")
    if t1 + horizon > t_end + TIME_TOLERANCE_S:
        raise ConfigError(
            f"entry window end {t1} s + horizon {horizon} s = {t1 + horizon} s is beyond the run's end "
            f"{t_end} s; the last entrants must be followed for the whole horizon (t1 <= {t_end - horizon} s)"
        )

    filled, _ = filled_table(table, config.rates)
    feed = feed_distribution(table, config.feed_weights_a, config.feed_weights_b, config.rates)
    factors = feed_factors(config, noise_intervals(config, t_end))[:, 0]
    if schedule is None:
        schedule, _law = config_schedule(table, config, feed, factors, t_end)
    props = Propagators(filled, feed, config.rates, config.kernel, schedule)
    n = n_populations(table, config.rates)
    m = props.n_states
    amount, vector = tracer_pulse(feed, np.array([config.feed_rate_a_per_s, config.feed_rate_b_per_s]), m)

    n_pulses = max(1, round((t1 - t0) / spacing))
    entries = 0.5 * (t0 + t1) + spacing * (np.arange(n_pulses) - 0.5 * (n_pulses - 1))
    edges = multiples(config.rtd_bin_s, 0.0, horizon)
    if horizon - edges[-1] > TIME_TOLERANCE_S:
        edges = np.append(edges, horizon)
    # Pulses that see one generator from the first entry to the last exit have one and
    # the same response in tau, so their average is any one of them: a time-invariant
    # model (the phase model, a steady table) propagates one column instead of a comb:
    # on the 20-slice phase chain (3603 states) that is 0.2 s instead of 40 s.
    switches = props.schedule.t[1:]
    varying = bool(np.any((switches > entries[0] + TIME_TOLERANCE_S) & (switches < entries[-1] + horizon)))
    pulses = entries if varying else entries[:1]
    # The action kernel keeps every breakpoint's state of every column: a comb whose
    # states would pass its memory bound is propagated in groups of pulses, each group over
    # its own span, so that the cheaper kernel still runs (the fill law's 91 pulses on a
    # 1203-state phase chain: 3 s by groups, 32 s by the dense path the bound forced);
    # the operators the dense path computes are kept across groups.
    times = breakpoints(pulses[0], pulses[-1] + horizon, (pulses[:, None] + edges[None, :]).ravel(), props.schedule.t)
    group = max(1, ACTION_MAX_BYTES // (times.size * m * 8))
    parts = [
        _propagate(props, pulses[i : i + group], edges, horizon, vector, n, config)
        for i in range(0, pulses.size, group)
    ]
    discharged = np.concatenate([d for d, _last in parts])  # (pulse, edge)
    last = np.concatenate([row for _d, row in parts])  # (pulse, row): state at entry + H
    columns = pulses.size
    density = (np.diff(discharged, axis=1) / (amount * np.diff(edges))).mean(axis=0)
    # Every tracer column starts at its pulse with zero integrals: the columns are empty
    # before, so the integrals accumulated from the march's start are those since entry.
    recovered, m1, m2 = recovered_moments(amount, last[:, 0], last[:, 2], last[:, 3], horizon)
    total = recovered.sum()
    # never a negative time or variance (coupling.metrics.residence_moments)
    moments = residence_moments(amount * columns, total, m1.sum(), m2.sum())
    mean, variance = moments["mean_s"], moments["variance_s2"]
    return PooledRtd(
        bin_edges=edges,
        density_per_s=density,
        recovered_fraction=float(total / (amount * columns)),
        mean_s=mean,
        variance_s2=variance,
        n_pulses=n_pulses,
        entry_times_s=entries,
    )


def _propagate(
    props: Propagators,
    pulses: np.ndarray,
    edges: np.ndarray,
    horizon: float,
    vector: np.ndarray,
    n: int,
    config: PbmConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """One march of a tracer column per pulse (entering at ``pulses`` [s] as ``vector``):
    (pulse, edge) the count discharged at each bin edge after its entry, never falling;
    (pulse, 4) tracer held, discharged and the two hold-up integrals at entry + H."""
    m = props.n_states
    columns = pulses.size
    record = pulses[:, None] + edges[None, :]  # (pulse, edge): absolute times to read
    times = breakpoints(pulses[0], pulses[-1] + horizon, record.ravel(), props.schedule.t)
    at = np.clip(np.searchsorted(times, record - TIME_TOLERANCE_S), 0, times.size - 1)
    injections = {}
    for p, b in enumerate(at[:, 0].tolist()):
        inj = np.zeros((m, columns))
        inj[:, p] = vector
        injections[b] = inj
    no_feed = np.zeros((2, columns))
    # Per breakpoint and pulse: tracer held, discharged, and the two hold-up integrals.
    rows = np.empty((times.size, 4, columns))
    z0 = np.zeros((m, columns))
    rows[0] = _tracked_rows(z0 + injections.get(0, 0.0), n)
    for b, z in march(
        props,
        times,
        z0,
        lambda _key: no_feed,
        np.zeros(times.size - 1, int),
        injections,
        method=config.method,
        rtol=config.bdf_rtol,
        atol=BDF_ATOL_PARTICLES,
    ):
        rows[b] = _tracked_rows(z, n)
    pulse_index = np.arange(columns)[:, None]
    # The count discharged cannot fall; once a pulse has left, the propagation's rounding
    # (~1e-16 of the pulse) would otherwise show as negative density in the empty bins.
    discharged = np.maximum.accumulate(rows[at, 1, pulse_index], axis=1)
    return discharged, rows[at[:, -1], :, np.arange(columns)]


def _tracked_rows(z: np.ndarray, n: int) -> np.ndarray:
    return np.stack([z[:n].sum(axis=0), z[n], z[n + 1], z[n + 2]])
