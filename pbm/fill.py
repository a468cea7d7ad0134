"""Flow that follows the fill: axial transfer rates that depend on the slice's hold-up.

The paper's PBM is linear: a compartment's rates do not depend on what it holds. The DEM
says otherwise. Doubling the feed raises its hold-up by 22 %, not 100 %, because the
blades carry a fuller slice forward faster while the backward rates hardly move. The net
axial flux is the small difference of the two, so a 30 % rise in the forward rate doubles
it. The law, per axial slice i and direction d (forward, including the discharge over the
weir from the last slice, and backward), is

    r_d(i, j, t) = r_d(i, j) * (N_i(t) / N_i)^beta[i, d]

with N_i(t) the slice's hold-up (all its compartments and phases: transverse mixing is
fast, and a slice's total is what the dumps measure with little noise), and r_d(i, j), N_i
the reference's rates and slice hold-ups over its steady period. So at the reference's own
fill the law is the identity. The transverse rates and the phase switching keep their
reference values: they move particles within a slice, not its hold-up. Also, 13 % of the
transverse rates sit at the dumps' cap (coupling/DEFINITIONS.md), so their dependence
cannot be measured.

The exponents are fitted (:func:`fit_fill_law`) from DEM runs of one vessel and speed
(:func:`fill_samples`: every window's slice fills and flux-weighted rates), by weighted
least squares on the log rates with an intercept per slice and direction. Several runs:
one point per run, slice and direction over its steady windows, the intercept common to
the runs (the law is the slice's, not the run's); that is what a change of throughput
moves. One run: its windows from a quarter of the steady fill on (the filling transient),
forward rates only. The form is the one with the least held-out error (leave one run out
from three runs on, else four blocks of windows): an exponent per slice and direction, one
per direction, or none (the linear model).

With the law, the PBM is nonlinear in the bulk (A + B) and linear in composition given
the bulk. :func:`solve_bulk` integrates the bulk with scipy's LSODA (analytic Jacobian);
:func:`fill_schedule` turns its fill history into a generator schedule (piecewise-constant
rates, a new entry wherever a rate has moved by :data:`SCHEDULE_LOG_TOL`). Composition,
tracer and RTD then march on that schedule with the exact linear kernels, which conserve
particles to rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from coupling.errors import ConfigError, TableError
from coupling.metrics import SteadyStateRule
from coupling.tables import RATE_NAMES, VELOCITY_NAMES, VelocityTable
from pbm.config import PbmConfig
from pbm.model import dense_generator, filled_table, n_phases, transfer_rates
from pbm.solver import Schedule, SolverError, table_schedule

#: the directions the law moves: 0 = forward (to i + 1, the discharge from the last slice), 1 = backward
DIRECTIONS = ("forward", "backward")
#: candidate forms of the exponents, by held-out error (:func:`fit_fill_law`)
FORMS = ("per-slice", "per-direction", "none")
#: windows where a slice holds less than this fraction of its steady fill are left out of
#: the fit: particles arriving in an empty slice fly over the blades rather than ride them
MIN_FILL_FRACTION = 0.25
#: exponents are clipped to [0, MAX_EXPONENT]: a fuller slice never moves slower, and a
#: steeper law than this is beyond what a few runs can pin down
MAX_EXPONENT = 8.0
#: a new schedule entry whenever a rate factor has moved this much in log
SCHEDULE_LOG_TOL = 0.005
#: the fill history is read at this spacing [s] to place the schedule's entries
SCHEDULE_SAMPLE_S = 0.05
#: the bulk's integrator: LSODA switches to its stiff method only where the flows are fast,
#: and factorises only the Jacobian's band (`pbmdem bench fill`: 2.3x and 5.8x faster than
#: BDF under 1-s feeder noise at 20 x 10, measured rates and phase model; hold-ups within
#: 1e-3 particles)
BULK_METHOD = "LSODA"
#: a slice's fill never counts below this many particles in the law (a power of 0 is 0,
#: but its derivative is not finite for exponents below 1)
FILL_FLOOR = 1e-6


@dataclass(frozen=True)
class FillSamples:
    """One run's slice-level windows: ``fill`` (K, NX) particles, ``rates`` (K, NX, 2)
    flux-weighted forward and backward rates [1/s] (NaN where unmeasured), ``weight``
    (K, NX, 2) the moves behind each rate, ``exposure`` (K, NX, 2) the particle-seconds
    behind it (its compartments' particles x the window), ``steady`` (K,) the steady
    windows."""

    fill: np.ndarray
    rates: np.ndarray
    weight: np.ndarray
    exposure: np.ndarray
    steady: np.ndarray

    @property
    def steady_fill(self) -> np.ndarray:
        return self.fill[self.steady].mean(axis=0)

    def steady_rates(self) -> tuple[np.ndarray, np.ndarray]:
        """((NX, 2) rates over the steady windows, as moves over particle-seconds (0 where
        none was measured), (NX, 2) the moves behind them)."""
        known = np.isfinite(self.rates[self.steady])
        moves = np.where(known, self.weight[self.steady], 0.0).sum(axis=0)
        seconds = np.where(known, self.exposure[self.steady], 0.0).sum(axis=0)
        return np.divide(moves, seconds, out=np.zeros_like(moves), where=seconds > 0), moves


@dataclass(frozen=True)
class FillLaw:
    """Exponents ``beta`` (NX, 2) of the law, the ``form`` chosen and the held-out error
    of every form tried (``scores``: weighted mean squared log residual)."""

    beta: np.ndarray
    form: str
    scores: dict[str, float]

    def factors(self, fill: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """(…, NX, 2) rate factors for slice fills ``fill`` (…, NX)."""
        ratio = np.maximum(np.asarray(fill, dtype=float), FILL_FLOOR) / reference
        return ratio[..., None] ** self.beta


def steady_windows(table: VelocityTable, steady: SteadyStateRule = SteadyStateRule()) -> np.ndarray:
    """(K,) the windows from the steady-state time on, by ``steady`` on the table's
    hold-up per window (a table of one window is steady). Raises TableError when the
    table never becomes steady."""
    if table.n_windows == 1:  # one window: time-invariant, its own steady state
        return np.ones(1, dtype=bool)
    holdup = (table.count_A + table.count_B).sum(axis=(1, 2))
    start = steady.time(table.t, holdup)
    if start is None:
        raise TableError(
            f"the table's hold-up never becomes steady ({table.n_windows} windows of {table.window_s:g} s, "
            f"rule: two {steady.window_s:g}-s means within {steady.rel_tol:g}); the fill law needs a steady "
            "reference"
        )
    return table.t >= start - 1e-9 * table.window_s


def fill_samples(table: VelocityTable, rates: str, steady: SteadyStateRule = SteadyStateRule()) -> FillSamples:
    """The slice-level fill and axial rates of every window of ``table`` in mode ``rates``
    (the phase model's are measured: its table's measured rates)."""
    mode = "measured" if rates == "phases" else rates
    if mode == "measured" and not table.has_rates:
        raise ConfigError("the fill law in mode 'measured' or 'phases' needs a table with measured rates (schema 2)")
    names = RATE_NAMES[:2] if mode == "measured" else VELOCITY_NAMES[:2]
    counts = table.count_A + table.count_B
    fill = counts.sum(axis=2)
    out = np.full((table.n_windows, table.nx, 2), np.nan)
    weight = np.zeros_like(out)
    exposure = np.zeros_like(out)
    for d, name in enumerate(names):
        values = np.asarray(getattr(table, name), dtype=float)
        if mode == "velocity":
            values = values / table.dx[None, :, None]
        known = np.isfinite(values) & (table.n_samples > 0)
        held = np.where(known, counts, 0.0).sum(axis=2)
        flux = np.where(known, values * counts, 0.0).sum(axis=2)
        out[..., d] = np.where(held > 0, flux / np.where(held > 0, held, 1.0), np.nan)
        weight[..., d] = flux * table.window_s  # moves seen: rate x particle-seconds
        exposure[..., d] = held * table.window_s
    out[:, 0, 1] = np.nan  # the inlet wall: no backward moves to learn from
    return FillSamples(fill, out, weight, exposure, steady_windows(table, steady))


def _window_points(samples: list[FillSamples]) -> tuple[np.ndarray, ...]:
    """Every usable slice-window of the forward rates: (fold, slice, direction, log fill,
    log rate, weight), the folds four consecutive blocks of windows per run.

    The backward rates are left out, so their exponents stay 0: in a filling transient they
    rise with the fill more steeply than the forward ones (exponents 1.2-2.3 on the
    validation baseline), while across the feed library's steady states most move by less
    than a fifth for a quarter more fill. Fitted, they predicted feed x2 from the baseline
    alone with 49 % too much hold-up; without them, 1.9 % (`pbmdem study fill`, before and
    at commit f85a006)."""
    cols: dict[str, list] = {k: [] for k in ("fold", "slice", "dir", "x", "y", "w")}
    for s in samples:
        ok = (
            np.isfinite(s.rates)
            & (s.rates > 0)
            & (s.weight > 0)
            & (s.fill[..., None] >= MIN_FILL_FRACTION * s.steady_fill[None, :, None])
        )
        ok[..., 1] = False
        k, i, d = np.nonzero(ok)
        cols["fold"].append(np.minimum(4 * k // max(s.fill.shape[0], 1), 3))
        cols["slice"].append(i)
        cols["dir"].append(d)
        cols["x"].append(np.log(s.fill[k, i]))
        cols["y"].append(np.log(s.rates[k, i, d]))
        cols["w"].append(s.weight[k, i, d])
    return tuple(np.concatenate(cols[k]) for k in ("fold", "slice", "dir", "x", "y", "w"))


def _steady_points(samples: list[FillSamples]) -> tuple[np.ndarray, ...]:
    """One point per run, slice and direction: its steady fill and its rate over the
    steady windows (moves over particle-seconds), weighted by the moves; the folds are
    the runs."""
    cols: dict[str, list] = {k: [] for k in ("fold", "slice", "dir", "x", "y", "w")}
    for r, s in enumerate(samples):
        rate, moves = s.steady_rates()
        i, d = np.nonzero(rate > 0)
        cols["fold"].append(np.full(i.size, r))
        cols["slice"].append(i)
        cols["dir"].append(d)
        cols["x"].append(np.log(s.steady_fill[i]))
        cols["y"].append(np.log(rate[i, d]))
        cols["w"].append(moves[i, d])
    return tuple(np.concatenate(cols[k]) for k in ("fold", "slice", "dir", "x", "y", "w"))


def _fit(form: str, slc, d, x, y, w, nx: int) -> tuple[np.ndarray, np.ndarray]:
    """(intercepts (NX, 2), exponents (NX, 2)) of ``form`` by weighted least squares: an
    intercept per slice and direction, the exponents shared as the form says."""
    group = slc * 2 + d

    def total(values: np.ndarray) -> np.ndarray:
        # float even for no points (bincount of nothing is an integer array)
        return np.bincount(group, values, nx * 2).astype(float)

    sw = total(w)
    safe = np.where(sw > 0, sw, 1.0)
    xm = total(w * x) / safe
    ym = total(w * y) / safe
    xc, yc = x - xm[group], y - ym[group]
    sxy = total(w * xc * yc)
    sxx = total(w * xc * xc)
    if form == "per-slice":
        b = np.divide(sxy, sxx, out=np.zeros_like(sxy), where=sxx > 0)
    elif form == "per-direction":
        pooled = [sxy[k::2].sum() / sxx[k::2].sum() if sxx[k::2].sum() > 0 else 0.0 for k in range(2)]
        b = np.tile(pooled, nx)
    elif form == "none":
        b = np.zeros(nx * 2)
    else:
        raise ConfigError(f"unknown fill-law form {form!r}; valid: {', '.join(FORMS)}")
    b = np.clip(b, 0.0, MAX_EXPONENT)
    return (ym - b * xm).reshape(nx, 2), b.reshape(nx, 2)


def fit_fill_law(samples: list[FillSamples], forms: tuple[str, ...] = FORMS) -> FillLaw:
    """The law fitted to one or more runs of one vessel and speed (module docstring).

    Several runs: from their steady points (a run's steady fill and rates per slice),
    which is what a change of throughput moves; with every window as a point, the slices'
    window-to-window noise in fill (as large as the fill's change between feeds) would
    flatten the exponents towards 0. The form by leave-one-run-out from
    three runs on; with two, one exponent per slice and direction (nothing is left to hold
    out). One run: from its windows (the filling transient), the form by leaving out
    blocks of windows, the forward rates only (:func:`_window_points` says why)."""
    if not samples:
        raise ConfigError("the fill law needs the windows of at least one DEM run")
    nx = samples[0].fill.shape[1]
    if any(s.fill.shape[1] != nx for s in samples):
        raise ConfigError(
            f"the runs' tables must share NX to fit one fill law, got {[s.fill.shape[1] for s in samples]}"
        )
    fold, slc, d, x, y, w = _steady_points(samples) if len(samples) >= 2 else _window_points(samples)
    if fold.size == 0:
        raise ConfigError("no window has a measured axial rate in a slice at least a quarter full: nothing to fit")
    scores = {}
    if len(samples) != 2:
        for form in forms:
            err = 0.0
            for f in np.unique(fold):
                train = fold != f
                a, b = _fit(form, slc[train], d[train], x[train], y[train], w[train], nx)
                test = ~train
                pred = a[slc[test], d[test]] + b[slc[test], d[test]] * x[test]
                err += float(np.sum(w[test] * (y[test] - pred) ** 2))
            scores[form] = err / float(w.sum())
    best = min(scores, key=scores.get) if scores else "per-slice"
    _a, beta = _fit(best, slc, d, x, y, w, nx)
    return FillLaw(beta, best, scores)


@dataclass(frozen=True)
class FillReference:
    """What the law scales: the steady generator (one schedule entry) of the table in its
    rate mode, its slice hold-ups ``fill`` (NX,) over the steady windows, and where each of
    its entries sits (``moves``: indices of the off-diagonal population moves and the
    discharge; ``move_slice``, ``move_dir`` their source slice and law direction, -1 for
    those it keeps; ``diagonal``: the index of each population's diagonal entry)."""

    schedule: Schedule
    fill: np.ndarray
    n_populations: int
    slice_of: np.ndarray
    moves: np.ndarray
    move_slice: np.ndarray
    move_dir: np.ndarray
    diagonal: np.ndarray

    def values(self, factors: np.ndarray) -> np.ndarray:
        """(W, nnz) generator entries under rate factors (W, NX, 2)."""
        base = self.schedule.vals[0]
        vals = np.broadcast_to(base, (factors.shape[0], base.size)).copy()
        scaled = self.move_dir >= 0
        idx = self.moves[scaled]
        vals[:, idx] = base[idx] * factors[:, self.move_slice[scaled], self.move_dir[scaled]]
        leaving = np.zeros((factors.shape[0], self.n_populations))
        src = self.schedule.cols[self.moves]
        for w in range(factors.shape[0]):
            leaving[w] = np.bincount(src, vals[w, self.moves], self.n_populations)
        vals[:, self.diagonal] = -leaving
        return vals


def steady_table(table: VelocityTable, steady: np.ndarray) -> VelocityTable:
    """One window: every velocity and rate field averaged over the ``steady`` windows,
    weighted by the particles each saw (NaN entries left out; none left: NaN, filled later
    by the mode's rule)."""
    weight = (table.count_A + table.count_B)[steady]
    fields = {}
    for name in (*VELOCITY_NAMES, *(RATE_NAMES if table.has_rates else ())):
        values = np.asarray(getattr(table, name), dtype=float)[steady]
        known = np.isfinite(values)
        total = np.where(known, weight, 0.0).sum(axis=0)
        mean = np.where(known, values * weight, 0.0).sum(axis=0) / np.where(total > 0, total, 1.0)
        fields[name] = np.where(total > 0, mean, np.nan)[None]
    for name in ("count_A", "count_B"):
        fields[name] = np.asarray(getattr(table, name), dtype=float)[steady].mean(axis=0)[None]
    fields["n_samples"] = np.asarray(table.n_samples)[steady].sum(axis=0)[None]
    return table.replace(t=np.array([table.t[np.argmax(steady)]]), **fields)


def fill_reference(table: VelocityTable, rates: str, steady: SteadyStateRule = SteadyStateRule()) -> FillReference:
    """The steady reference of ``table`` in mode ``rates`` for the law."""
    windows = steady_windows(table, steady)
    one = table if rates == "phases" else filled_table(steady_table(table, windows), rates)[0]
    schedule = table_schedule(one, rates)
    if rates != "phases":
        transfer_rates(one, 0, rates)  # raises on anything left unmeasured
    k = n_phases(table, rates)
    n = table.nx * table.ny * k
    slice_of = np.arange(n) // k // table.ny
    rows, cols = schedule.rows, schedule.cols
    moves = np.flatnonzero((cols < n) & (rows != cols) & (rows <= n))
    src = slice_of[cols[moves]]
    dst = np.where(rows[moves] == n, src + 1, slice_of[np.minimum(rows[moves], n - 1)])
    move_dir = np.where(dst == src + 1, 0, np.where(dst == src - 1, 1, -1))
    diagonal = np.full(n, -1)
    on_diag = np.flatnonzero((rows == cols) & (cols < n))
    diagonal[cols[on_diag]] = on_diag
    if np.any(diagonal < 0):
        raise TableError("the generator lacks a diagonal entry for some population: not a rate-mode generator")
    fill = (table.count_A + table.count_B)[windows].sum(axis=2).mean(axis=0)
    if np.any(fill <= 0):
        empty = np.flatnonzero(fill <= 0).tolist()
        raise TableError(f"slices {empty} hold no particles over the steady windows: no fill to scale the rates from")
    return FillReference(schedule, fill, n, slice_of, moves, src, move_dir, diagonal)


@dataclass(frozen=True)
class BulkSolution:
    """The bulk's history: per feed piece (start, end, dense interpolant of the
    populations)."""

    pieces: list

    def slice_fill(self, times: np.ndarray, reference: FillReference) -> np.ndarray:
        """(len(times), NX) slice hold-ups at ``times``."""
        times = np.asarray(times, dtype=float)
        out = np.empty((times.size, reference.fill.size))
        starts = np.array([p[0] for p in self.pieces])
        which = np.clip(np.searchsorted(starts, times, side="right") - 1, 0, len(self.pieces) - 1)
        for q in np.unique(which):
            sel = which == q
            y = self.pieces[q][2](times[sel])  # (n, count)
            out[sel] = np.stack([np.bincount(reference.slice_of, col, reference.fill.size) for col in y.T])
        return out


def _flow_derivative(reference: FillReference, law: FillLaw, rate: np.ndarray, z: np.ndarray, fill: np.ndarray):
    """(n + 1, NX): the derivative of the flows of populations ``z`` with respect to each
    slice's fill, row n the discharge. ``rate`` holds every move's current rate (of
    ``reference.moves``): a move out of slice i scaled by the law changes by
    beta * rate * z[source] / N_i per particle of fill, out of its source, into its target."""
    n, nx = reference.n_populations, reference.fill.size
    s = reference.schedule
    src, dst = s.cols[reference.moves], s.rows[reference.moves]
    slices, direction = reference.move_slice, reference.move_dir
    beta = np.where(direction >= 0, law.beta[slices, np.maximum(direction, 0)], 0.0)
    dflux = beta * rate * z[src] / np.maximum(fill[slices], FILL_FLOOR)
    d = np.zeros((n + 1, nx))
    np.add.at(d, (src, slices), -dflux)
    np.add.at(d, (dst, slices), dflux)
    return d


def _bulk_rhs_and_jacobian(reference: FillReference, law: FillLaw, compiled: bool):
    """The bulk ODE's right-hand side without the feed, and its Jacobian. ``compiled``: the
    right-hand side by :func:`pbm.kernels.bulk_flows` (3 us a call against numpy's 40, for
    an integrator that calls it tens of thousands of times per noisy run), else in numpy
    (for a Newton solve's few dozen calls, which numba's import and load, half a second in a fresh
    process, would cost more than they save)."""
    n = reference.n_populations
    nx = reference.fill.size
    s = reference.schedule
    base = s.vals[0][reference.moves]
    src, dst = s.cols[reference.moves], s.rows[reference.moves]
    internal = dst < n
    kept = reference.move_dir < 0
    slices, direction = reference.move_slice, np.maximum(reference.move_dir, 0)

    def factors(y):
        fill = np.bincount(reference.slice_of, y, nx)
        per_move = np.where(kept, 1.0, law.factors(fill, reference.fill)[slices, direction])
        return fill, base * per_move

    if compiled:
        from pbm import kernels  # see pbm.kernels for why it is imported here

        beta = np.ascontiguousarray(law.beta, dtype=float).ravel()
        scale = np.where(kept, -1, slices * 2 + direction)
        slice_of, ref_fill = np.ascontiguousarray(reference.slice_of), np.ascontiguousarray(reference.fill)
        sink = np.where(internal, dst, -1)

        def flows(y):
            return kernels.bulk_flows(y, slice_of, ref_fill, beta, base, src, sink, scale, n, nx, FILL_FLOOR)

    else:

        def flows(y):
            _, rate = factors(y)
            flux = rate * y[src]
            return np.bincount(dst[internal], flux[internal], n) - np.bincount(src, flux, n)

    def jac(y):
        fill, rate = factors(y)
        j = np.zeros((n, n))
        np.add.at(j, (src, src), -rate)
        np.add.at(j, (dst[internal], src[internal]), rate[internal])
        # the rates' own change with the source slice's fill, spread over its populations
        j += _flow_derivative(reference, law, rate, y, fill)[:n][:, reference.slice_of]
        return j

    return flows, jac


def bulk_bandwidth(reference: FillReference) -> int:
    """How far from the diagonal the bulk Jacobian reaches: the populations are numbered
    slice by slice, a move goes at most one slice, and its rate follows its source slice's
    fill, so a population's flows depend on the populations of its own and the two
    neighbouring slices: within 2 x (populations per slice) - 1 of it."""
    per_slice = reference.n_populations // reference.fill.size
    return min(2 * per_slice - 1, reference.n_populations - 1)


def _packed(j: np.ndarray, band: int) -> np.ndarray:
    """The (2 band + 1, n) band storage LSODA takes: packed[band + r - c, c] = j[r, c]."""
    n = j.shape[0]
    packed = np.zeros((2 * band + 1, n))
    for offset in range(-band, band + 1):  # diagonal r - c = offset
        diagonal = np.diagonal(j, -offset)
        if offset >= 0:
            packed[band + offset, : n - offset] = diagonal
        else:
            packed[band + offset, -offset:] = diagonal
    return packed


def solve_bulk(
    reference: FillReference,
    law: FillLaw,
    feed: np.ndarray,
    feed_times: np.ndarray,
    feed_rates: np.ndarray,
    t_end: float,
    y0: np.ndarray,
    rtol: float = 1e-6,
    atol: float = 1e-6,
) -> BulkSolution:
    """The bulk populations (A + B) under the law: dy/dt = G(fill(y)) y + feed @ rate(t),
    with the total feed rates ``feed_rates[q]`` (2,) [particles/s] in force from
    ``feed_times[q]`` to the next (the first from 0), by :data:`BULK_METHOD` with the
    analytic Jacobian, one piece per feed interval."""
    # imported here: scipy.integrate costs a fifth of a second that the steady solves do not need
    from scipy.integrate import solve_ivp

    rhs, jac = _bulk_rhs_and_jacobian(reference, law, compiled=True)
    n = reference.n_populations
    band = bulk_bandwidth(reference)
    jacobian, banded = (lambda _t, v: jac(v)), {}
    if BULK_METHOD == "LSODA" and band < n - 1:
        # LSODA factorises a banded Jacobian in n band^2 operations, not n^3 / 3: at 20 x 10
        # x 3 phases (n = 600, band 59) 30 times fewer, and every step change refactorises
        banded = {"lband": band, "uband": band}
        jacobian = lambda _t, v: _packed(jac(v), band)  # noqa: E731
    edges = np.concatenate([np.asarray(feed_times, dtype=float), [t_end]])
    y = np.asarray(y0, dtype=float).copy()
    pieces = []
    for q in range(edges.size - 1):
        t0, t1 = max(edges[q], 0.0), min(edges[q + 1], t_end)
        if t1 <= t0:
            continue
        source = feed[:n] @ np.asarray(feed_rates[q], dtype=float)
        sol = solve_ivp(
            lambda _t, v, source=source: rhs(v) + source,
            (t0, t1),
            y,
            method=BULK_METHOD,
            jac=jacobian,
            rtol=rtol,
            atol=atol,
            dense_output=True,
            **banded,
        )
        if not sol.success:
            raise SolverError(f"the bulk under the fill law failed between {t0:.6g} s and {t1:.6g} s: {sol.message}")
        pieces.append((t0, t1, sol.sol))
        y = sol.y[:, -1].copy()
    return BulkSolution(pieces)


def fill_schedule(reference: FillReference, law: FillLaw, bulk: BulkSolution, t_end: float) -> Schedule:
    """The generator schedule of the bulk's fill history: a new entry wherever a rate
    factor has moved by :data:`SCHEDULE_LOG_TOL` in log since the entry began (read every
    :data:`SCHEDULE_SAMPLE_S`, and at every feed change), each entry at the mean of the
    factors it spans."""
    samples = max(2, math.ceil(t_end / SCHEDULE_SAMPLE_S) + 1)
    times = np.union1d(np.linspace(0.0, t_end, samples), [p[0] for p in bulk.pieces])
    logf = np.log(law.factors(bulk.slice_fill(times, reference), reference.fill)).reshape(times.size, -1)
    feed_starts = set(np.round(np.array([p[0] for p in bulk.pieces]) / 1e-9).astype(np.int64).tolist())
    starts = [0]
    anchor = logf[0]
    for s in range(1, times.size - 1):
        if np.abs(logf[s] - anchor).max() > SCHEDULE_LOG_TOL or round(times[s] / 1e-9) in feed_starts:
            starts.append(s)
            anchor = logf[s]
    starts = np.array(starts)
    ends = np.append(starts[1:], times.size - 1)
    # each entry: the factors' mean over its samples, ends included (trapezoid weights)
    means = np.empty((starts.size, logf.shape[1]))
    for e, (a, b) in enumerate(zip(starts, ends)):
        seg = np.exp(logf[a : b + 1])
        dt = np.diff(times[a : b + 1])
        means[e] = (0.5 * (seg[1:] + seg[:-1]) * dt[:, None]).sum(axis=0) / dt.sum() if dt.size else seg[0]
    factors = means.reshape(starts.size, reference.fill.size, 2)
    s = reference.schedule
    return Schedule(times[starts], s.rows, s.cols, reference.values(factors), s.m)


def feed_pieces(rates: np.ndarray, factors: np.ndarray, interval_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(start times, (Q, 2) rates) of the piecewise-constant feed: ``rates`` (2,) times the
    per-interval ``factors`` (n, 2), consecutive equal intervals merged."""
    per = np.asarray(rates, dtype=float)[None, :] * np.asarray(factors, dtype=float)
    change = np.concatenate([[True], np.any(per[1:] != per[:-1], axis=1)])
    keep = np.flatnonzero(change)
    return interval_s * keep.astype(float), per[keep]


def law_for(table: VelocityTable, config: PbmConfig, steady: SteadyStateRule = SteadyStateRule()) -> FillLaw:
    """The law a run under ``config`` follows: ``config.fill_exponents``, else the one
    fitted to ``table``'s own windows."""
    if config.fill_exponents is None:
        return fit_fill_law([fill_samples(table, config.rates, steady)])
    beta = np.asarray(config.fill_exponents, dtype=float)
    if beta.shape != (table.nx, 2):
        raise ConfigError(
            f"fill_exponents has {beta.shape[0]} [forward, backward] pairs; the table has NX = {table.nx} slices"
        )
    return FillLaw(beta, "given", {})


def config_schedule(
    table: VelocityTable,
    config: PbmConfig,
    feed: np.ndarray,
    factors: np.ndarray,
    t_end: float,
    y0: np.ndarray | None = None,
    steady: SteadyStateRule = SteadyStateRule(),
) -> tuple[Schedule | None, FillLaw | None]:
    """The schedule of a run under ``config`` with the per-interval feed ``factors``
    (n, 2), from the bulk ``y0`` (default empty), and its law; (None, None) under
    ``rate_law`` = "table" (the table's own windows)."""
    if config.rate_law != "fill":
        return None, None
    law = law_for(table, config, steady)
    reference = fill_reference(table, config.rates, steady)
    rates = np.array([config.feed_rate_a_per_s, config.feed_rate_b_per_s])
    feed_times, feed_rates = feed_pieces(rates, factors, config.noise_interval_s)
    y0 = np.zeros(reference.n_populations) if y0 is None else y0
    bulk = solve_bulk(reference, law, feed, feed_times, feed_rates, t_end, y0)
    return fill_schedule(reference, law, bulk, t_end), law


def steady_bulk(reference: FillReference, law: FillLaw, source: np.ndarray, tol: float = 1e-10) -> np.ndarray:
    """The bulk populations (n,) at which the law's flows balance the constant feed
    ``source`` (n,) [particles/s]: Newton's method with the analytic Jacobian, started
    from the reference rates' steady state and halving a step that would empty a
    population or raise the residual. Raises SolverError when it does not converge."""
    rhs, jac = _bulk_rhs_and_jacobian(reference, law, compiled=False)
    n = reference.n_populations
    g0 = reference.schedule.dense(0)[:n, :n]
    y = np.maximum(np.linalg.solve(-g0, source), FILL_FLOOR)
    res = rhs(y) + source
    scale = max(float(np.abs(source).sum()), 1.0)
    for _ in range(100):
        if np.abs(res).max() <= tol * scale:
            return y
        step = np.linalg.solve(jac(y), -res)
        size = 1.0
        while size > 1e-6:
            trial = y + size * step
            if np.all(trial > 0):
                trial_res = rhs(trial) + source
                if np.abs(trial_res).max() < np.abs(res).max():
                    y, res = trial, trial_res
                    break
            size *= 0.5
        else:
            break
    raise SolverError(
        f"no steady bulk under the fill law: Newton stalled at a residual of {np.abs(res).max():.3g} particles/s"
    )


@dataclass(frozen=True)
class Linearised:
    """The fill-law PBM linearised about its steady state under a constant feed: the
    deviations x = (dz_A, dz_B) (2n) of the two species obey dx/dt = ``generator`` x +
    ``feed`` dF (dF = (dF_A, dF_B) [particles/s]), and the outlet fluxes are (dq_A, dq_B) =
    ``outlet`` x. ``species`` (2, n) is the steady state of A and B."""

    generator: np.ndarray
    feed: np.ndarray
    outlet: np.ndarray
    species: np.ndarray


def linearised(reference: FillReference, law: FillLaw, feed: np.ndarray, rates: np.ndarray) -> Linearised:
    """:class:`Linearised` at the steady state of the feed ``rates`` (2,) distributed by
    ``feed`` (n, 2). A feeder's noise moves the fill, which moves every rate of its slice
    for both species: dz_s/dt = G* dz_s + D_s S (dz_A + dz_B) + b_s dF_s, with G* the law's
    generator at the steady fill, S the slice sums and D_s the derivative of species s's
    flows with respect to each slice's fill (beta phi r z_s / N_i per move)."""
    n = reference.n_populations
    nx = reference.fill.size
    rates = np.asarray(rates, dtype=float)
    bulk = steady_bulk(reference, law, feed[:n] @ rates)
    fill = np.bincount(reference.slice_of, bulk, nx)
    vals = reference.values(law.factors(fill, reference.fill)[None])[0]
    s = reference.schedule
    g = dense_generator(s.rows, s.cols, vals, s.m)
    g_star, c_star = g[:n, :n], g[n, :n]
    slices = np.zeros((nx, n))
    slices[reference.slice_of, np.arange(n)] = 1.0
    rate = vals[reference.moves]  # each move's rate at the steady fill
    big = np.zeros((2 * n, 2 * n))
    out = np.zeros((2, 2 * n))
    species = np.zeros((2, n))
    for sp in range(2):
        species[sp] = np.linalg.solve(-g_star, feed[:n, sp] * rates[sp])
        d = _flow_derivative(reference, law, rate, species[sp], fill) @ slices  # (n + 1, n)
        block = slice(sp * n, (sp + 1) * n)
        big[block, block] = g_star
        big[block, :n] += d[:n]
        big[block, n:] += d[:n]
        out[sp, block] = c_star
        out[sp, :n] += d[n]
        out[sp, n:] += d[n]
    inputs = np.zeros((2 * n, 2))
    inputs[:n, 0] = feed[:n, 0]
    inputs[n:, 1] = feed[:n, 1]
    return Linearised(big, inputs, out, species)
