"""Feed-noise ensembles (paper section 3.2.3, Figs 5-6).

All members share the velocity table, so they share every step operator. A few members
are one propagation of a state matrix with 2 M columns (A and B of each member), each
member's noisy feed entering through the feed term of the same exact step
``z <- P z + Q r``. Beyond as many members as noise intervals, the responses to a unit feed
in each interval are propagated instead and every member is their weighted sum
(superposition: the PBM is linear in its feed), which costs the same for 10 000 members as
for 300. CQAs are reduced output by output, so memory stays O(M x outputs) and never holds
M full state histories.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from coupling.blas import free_cores, single_threaded_blas
from coupling.errors import ConfigError
from coupling.metrics import outflow_fraction_a, rsd
from coupling.tables import VelocityTable
from pbm.config import PbmConfig
from pbm.feed import resolve_feed
from pbm.model import collapse_phases, feed_distribution, filled_table, n_phases
from pbm.resources import check_ensemble_memory
from pbm.simulate import check_run, feed_factors, noise_intervals
from pbm.solver import MAX_THREADS, TIME_TOLERANCE_S, Propagators, breakpoints, march, multiples, shared_pool

BAND_QUANTILES = (0.05, 0.95)
#: Pivots (of a column-pivoted QR) below this fraction of the largest are dropped from
#: the outlet's unit responses: the rounding level of the responses themselves.
LOW_RANK_RTOL = float(np.finfo(float).eps)


@dataclass(frozen=True)
class EnsembleResult:
    """Statistics of M noise realisations. Series are (K,) over ``times`` [s].

    ``C_A_*`` and ``rsd_outlet_*``: ensemble mean and 5 % / 95 % quantiles (NaN where
    undefined for every member); ``rsd_by_slice_*`` (NX,) the same for RSD(x) at the end.
    ``C_A_members`` and ``rsd_outlet_members`` (M, K) keep every realisation.
    """

    sigma: float
    members: int
    times: np.ndarray
    C_A_mean: np.ndarray
    C_A_p05: np.ndarray
    C_A_p95: np.ndarray
    rsd_outlet_mean: np.ndarray
    rsd_outlet_p05: np.ndarray
    rsd_outlet_p95: np.ndarray
    rsd_by_slice_mean: np.ndarray
    rsd_by_slice_p05: np.ndarray
    rsd_by_slice_p95: np.ndarray
    C_A_members: np.ndarray
    rsd_outlet_members: np.ndarray


def _bands(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and 5/95 % quantiles of each row (a series' members along axis 1), ignoring
    NaN; NaN where all are NaN. Row blocks run on the free cores: the quantiles' partitions
    release the GIL, and each row's numbers do not depend on the blocks."""
    blocks = np.array_split(rows, free_cores(min(MAX_THREADS, max(1, rows.shape[0]))))
    if len(blocks) == 1:
        return _row_bands(rows)
    parts = list(shared_pool().map(_row_bands, blocks))
    return tuple(np.concatenate([part[i] for part in parts]) for i in range(3))


def _row_bands(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_bands` of one block of rows, on the calling thread."""
    finite = np.isfinite(rows)
    count = finite.sum(axis=1)
    mean = np.full(rows.shape[0], np.nan)
    lo = np.full(rows.shape[0], np.nan)
    hi = np.full(rows.shape[0], np.nan)
    whole = count == rows.shape[1]
    if whole.any():
        sub = rows[whole]
        mean[whole] = sub.mean(axis=1)
        lo[whole], hi[whole] = np.quantile(sub, BAND_QUANTILES, axis=1)
    # nanquantile is ~10x slower than quantile: only where some member is NaN
    partial = ~whole & (count > 0)
    if partial.any():
        sub = rows[partial]
        mean[partial] = np.where(finite[partial], sub, 0.0).sum(axis=1) / count[partial]
        lo[partial], hi[partial] = np.nanquantile(sub, BAND_QUANTILES, axis=1)
    return mean, lo, hi


@single_threaded_blas()
def noise_ensemble(
    table: VelocityTable, config: PbmConfig | None = None, sigma: float | None = None, members: int = 100
) -> EnsembleResult:
    """Run ``members`` feed-noise realisations at once; return mean and 5-95 % bands.

    ``sigma`` (default ``config.noise_sigma``) is the relative SD of the feed-rate factor
    N(1, sigma), clipped at 0 and redrawn every ``config.noise_interval_s``, independently
    for A and B (:func:`pbm.simulate.noise_factors`); member 0 has the factors
    :func:`pbm.simulate.simulate` uses. Exact propagation only (the BDF
    path is a cross-check of single runs). No tracer: the RTD does not depend on the feed.
    """
    config, _ = resolve_feed(config, table)  # the run's simulate() names any override
    sigma = config.noise_sigma if sigma is None else float(sigma)
    if not (math.isfinite(sigma) and sigma >= 0):
        raise ConfigError(f"noise sigma must be a finite number >= 0, got {sigma}")
    if isinstance(members, bool) or int(members) != members or members < 1:
        raise ConfigError(f"members must be an integer >= 1, got {members!r}")
    members = int(members)
    t_end = check_run(table, config)
    # refused up front with the estimate, not killed by the kernel halfway (pbm.resources)
    check_ensemble_memory(members, t_end, config.noise_interval_s, config.output_interval_s, table.nx)
    if config.rate_law != "table":
        raise ConfigError(
            f"the noise ensemble needs rate_law = 'table', got {config.rate_law!r}: under the fill law each "
            "member's rates follow its own fill, so members do not superpose"
        )
    filled, _ = filled_table(table, config.rates)
    feed = feed_distribution(table, config.feed_weights_a, config.feed_weights_b, config.rates)
    props = Propagators(filled, feed, config.rates, config.kernel)
    # the compartments' populations: (NX, NY, K) in mode "phases", K = 1 otherwise
    grid = (table.nx, table.ny, n_phases(table, config.rates))

    # With sigma = 0 every member is the same run: propagate one and replicate it.
    distinct = members if sigma > 0 else 1
    n_noise = noise_intervals(config, t_end)
    # drawn on another core while the unit responses march: they need no factors
    factors = shared_pool().submit(feed_factors, config, n_noise, distinct, sigma)
    rates = np.array([config.feed_rate_a_per_s, config.feed_rate_b_per_s])

    out_times = multiples(config.output_interval_s, config.output_interval_s, t_end)
    switch_sets = [props.schedule.t]
    if sigma > 0:
        switch_sets.append(multiples(config.noise_interval_s, 0.0, t_end))
    if config.feed_step_s is not None:
        switch_sets.append(np.array([config.feed_step_s]))
    times = breakpoints(0.0, t_end, out_times, *switch_sets)
    mids = 0.5 * (times[:-1] + times[1:])
    feed_key = np.clip(np.floor(mids / config.noise_interval_s).astype(int), 0, n_noise - 1)
    out_index = np.full(times.size, -1)
    out_index[np.searchsorted(times, out_times - TIME_TOLERANCE_S)] = np.arange(out_times.size)

    run = _by_superposition if distinct > n_noise else _by_columns
    series = run(props, times, feed_key, out_index, out_times.size, rates, factors, grid)
    # each series' members along axis 1, every distinct run repeated for the members it stands for
    reps = members // distinct
    c_a_rows, rsd_rows, slice_rows = (x if reps == 1 else np.repeat(x, reps, axis=1) for x in series)
    ca_stats = _bands(c_a_rows)
    rsd_stats = _bands(rsd_rows)
    slice_stats = _bands(slice_rows)
    return EnsembleResult(
        sigma=sigma,
        members=members,
        times=out_times,
        C_A_mean=ca_stats[0],
        C_A_p05=ca_stats[1],
        C_A_p95=ca_stats[2],
        rsd_outlet_mean=rsd_stats[0],
        rsd_outlet_p05=rsd_stats[1],
        rsd_outlet_p95=rsd_stats[2],
        rsd_by_slice_mean=slice_stats[0],
        rsd_by_slice_p05=slice_stats[1],
        rsd_by_slice_p95=slice_stats[2],
        C_A_members=c_a_rows.T,
        rsd_outlet_members=rsd_rows.T,
    )


def _compartments(z: np.ndarray, grid: tuple[int, int, int]) -> np.ndarray:
    """The (NX, NY, columns) populations of the compartments in the state ``z``: the
    phases of each summed (:func:`pbm.model.collapse_phases`)."""
    nx, ny, k = grid
    return collapse_phases(z[: nx * ny * k], k).reshape(nx, ny, -1)


def _by_columns(props, times, feed_key, out_index, n_out, rates, factors, grid):
    """Every member's A and B as two columns of one propagated state: cost ~ members.
    ``factors`` is a future of the (J, M, 2) feed factors, as in :func:`_by_superposition`."""
    nx, ny, k = grid
    n = nx * ny * k
    factors = factors.result()
    distinct = factors.shape[1]

    def feed_rates(key: int) -> np.ndarray:
        r = np.zeros((2, 2 * distinct))
        r[0, 0::2] = rates[0] * factors[key, :, 0]
        r[1, 1::2] = rates[1] * factors[key, :, 1]
        return r

    c_a = np.empty((n_out, distinct))
    rsd_out = np.empty((n_out, distinct))
    last_discharged = np.zeros(2 * distinct)
    z = np.zeros((props.n_states, 2 * distinct))
    for b, z in march(props, times, z, feed_rates, feed_key):  # noqa: B020 -- march returns each step's new state
        out = out_index[b]
        if out < 0:
            continue
        discharged = z[n]
        inc = discharged - last_discharged
        last_discharged = discharged.copy()
        c_a[out] = outflow_fraction_a(inc[0::2], inc[1::2])
        outlet = _compartments(z, grid)[-1]
        rsd_out[out] = rsd(outlet[:, 0::2], outlet[:, 1::2], axis=0)
    final = _compartments(z, grid)
    return c_a, rsd_out, rsd(final[:, :, 0::2], final[:, :, 1::2], axis=1)


def _by_superposition(props, times, feed_key, out_index, n_out, rates, factors, grid, chunk: int = 16):
    """The same numbers as :func:`_by_columns` at a cost independent of the members: the
    PBM is linear in its feed, so the particles fed at one particle/s during noise
    interval j alone are propagated once per feeder and interval (2 J columns), their
    outlet compartments and discharge recorded at every output; each member is then the
    sum over j of those responses times its feed rate in interval j (matrix products per
    block of outputs, reduced to C_A and RSD before the next block). ``factors`` is a
    future of the (J, M, 2) feed factors, awaited only after the march."""
    nx, ny, k = grid
    n = nx * ny * k
    n_int = int(feed_key.max()) + 1  # the intervals a step feeds in; a later one feeds nothing

    def unit_feed(key: int) -> np.ndarray:
        r = np.zeros((2, 2 * n_int))
        r[0, 2 * key] = 1.0
        r[1, 2 * key + 1] = 1.0
        return r

    outlet = np.empty((n_out, ny, 2 * n_int))
    discharged = np.empty((n_out, 2 * n_int))
    z = np.zeros((props.n_states, 2 * n_int))
    # Interval j's pair of columns (A, B) is 2j, 2j + 1, so the columns fed so far lead the
    # state and the march leaves the others, still zero, alone: half its products.
    live = 2 * (np.maximum.accumulate(feed_key) + 1)
    for b, z in march(props, times, z, unit_feed, feed_key, live=live):  # noqa: B020 -- march returns each step's new state
        out = out_index[b]
        if out >= 0:
            outlet[out] = _by_species(_compartments(z, grid)[-1])
            discharged[out] = _by_species(z[n])
    final = _by_species(_compartments(z, grid).reshape(nx * ny, -1))
    running = np.concatenate([np.zeros((1, 2 * n_int)), discharged])  # the totals before each output

    def factored_block(first: int) -> tuple:
        end = min(n_out, first + chunk)
        return _factored_block(outlet[first:end], running[first : end + 1])

    factored = list(shared_pool().map(factored_block, range(0, n_out, chunk)))
    factors = factors.result()[:n_int]
    fed = [rates[s] * factors[:, :, s] for s in (0, 1)]  # (J, M) feed rate of each member
    # Member blocks on a thread per free core: numpy releases the GIL in its products, and
    # each thread's BLAS stays single-threaded (see coupling.blas).
    members = factors.shape[1]
    blocks = np.array_split(np.arange(members), free_cores(min(MAX_THREADS, members)))
    kernels = (factored, final, n_out, n_int, nx, ny, chunk)
    # each block writes its members' columns of the results: no copy to join them
    results = (np.empty((n_out, members)), np.empty((n_out, members)), np.empty((nx, members)))

    def combine(idx: np.ndarray) -> None:
        cols = slice(int(idx[0]), int(idx[-1]) + 1)
        _combine(*kernels, fed[0][:, cols], fed[1][:, cols], *(r[:, cols] for r in results))

    with ThreadPoolExecutor(max_workers=len(blocks)) as pool:
        list(pool.map(combine, blocks))
    return results


def _by_species(columns: np.ndarray) -> np.ndarray:
    """Interval-pair columns (A0, B0, A1, B1, ...) reordered as A's intervals, then B's."""
    return np.concatenate([columns[..., 0::2], columns[..., 1::2]], axis=-1)


def _factored_block(outlet: np.ndarray, discharged: np.ndarray):
    """``(used, [(Q, R) of A, (Q, R) of B])`` of a block of outputs' unit responses: the
    intervals it needs (nothing fed after its last output has arrived anywhere, so later
    columns are dropped) and each species' responses factored to their rounding level
    (:func:`_low_rank`), rows the outlet's cells output after output, then the discharge's
    increments (``discharged``: the running totals from the output before the block's).

    Over a block of outputs the outlet cells follow smooth curves, so the responses to
    every interval fed by then span ~30 directions where there are up to J of them (260 in
    the benchmark's run): two thin products per member instead of one wide one, half the
    multiply-adds. C_A needs the increments only, and differencing the members' running
    totals instead would cancel most of their digits."""
    n_int = discharged.shape[1] // 2
    increments = np.diff(discharged, axis=0)
    live = (np.any(outlet != 0, axis=(0, 1)) | np.any(increments != 0, axis=0)).reshape(2, n_int).any(axis=0)
    used = int(np.flatnonzero(live).max()) + 1 if live.any() else 1
    pieces = [
        np.concatenate(
            [outlet[:, :, s * n_int : s * n_int + used].reshape(-1, used), increments[:, s * n_int : s * n_int + used]]
        )
        for s in (0, 1)
    ]
    return used, [_low_rank(piece) for piece in pieces]


def _low_rank(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Q, R) with Q R = ``b`` to its rounding level and as few columns of Q as that
    allows: a column-pivoted QR truncated at :data:`LOW_RANK_RTOL` of its largest pivot."""
    q, r, perm = scipy.linalg.qr(b, mode="economic", pivoting=True)
    pivots = np.abs(np.diag(r))
    rank = max(1, int(np.count_nonzero(pivots > LOW_RANK_RTOL * pivots[0]))) if pivots.size else 1
    unpermuted = np.empty((rank, b.shape[1]))
    unpermuted[:, perm] = r[:rank]
    return np.ascontiguousarray(q[:, :rank]), unpermuted


def _combine(factored, final, n_out, n_int, nx, ny, chunk, fed_a, fed_b, c_a, rsd_out, slices):
    """C_A, outlet RSD and final slice RSDs of the members whose interval feed rates are
    the columns of ``fed_a`` / ``fed_b`` (J, M), from the unit responses, written into
    ``c_a``, ``rsd_out`` (outputs, M) and ``slices`` (NX, M). ``factored``: each block of
    ``chunk`` outputs' :func:`_factored_block`."""
    members = fed_a.shape[1]
    fed = (fed_a, fed_b)
    # One set of buffers for every block: a fresh array per product is fresh pages, and
    # faulting them in cost as much as the products on these machines.
    cells = np.empty((2, chunk * (ny + 1), members))
    reduced = np.empty(max(q.shape[1] for _, pair in factored for q, _ in pair) * members)
    for i, k0 in enumerate(range(0, n_out, chunk)):
        rows = min(n_out, k0 + chunk) - k0
        u, pair = factored[i]
        for s, (q, r) in enumerate(pair):
            inner = reduced[: r.shape[0] * members].reshape(r.shape[0], members)
            np.matmul(r, fed[s][:u], out=inner)
            np.matmul(q, inner, out=cells[s, : rows * (ny + 1)])
        shaped = cells[:, : rows * ny].reshape(2, rows, ny, members)
        rsd_out[k0 : k0 + rows] = rsd(shaped[0], shaped[1], axis=1)
        inc = cells[:, rows * ny : rows * (ny + 1)]
        c_a[k0 : k0 + rows] = outflow_fraction_a(inc[0], inc[1])
    state = [(final[:, s * n_int : (s + 1) * n_int] @ fed[s]).reshape(nx, ny, -1) for s in (0, 1)]
    slices[:] = rsd(state[0], state[1], axis=1)


PAPER_SIGMAS = (0.0, 0.05, 0.1, 0.2, 0.3)


def noise_study(
    table: VelocityTable, config: PbmConfig | None = None, sigmas=PAPER_SIGMAS, members: int = 200
) -> dict[float, EnsembleResult]:
    """The paper's Figs 5-6 study: one :func:`noise_ensemble` per sigma (default 0-0.3)."""
    return {float(s): noise_ensemble(table, config, sigma=s, members=members) for s in sigmas}
