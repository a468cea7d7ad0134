"""Hidden mobility phases fitted to every particle's compartment sequence (EM / Baum-Welch).

The measured-rate chain (:mod:`dem.rates`) is Markov on compartments alone, and the DEM's
particles are not: the ones that stay long keep staying (slow bed), the fast ones keep
running (the stream over the bed). Here each particle also carries a hidden phase h =
0..K-1 and the chain is Markov on (compartment, phase): :class:`coupling.phases.PhaseTransport`,
a generator Q with phase-dependent nearest-neighbour rates, phase switching inside each
compartment and an entry-phase distribution per feeder. K = 1 is the measured-rate chain.

Data: :class:`dem.tracking.CompartmentSequences`, every particle's compartment at every
dump (interval Delta) from its first sight until it passes the weir (absorbing) or the
record ends (censored: its likelihood is that of the part seen).

Likelihood. With P = expm(Q Delta), a particle's sequence c_0, c_1, ..., c_T has
probability sum over phase paths of pi(h_0) prod_t P[(c_{t-1}, h_{t-1}), (c_t, h_t)]: a
hidden Markov model whose observation pins the compartment, so the forward-backward
recursion runs over the K phases only, K^2 per particle-step (a general HMM on the
S*K states would cost (S*K)^2). It is vectorised over particles: sequences sorted by
length, step t of all particles still followed is one gather of their (K, K) blocks of P
and one batched product.

EM. E-step: forward-backward gives, for every compartment pair seen between dumps, the
expected number of (c, h) -> (c', h') transitions over one interval (soft counts C) and
the posterior entry phase. M-step: the entry distribution is the mean posterior entry
phase per feeder; Q maximises sum_ab C_ab log P_ab(Q), which is exactly the likelihood of
a discretely observed chain that :func:`dem.rates.fit_pattern` maximises (L-BFGS with the
exact gradient through expm's Frechet derivative, capped at :data:`PHASE_MAX_RATE_X_INTERVAL` / Delta), here on the
(compartment, phase) states, warm-started from the previous iteration. It need not be
maximised: a generalised EM only has to increase it at each M-step. The default M-step
(``m_step="em"``) makes a few updates of the classic EM of a discretely observed
continuous-time chain instead: each rate becomes the expected number of its jumps over the
expected time spent in its source state, both read off the same Frechet derivative that
gives dem.rates its gradient (:func:`_ctmc_em_steps`), one derivative per update. On the
validation run's first 20 s (10 x 10, K = 2, 1.4e5 particle-steps) it reached the
L-BFGS M-step's log-likelihood (20 L-BFGS iterations per M-step) in half the EM
iterations and a tenth of the time per iteration (0.86 s against ~4.7 s); on 10 x 1 both
end at the same likelihood in 32 iterations, 6 s against 26 s. The fit stops when the
log-likelihood gains less than ``tol`` nats per particle-step.

Cost: the forward-backward is a loop over particles and dumps with K^2 work per step.
Vectorised over particles with numpy it took 1.0 s for 3.1e5 particle-steps (K = 2);
compiled with numba (:func:`_fb_kernel_python`, identical to 1e-10) 0.04 s, so numba pays
25x and the E-step is no longer the cost: the matrix exponentials of the M-step are.

Continuous time, not a discrete chain at the dump interval. A discrete (S*K)^2 transition
matrix has a closed-form M-step, but the PBM needs a generator, and the logarithm of a
fitted transition matrix is in general no generator (negative off-diagonal entries, moves
beyond the nearest neighbours), so it has to be projected, which changes the very RTD it
was fitted to reproduce. Fitting Q directly keeps the PBM's structure (nearest-neighbour
moves, conservation) and the likelihood of exactly the model that is solved. Measured
(``workflows.study_phases.compare_time``; fresh validation run, particles in the blender
from 25 to 60 s, 10 x 1 slices, K = 2, 5.5e5 particle-steps): the discrete chain (216 free
entries) scores 0.010 nats per particle-step above the generator (60 rates), and its own
RTD is the generator's (21.75 s / 233 s^2 against 21.74 s / 238 s^2); but its projected
logarithm, the only way to make it a PBM, gives 9.9 s / 69 s^2. The generator is the
model.

Identifiability. Phases have no names: any relabelling fits equally well. After the fit
they are ordered by mobility, slowest first (:func:`coupling.phases.mobility`: forward
axial rate weighted by the expected time each phase spends in each compartment). Starts:
start 0 splits the K = 1 rates into phases whose rates are the K = 1 rates times
geometrically spaced factors (0.3 ... 3), switching at 0.2 /s and a uniform entry; the
others draw the factors, the switching rates and the entry at random (seeded). Every
start is run to convergence and the best kept; the spread of their log-likelihoods is
reported (:attr:`PhaseFit.start_log_likelihoods`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm
from scipy.optimize import brentq

try:  # compiled forward-backward (module docstring, "Cost"); the numpy version is the reference
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; kept importable without it
    numba = None

from coupling import phases as phase_model
from coupling.blas import single_threaded_blas
from coupling.phases import PhaseTransport
from dem import rates as rate_fit
from dem.tracking import CompartmentSequences

#: components of the feed (the sequences' ``component``): rows of the entry distribution
FEEDERS = (1, 2)


#: The number of hidden phases the post-processing fits (:func:`table_with_phases`). On the
#: validation run's steady particles (10 axial slices, ``pbmdem study phases``) the held-out
#: log-likelihood per particle-step rose from -0.672 (K = 1) to -0.607 (K = 2) and -0.601
#: (K = 3), and the PBM's RTD variance from 172 to 238 and 258 s^2 against the DEM's 261
#: [244, 277]: K = 3 is the first inside the interval. K = 4 adds nothing (on the whole
#: validation baseline at a 0.2-s lag: 262.9 s^2 against K = 3's 262.4, K = 2's 231).
#: A fourth phase that is a dead zone (:func:`fit`'s ``stagnant_exit_max``, left at most
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
#: develops more slowly and needs the tighter stop (:func:`fit`).
PHASE_TOL = 1e-5

#: Particles keep their size, and sizes move at different speeds: on a fresh validation
#: run at 300 rpm and feed x1.25 (sizes 5.48 / 6.00 / 6.52 mm) the pooled mean residence
#: times were 19.9, 15.9 and 12.4 s and 1.15 %, 0.19 % and 0 % stayed beyond the horizon
#: (``pbmdem study sizes``). A chain for every size learns that as a phase particles can
#: leave, and its pooled mean came out 1.8 % high (16.31 s against 16.02 [15.78, 16.26]);
#: a chain per size class, fed in the classes' shares, gave 16.25 s, 143.7 s^2, the
#: hold-up and the RTD overlap, all inside. So where the records carry the diameters, each size class with at
#: least this many particles entering in the fit window gets its own chain
#: (:func:`table_with_phases`); a smaller class joins its neighbour in size.
MIN_KIND_PARTICLES = 300
#: ... and at least this share of them: a class of 1 % (the tails of the reduced preset's
#: five classes) adds as many states to every solve as the middle one for 1 % of the
#: particles; joined to its neighbour, the reduced comparison runs on 9 phases, not 15.
MIN_KIND_SHARE = 0.05
#: A chain per size class adds, beside its PHASES moving phases, a dead zone (:func:`fit`'s
#: stagnant phase 0) left at most once per this many Little's-law residence times of the
#: run (:func:`little_residence_time`), its size then held to the class's own Little's law
#: (:func:`zone_held_to_little`). Inside a class the zone no longer has to stand for the
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
#: more distinct diameters than this are grouped into QUANTILE_CLASSES classes of equal counts
MAX_CLASSES = 8
QUANTILE_CLASSES = 5
#: diameters closer than this are one class [m] (the dumps print radii to ~6 digits)
SAME_DIAMETER_M = 1e-7


# ----------------------------------------------------------------------------- data
@dataclass(frozen=True)
class PhaseData:
    """Sequences prepared for the forward-backward pass.

    ``obs`` (P, L) int16: state at each dump since first sight (compartment of the fitted
    grid, ``n_cells`` = discharged, -1 after the sequence ended), rows sorted by
    ``lengths`` descending, so that the particles still followed at step t are the first
    ``active[t]`` rows. ``group`` (P,): the row of the initial phase distribution: 0 =
    entered from feeder A (other types count as A), 1 = from feeder B, 2 + c = already
    inside when the data's window opened, first observed in compartment c (its phase then
    is not the feed's). ``start`` (P,): index of the first dump (absolute, in the
    sequences' ``snapshot_t``); ``last_dump``: index of the last dump of the run.
    """

    obs: np.ndarray
    lengths: np.ndarray
    active: np.ndarray
    group: np.ndarray
    start: np.ndarray
    last_dump: int
    nx: int
    ny: int
    interval_s: float
    #: every sequence, one after the other (int64, row order), and where each starts (P + 1,)
    flat: np.ndarray
    offsets: np.ndarray

    @property
    def n_cells(self) -> int:
        return self.nx * self.ny

    @property
    def n_particles(self) -> int:
        return int(self.obs.shape[0])

    @property
    def n_groups(self) -> int:
        """Rows of the initial distribution: the two feeders and one per compartment."""
        return 2 + self.n_cells

    @property
    def n_steps(self) -> int:
        """Particle-steps (pairs of consecutive dumps) in the data."""
        return int(np.maximum(self.lengths - 1, 0).sum())

    def counts(self, lag: int = 1) -> np.ndarray:
        """(S+1, S+1) counts of state a at one dump and b ``lag`` dumps later (moves of the
        observed chain; a particle discharged before then counts as discharged)."""
        s = self.n_cells
        out = np.zeros((s + 1) * (s + 1), np.int64)
        obs, lengths = self.obs, self.lengths
        ends_out = obs[np.arange(obs.shape[0]), np.maximum(lengths - 1, 0)] == s
        for t in range(obs.shape[1] - 1):
            n = int(self.active[t])
            a = obs[:n, t].astype(np.int64)
            ahead = t + lag
            in_range = lengths[:n] > ahead
            b = np.where(in_range, obs[:n, min(ahead, obs.shape[1] - 1)], np.where(ends_out[:n], s, -1))
            ok = (a < s) & (b >= 0)
            out += np.bincount(a[ok] * (s + 1) + b[ok], minlength=out.size)
        return out.reshape(s + 1, s + 1)


def coarsen(states: np.ndarray, nx: int, ny: int, to_nx: int, to_ny: int) -> np.ndarray:
    """Map flat states of an ``nx`` x ``ny`` grid onto a coarser ``to_nx`` x ``to_ny`` grid
    whose edges are a subset (``nx`` and ``ny`` multiples of ``to_nx`` and ``to_ny``);
    the discharged state and -1 are kept as such."""
    if nx % to_nx or ny % to_ny:
        raise ValueError(f"grid {to_nx}x{to_ny} does not divide {nx}x{ny}: its edges must be the finer grid's")
    s = nx * ny
    cells = np.arange(s)
    # one look-up per state (index 0 = -1, then every cell, then discharged): a gather
    # rather than integer divisions over the whole (particles x dumps) array
    table = np.concatenate(
        [[-1], (cells // ny // (nx // to_nx)) * to_ny + cells % ny // (ny // to_ny), [to_nx * to_ny]]
    ).astype(np.int16)
    states = np.asarray(states)
    if states.size and (states.min() < -1 or states.max() > s):
        raise ValueError(
            f"states must lie in -1 ... {s} (the grid's cells and discharged), got {states.min()} ... {states.max()}"
        )
    return table[states + np.int16(1)] if states.dtype == np.int16 else table[states + 1]


def prepare(
    sequences: CompartmentSequences,
    entered_s: tuple[float, float] | None = None,
    grid: tuple[int, int] | None = None,
    lag: int = 1,
    residents: bool = False,
) -> PhaseData:
    """The sequences of the particles first seen in ``entered_s`` = (t0, t1] [s] (default
    all), on ``grid`` = (NX, NY) (default the sequences' own; a coarser grid must divide
    it), observed every ``lag`` dumps (a particle discharged in between is seen discharged
    at the next observation), as a :class:`PhaseData`. With ``residents`` also the
    particles already inside at t0, from their first dump after t0 on (initial group 2 + c):
    the moves they make in the window are data too, and the only data on how long
    particles stay when the window is shorter than the longest stays. Raises ValueError
    for an empty selection or a lag < 1."""
    if not isinstance(lag, (int, np.integer)) or lag < 1:
        raise ValueError(f"lag = {lag!r}: expected a whole number of dumps >= 1")
    entry_t = sequences.entry_t
    chosen = np.ones(sequences.n_particles, bool)
    if entered_s is not None:
        chosen = _first_seen_in(sequences, entered_s)
    index = np.flatnonzero(chosen)
    if not index.size:
        raise ValueError(
            f"no particle entered in {entered_s} s (sequences span {entry_t.min() if entry_t.size else 'nothing'}"
            f"..{entry_t.max() if entry_t.size else ''} s)"
        )
    obs = sequences.padded(index)
    group = np.where(sequences.component[index] == FEEDERS[1], 1, 0)
    start = sequences.start[index].astype(np.int64)
    if residents and entered_s is not None:
        old_obs, old_start, old_cells = _residents(sequences, entered_s[0])
        width = max(obs.shape[1], old_obs.shape[1])
        obs = np.concatenate([_widen(obs, width), _widen(old_obs, width)])
        group = np.concatenate(
            [group, 2 + coarsen(old_cells, sequences.nx, sequences.ny, *(grid or (sequences.nx, sequences.ny)))]
        )
        start = np.concatenate([start, old_start])
    nx, ny = grid or (sequences.nx, sequences.ny)
    if (nx, ny) != (sequences.nx, sequences.ny):
        obs = coarsen(obs, sequences.nx, sequences.ny, nx, ny)
    if lag > 1:
        obs = _subsample(obs, lag, nx * ny)
    lengths = (obs >= 0).sum(axis=1)
    order = np.argsort(-lengths, kind="stable")
    obs, lengths = obs[order], lengths[order]
    active = np.searchsorted(-lengths, -np.arange(obs.shape[1]), side="left")  # rows with length > t
    # with a lag, dump indices count observations: start and last dump in units of the lag
    return PhaseData(
        obs=obs,
        lengths=lengths,
        active=active,
        group=group[order].astype(np.int64),
        start=start[order] // lag,
        last_dump=int(sequences.snapshot_t.size - 1) // lag,
        nx=int(nx),
        ny=int(ny),
        interval_s=float(sequences.interval_s) * lag,
        flat=obs[obs >= 0].astype(np.int64),
        offsets=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
    )


def _widen(obs: np.ndarray, width: int) -> np.ndarray:
    return (
        obs
        if obs.shape[1] == width
        else np.concatenate([obs, np.full((obs.shape[0], width - obs.shape[1]), -1, obs.dtype)], axis=1)
    )


def _residents(sequences: CompartmentSequences, t0_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(padded sequences from the first dump after ``t0_s`` on, that dump's index, the
    compartment there) of the particles first seen at or before ``t0_s`` and still in a
    compartment at that dump."""
    first = int(np.searchsorted(sequences.snapshot_t, t0_s + 1e-6 * sequences.interval_s, side="right"))
    entered_before = np.flatnonzero(sequences.start < first)
    ends = sequences.start[entered_before] + sequences.lengths[entered_before]  # one past the last dump
    alive = entered_before[ends > first]
    if not alive.size:
        return np.zeros((0, 1), np.int16), np.zeros(0, np.int64), np.zeros(0, np.int16)
    full = sequences.padded(alive)
    shift = first - sequences.start[alive].astype(np.int64)
    width = full.shape[1] - int(shift.min())
    cols = np.arange(width)[None, :] + shift[:, None]
    obs = np.where(cols < full.shape[1], full[np.arange(alive.size)[:, None], np.minimum(cols, full.shape[1] - 1)], -1)
    keep = (obs[:, 0] >= 0) & (obs[:, 0] < sequences.n_cells)  # not already discharged there
    return obs[keep].astype(np.int16), np.full(int(keep.sum()), first, np.int64), obs[keep, 0].astype(np.int16)


def _subsample(obs: np.ndarray, lag: int, n_cells: int) -> np.ndarray:
    """Every ``lag``-th column of the padded sequences, a discharge in between moved to the
    next kept column."""
    lengths = (obs >= 0).sum(axis=1)
    last = obs[np.arange(obs.shape[0]), np.maximum(lengths - 1, 0)]
    out = obs[:, ::lag].copy()
    out[out == n_cells] = -1
    discharged = (last == n_cells) & (lengths > 0)
    column = -(-(lengths - 1) // lag)  # ceil((length - 1) / lag): first kept column at or after the discharge
    if out.shape[1] <= column.max(initial=0):
        out = np.concatenate([out, np.full((out.shape[0], column.max() + 1 - out.shape[1]), -1, out.dtype)], axis=1)
    out[np.flatnonzero(discharged), column[discharged]] = n_cells
    return out


# ----------------------------------------------------------------------------- E-step
@dataclass(frozen=True)
class Expectations:
    """What one forward-backward pass gives: ``log_likelihood`` [nats] of the data,
    ``counts`` (S*K+1, S*K+1) expected (compartment, phase) transitions per interval,
    ``entry`` (G, K) summed posterior initial phases per initial group (:class:`PhaseData`)."""

    log_likelihood: float
    counts: np.ndarray
    entry: np.ndarray


def _blocks(p: np.ndarray, n_cells: int, k: int) -> np.ndarray:
    """P as (S, K, S+1, K): [c, h, c', h'] = P[(c, h), (c', h')], and [c, h, S, 0] the
    discharge (the other phases of the discharged "compartment" are empty)."""
    s = n_cells
    out = np.zeros((s, k, s + 1, k))
    out[:, :, :s, :] = p[: s * k, : s * k].reshape(s, k, s, k)
    out[:, :, s, 0] = p[: s * k, s * k].reshape(s, k)
    return out


def forward_backward(
    p: np.ndarray, entry: np.ndarray, data: PhaseData, k: int, backward: bool = True, compiled: bool | None = None
) -> Expectations:
    """Forward-backward on every sequence of ``data`` for the transition matrix ``p``
    (S*K+1, S*K+1) over one dump interval and ``entry`` (2, K). With ``backward`` False
    only the log-likelihood is computed (counts and entry are zeros). ``compiled``: use
    the numba kernel (default: when numba is there) or the vectorised numpy version (the
    reference it is tested against)."""
    if compiled is None:
        compiled = numba is not None
    if compiled:
        return _forward_backward_compiled(p, entry, data, k, backward)
    s, obs, active = data.n_cells, data.obs, data.active
    blocks = _blocks(p, s, k)
    m = s * k + 1
    n_steps = obs.shape[1]
    alphas = [entry[data.group]]  # (P, K); emission 1: the first compartment is given
    scales = [np.ones(data.n_particles)]
    log_likelihood = 0.0
    for t in range(1, n_steps):
        n = int(active[t])
        block = blocks[obs[:n, t - 1], :, obs[:n, t], :]  # (n, K, K)
        a = np.einsum("nk,nkl->nl", alphas[-1][:n], block)
        c = a.sum(axis=1)
        if np.any(c <= 0):
            bad = int(np.flatnonzero(c <= 0)[0])
            raise FloatingPointError(
                f"a move {int(obs[bad, t - 1])} -> {int(obs[bad, t])} has probability 0 under the "
                "model (a jump the nearest-neighbour pattern cannot make within a dump interval?)"
            )
        a /= c[:, None]
        log_likelihood += float(np.log(c).sum())
        alphas.append(a)
        scales.append(c)
    if not backward:
        return Expectations(log_likelihood, np.zeros((m, m)), np.zeros((entry.shape[0], k)))
    flat = np.zeros(m * m)
    h_from = np.arange(k)[:, None]
    h_to = np.arange(k)[None, :]
    beta = np.ones((int(active[n_steps - 1]), k))
    pending_index, pending_weight, pending = [], [], 0
    for t in range(n_steps - 1, 0, -1):
        n = int(active[t])
        a_prev, b_now = obs[:n, t - 1].astype(np.int64), obs[:n, t].astype(np.int64)
        block = blocks[a_prev, :, b_now, :]
        xi = alphas[t - 1][:n, :, None] * block * (beta / scales[t][:, None])[:, None, :]
        src = a_prev[:, None, None] * k + h_from[None]
        dst = np.where(b_now[:, None, None] == s, s * k, b_now[:, None, None] * k + h_to[None])
        pending_index.append((src * m + dst).ravel())
        pending_weight.append(xi.ravel())
        pending += xi.size
        if pending > 2_000_000:
            flat += np.bincount(np.concatenate(pending_index), np.concatenate(pending_weight), minlength=m * m)
            pending_index, pending_weight, pending = [], [], 0
        new_beta = np.einsum("nkl,nl->nk", block, beta) / scales[t][:, None]
        previous = int(active[t - 1])
        beta = np.ones((previous, k))
        beta[:n] = new_beta
    if pending_index:
        flat += np.bincount(np.concatenate(pending_index), np.concatenate(pending_weight), minlength=m * m)
    gamma0 = alphas[0] * beta
    gamma0 /= gamma0.sum(axis=1, keepdims=True)
    entry_sums = np.zeros((entry.shape[0], k))
    np.add.at(entry_sums, data.group, gamma0)
    return Expectations(log_likelihood, flat.reshape(m, m), entry_sums)


def _fb_kernel_python(blocks, entry, flat, offsets, feeder, backward):
    """Forward-backward particle by particle (compiled by numba): per step K^2 products,
    the blocks of P gathered by the observed pair. Returns (log-likelihood, counts
    (S, K, S+1, K), entry sums (2, K)); a move of probability 0 returns -inf."""
    k = entry.shape[1]
    s = blocks.shape[0]
    counts = np.zeros((s, k, s + 1, k))
    entry_sums = np.zeros((entry.shape[0], k))
    longest = 1
    for p in range(offsets.size - 1):
        longest = max(longest, offsets[p + 1] - offsets[p])
    alpha = np.empty((longest, k))
    scale = np.empty(longest)
    beta = np.empty(k)
    new_beta = np.empty(k)
    total = 0.0
    for p in range(offsets.size - 1):
        a0, length = offsets[p], offsets[p + 1] - offsets[p]
        f = feeder[p]
        for h in range(k):
            alpha[0, h] = entry[f, h]
        scale[0] = 1.0
        for t in range(1, length):
            a, b = flat[a0 + t - 1], flat[a0 + t]
            c = 0.0
            for g in range(k):
                v = 0.0
                for h in range(k):
                    v += alpha[t - 1, h] * blocks[a, h, b, g]
                alpha[t, g] = v
                c += v
            if c <= 0.0:
                return -np.inf, counts, entry_sums
            for g in range(k):
                alpha[t, g] /= c
            scale[t] = c
            total += np.log(c)
        if not backward:
            continue
        for h in range(k):
            beta[h] = 1.0
        for t in range(length - 1, 0, -1):
            a, b = flat[a0 + t - 1], flat[a0 + t]
            c = scale[t]
            for h in range(k):
                v = 0.0
                for g in range(k):
                    w = blocks[a, h, b, g] * beta[g] / c
                    counts[a, h, b, g] += alpha[t - 1, h] * w
                    v += w
                new_beta[h] = v
            for h in range(k):
                beta[h] = new_beta[h]
        norm = 0.0
        for h in range(k):
            norm += alpha[0, h] * beta[h]
        for h in range(k):
            entry_sums[f, h] += alpha[0, h] * beta[h] / norm
    return total, counts, entry_sums


_fb_kernel = numba.njit(cache=True, nogil=True)(_fb_kernel_python) if numba is not None else None


def _forward_backward_compiled(
    p: np.ndarray, entry: np.ndarray, data: PhaseData, k: int, backward: bool
) -> Expectations:
    s = data.n_cells
    blocks = _blocks(p, s, k)
    log_likelihood, counts4, entry_sums = _fb_kernel(
        blocks, np.ascontiguousarray(entry, dtype=np.float64), data.flat, data.offsets, data.group, backward
    )
    if not np.isfinite(log_likelihood):
        raise FloatingPointError(
            "a move has probability 0 under the model (a jump the nearest-neighbour pattern "
            "cannot make within a dump interval?)"
        )
    m = s * k + 1
    counts = np.zeros((m, m))
    counts[: s * k, : s * k] = counts4[:, :, :s, :].reshape(s * k, s * k)
    counts[: s * k, s * k] = counts4[:, :, s, 0].reshape(s * k)
    return Expectations(float(log_likelihood), counts, entry_sums)


# ----------------------------------------------------------------------------- the model
@dataclass(frozen=True)
class CkTest:
    """Chapman-Kolmogorov test of a fitted chain on the observed axial slices.

    For start points in slice i (every particle-dump of the data there, whose particle is
    followed, or discharged, ``lags_s[n]`` later): ``observed[n, i, j]`` the fraction in
    slice j then (j = NX: discharged), ``predicted[n, i, j]`` the model's probability,
    starting from the data's compartments in slice i with the model's steady phase
    distribution in each; ``standard_error`` of the observed fractions (particles as
    clusters: a particle's start points are not independent); ``particles``: how many
    particles the start points of (lag, slice) come from; ``z`` = |predicted - observed| /
    the standard error, floored at the binomial one of the predicted probability over those
    particles (a cluster estimate is 0 for an outcome never observed, however unlikely).
    ``passed``: max z <= ``z_limit`` over the entries with at least ``min_starts`` starts.
    """

    lags_s: np.ndarray
    observed: np.ndarray
    predicted: np.ndarray
    standard_error: np.ndarray
    starts: np.ndarray
    particles: np.ndarray
    z_limit: float

    @property
    def z(self) -> np.ndarray:
        p = np.clip(self.predicted, 0.0, 1.0)
        floor = np.sqrt(p * (1 - p) / np.maximum(self.particles, 1)[:, :, None])
        floor = np.maximum(floor, 1.0 / np.maximum(self.starts, 1)[:, :, None])
        return np.abs(self.predicted - self.observed) / np.maximum(self.standard_error, floor)

    def max_z(self, min_starts: int = 200) -> float:
        use = self.starts >= min_starts
        return float(self.z[use].max()) if use.any() else float("nan")

    def max_abs_error(self, min_starts: int = 200) -> float:
        use = self.starts >= min_starts
        return float(np.abs(self.predicted - self.observed)[use].max()) if use.any() else float("nan")

    @property
    def passed(self) -> bool:
        return bool(self.max_z() <= self.z_limit)


@dataclass(frozen=True)
class PhaseFit:
    """A fitted hidden-phase chain and how the fit went.

    ``transport``: the model (:class:`coupling.phases.PhaseTransport`, phases slowest
    first); ``log_likelihood`` [nats] of the training data; ``n_particles``, ``n_steps``
    (particle-steps) of the training data; ``iterations`` (EM) and ``converged`` of the
    best start; ``start_log_likelihoods``: the final log-likelihood of every start (their
    spread says how multimodal the likelihood is); ``wall_time_s`` of the whole fit.
    """

    transport: PhaseTransport
    log_likelihood: float
    n_particles: int
    n_steps: int
    iterations: int
    converged: bool
    start_log_likelihoods: tuple[float, ...] = ()
    wall_time_s: float = float("nan")
    occupancy: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def n_phases(self) -> int:
        return self.transport.n_phases

    @property
    def interval_s(self) -> float:
        return self.transport.interval_s

    def generator(self) -> np.ndarray:
        """Q (S*K+1, S*K+1) [1/s], row = from; last state discharged."""
        return self.transport.generator()

    def entry_distribution(self) -> np.ndarray:
        """(2, K): probability of entering in each phase, feed A and feed B."""
        return self.transport.entry

    def initial_distribution(self, data: PhaseData) -> np.ndarray:
        """(2 + S, K): :func:`initial_distribution` of this model for ``data``."""
        return initial_distribution(self.transport, data)

    def n_parameters(self) -> int:
        """Free parameters: every allowed move's rate and K-1 entry probabilities per feeder."""
        moves = phase_model.transitions(self.transport.nx, self.transport.ny, self.n_phases)
        return int(sum(src.size for src, _dst, _c in moves.values()) + 2 * (self.n_phases - 1))

    def score(self, data: PhaseData) -> float:
        """Log-likelihood [nats] of ``data`` (e.g. held out) under this model."""
        check_grid(self.transport, data)
        p = expm(self.generator() * data.interval_s)
        return forward_backward(
            p, initial_distribution(self.transport, data), data, self.n_phases, backward=False
        ).log_likelihood

    def implied_timescales(self, count: int = 5) -> np.ndarray:
        """The ``count`` longest relaxation times [s] of the chain, -1/Re(lambda) over the
        eigenvalues of Q restricted to the transient states (a continuous-time chain's are
        the same at every lag; the observed chain's, fitted at growing lags, are not when
        the compartments alone are not Markovian)."""
        q = self.generator()[:-1, :-1]
        eigenvalues = np.linalg.eigvals(q)
        times = np.sort(-1.0 / eigenvalues.real[eigenvalues.real < 0])[::-1]
        return times[:count]

    def steady_occupancy(self, data: PhaseData) -> np.ndarray:
        """(S, K): expected particles in each (compartment, phase) at steady state for a
        feed of one particle per second entering where ``data``'s particles were first seen,
        in the entry phases [particles per (particle/s)]."""
        return steady_occupancy(self.transport, first_compartments(data))

    def chapman_kolmogorov(
        self, data: PhaseData, lags: tuple[int, ...] = (10, 20, 50, 100), z_limit: float = 4.0
    ) -> CkTest:
        """:class:`CkTest` at ``lags`` (in dumps) on ``data``'s particle-dumps."""
        return chapman_kolmogorov(self.transport, data, lags, z_limit)


def check_grid(model: PhaseTransport, data: PhaseData) -> None:
    if (model.nx, model.ny) != (data.nx, data.ny):
        raise ValueError(f"model grid {model.nx}x{model.ny} differs from the data's {data.nx}x{data.ny}")


def initial_distribution(model: PhaseTransport, data: PhaseData) -> np.ndarray:
    """(2 + S, K) initial phase distribution of each group of :class:`PhaseData`: the
    entry distributions of the two feeders, then for the particles already inside, the
    model's steady phase distribution in their first compartment (what the EM starts
    from and what a held-out score assumes; the EM refits those rows).

    A model ``r`` times finer along x than the data (:func:`fit`'s ``refine``) hides the
    sub-slice too: (2 + S, r K) over (sub-slice, phase), the feed spread evenly over the
    sub-slices of the compartment it is first seen in."""
    refine = _refinement(model, data)
    first = np.maximum(first_compartments(data), 0.0) + 1e-12
    if refine == 1:
        occupancy = steady_occupancy(model, first)
        entry = model.entry
    else:
        occupancy = steady_occupancy(model, np.repeat(first / refine, refine, axis=1)).reshape(data.n_cells, -1)
        entry = np.repeat(model.entry[:, None, :] / refine, refine, axis=1).reshape(2, -1)
    given_cell = occupancy / np.maximum(occupancy.sum(axis=1, keepdims=True), 1e-300)
    return np.vstack([entry, given_cell])


def _refinement(model: PhaseTransport, data: PhaseData) -> int:
    """How many of ``model``'s axial slices make one of ``data``'s (1: the same grid). A
    finer model has its states ordered (slice, phase), so the states of one observed
    slice, (sub-slice, phase), are contiguous: they are the hidden state there."""
    if (model.nx, model.ny) == (data.nx, data.ny):
        return 1
    if data.ny != 1 or model.ny != 1 or model.nx % data.nx:
        raise ValueError(
            f"model grid {model.nx}x{model.ny} neither equals the data's {data.nx}x{data.ny} nor refines its "
            "slices (NY = 1 and a multiple of its NX)"
        )
    return model.nx // data.nx


def first_compartments(data: PhaseData) -> np.ndarray:
    """(2, S): how many particles of each feeder were first seen in each compartment."""
    first = data.obs[:, 0].astype(np.int64)
    return np.stack(
        [np.bincount(first[data.group == f], minlength=data.n_cells)[: data.n_cells] for f in (0, 1)]
    ).astype(float)


def steady_occupancy(model: PhaseTransport, entering: np.ndarray) -> np.ndarray:
    """(S, K) steady particles per (compartment, phase) for ``entering`` (2, S) particles/s
    of feed A and B into each compartment, in the model's entry phases: the solution of
    0 = feed + N Q on the transient states."""
    k, s = model.n_phases, model.n_cells
    feed = np.zeros(s * k)
    for f in (0, 1):
        feed += (entering[f][:, None] * model.entry[f][None, :]).ravel()
    q = model.generator()[:-1, :-1]
    return np.linalg.solve(-q.T, feed).reshape(s, k)


def chapman_kolmogorov(model: PhaseTransport, data: PhaseData, lags: tuple[int, ...], z_limit: float = 4.0) -> CkTest:
    """The Chapman-Kolmogorov test (:class:`CkTest`) of ``model`` on ``data``.

    Start points: every particle-dump at index t of a particle's sequence, in a
    compartment, such that the run lasts at least ``lag`` dumps more (so that no outcome is
    censored by the end of the run); a sequence censored otherwise (lost particle) before
    t + lag is left out. Outcome: the slice at t + lag, or discharged."""
    check_grid(model, data)
    s, nx, ny, k = data.n_cells, data.nx, data.ny, model.n_phases
    occupancy = steady_occupancy(model, first_compartments(data))
    phase_given_cell = occupancy / np.maximum(occupancy.sum(axis=1, keepdims=True), 1e-300)
    q = model.generator()
    slice_of = np.append(np.arange(s) // ny, nx)  # discharged -> column NX
    lag_array = np.asarray(lags, np.int64)
    cell_counts, sums, n_squared, particles = _ck_counts(
        data.flat, data.offsets, data.start.astype(np.int64), int(data.last_dump), slice_of, lag_array, nx, s
    )
    aggregate = np.zeros((s * k + 1, nx + 1))
    aggregate[np.arange(s * k + 1), np.append(np.repeat(slice_of[:-1], k), nx)] = 1.0
    # the model from each compartment in slice i, its phases at their steady distribution there
    predicted = np.zeros((len(lags), nx, nx + 1))
    for n, lag in enumerate(lags):
        from_cell = (expm(q * lag * data.interval_s) @ aggregate)[:-1].reshape(s, k, nx + 1)
        from_cell = (from_cell * phase_given_cell[:, :, None]).sum(axis=1).reshape(nx, ny, nx + 1)
        predicted[n] = np.einsum("ic,icj->ij", cell_counts[n].reshape(nx, ny), from_cell)
    starts = cell_counts.reshape(len(lags), nx, ny).sum(axis=2)
    safe = np.maximum(starts, 1.0)[:, :, None]
    predicted /= safe
    # cluster standard error (particles as clusters): with h[p, j] a particle's starts in
    # slice i that end in j and n_p = sum_j h[p, j], sqrt(sum_p (h[p, j] - n_p f_j)^2) / N,
    # expanded into the sums the kernel accumulates
    observed = sums[:, 0] / safe
    squares = sums[:, 1] - 2.0 * observed * sums[:, 2] + observed**2 * n_squared[:, :, None]
    error = np.sqrt(np.maximum(squares, 0.0)) / safe
    return CkTest(
        np.asarray(lags, float) * data.interval_s, observed, predicted, error, starts, particles, float(z_limit)
    )


def _ck_counts_python(flat, offsets, start, last_dump, slice_of, lags, nx, s):
    """The Chapman-Kolmogorov test's tallies in one pass over the sequences (compiled by
    numba), per lag n: start points per compartment (n, S); and over the particles, per
    start slice i and end slice j, sum_p h, sum_p h^2 and sum_p h n_p (n, 3, NX, NX+1),
    sum_p n_p^2 and the number of particles with a start in i (n, NX), where h[p, j] counts
    particle p's start points in i that end in j and n_p = sum_j h[p, j]."""
    n_lags = lags.size
    width = nx + 1
    cell_counts = np.zeros((n_lags, s))
    sums = np.zeros((n_lags, 3, nx, width))
    n_squared = np.zeros((n_lags, nx))
    particles = np.zeros((n_lags, nx))
    hits = np.zeros((nx, width))
    per_slice = np.zeros(nx)
    for p in range(offsets.size - 1):
        a0, length = offsets[p], offsets[p + 1] - offsets[p]
        discharged = length > 0 and flat[a0 + length - 1] == s
        for n in range(n_lags):
            lag = lags[n]
            hits[:] = 0.0
            per_slice[:] = 0.0
            for t in range(length):
                if start[p] + t + lag > last_dump:  # the run ends first: censored, and so are later t
                    break
                c = flat[a0 + t]
                if c < 0 or c >= s:
                    continue
                if t + lag < length:
                    outcome = flat[a0 + t + lag]
                elif discharged:
                    outcome = s
                else:  # lost before t + lag
                    continue
                if outcome < 0:
                    continue
                i = slice_of[c]
                hits[i, slice_of[outcome]] += 1.0
                per_slice[i] += 1.0
                cell_counts[n, c] += 1.0
            for i in range(nx):
                if per_slice[i] == 0.0:
                    continue
                particles[n, i] += 1.0
                n_squared[n, i] += per_slice[i] * per_slice[i]
                for j in range(width):
                    h = hits[i, j]
                    sums[n, 0, i, j] += h
                    sums[n, 1, i, j] += h * h
                    sums[n, 2, i, j] += h * per_slice[i]
    return cell_counts, sums, n_squared, particles


_ck_counts = numba.njit(cache=True, nogil=True)(_ck_counts_python) if numba is not None else _ck_counts_python


# ----------------------------------------------------------------------------- the fit
def _moves(nx: int, ny: int, k: int):
    moves = phase_model.transitions(nx, ny, k)
    return moves, {name: src.size for name, (src, _d, _c) in moves.items()}


def _move_rates(model: PhaseTransport) -> dict[str, np.ndarray]:
    """The rate of every move of :func:`coupling.phases.transitions`, read off ``model``."""
    q = model.generator()
    return {
        name: q[src, dst]
        for name, (src, dst, _c) in phase_model.transitions(model.nx, model.ny, model.n_phases).items()
    }


def _initial(
    base: PhaseTransport,
    k: int,
    rng: np.random.Generator | None,
    max_rate_x_interval: float = PHASE_MAX_RATE_X_INTERVAL,
) -> PhaseTransport:
    """A K-phase start from the one-phase fit ``base`` (module docstring, "Starts")."""
    nx, ny = base.nx, base.ny
    if rng is None:
        factors = np.geomspace(0.3, 3.0, k) if k > 1 else np.ones(1)
        switch = np.full((k, k), 0.2)
        entry = np.full(k, 1.0 / k)
    else:
        factors = np.sort(np.exp(rng.normal(0.0, 0.8, k)))
        switch = np.exp(rng.uniform(np.log(0.02), np.log(1.0), (k, k)))
        entry = rng.dirichlet(np.ones(k))
    rates = np.stack([base.rates[0] * f for f in factors])
    if rng is not None:
        rates = rates * np.exp(rng.normal(0.0, 0.1, rates.shape))
    switching = np.broadcast_to(switch[:, :, None, None], (k, k, nx, ny)).copy()
    switching[np.arange(k), np.arange(k)] = 0.0
    cap = max_rate_x_interval / base.interval_s
    return PhaseTransport(np.minimum(rates, cap), switching, np.stack([entry, entry]), base.interval_s)


def _stagnant_projection(moves: dict, exit_max: float):
    """The constraints of a stagnant phase 0 on the rates of ``moves`` (their order): it
    makes no move, and leaves each compartment at ``exit_max`` [1/s] at most in all. The
    update of each rate is the maximiser of jumps log r - r dwell, separately, so under
    a bound on their sum the rates leaving one compartment are scaled down together."""
    names = list(moves)
    bounds = np.cumsum([0] + [moves[name][0].size for name in names])
    span = {name: slice(int(a), int(b)) for name, a, b in zip(names, bounds[:-1], bounds[1:])}
    still = [span[n] for n in names if not n.startswith("switch/") and n.endswith("/0")]
    leave = [span[n] for n in names if n.startswith("switch/0/")]

    def project(rates: np.ndarray) -> np.ndarray:
        rates = rates.copy()
        for part in still:
            rates[part] = 0.0
        if leave:
            total = np.sum([rates[part] for part in leave], axis=0)
            scale = np.minimum(1.0, exit_max / np.maximum(total, 1e-300))
            for part in leave:
                rates[part] *= scale
        return rates

    return project


def _with_stagnant(mobile: PhaseTransport, exit_max: float) -> PhaseTransport:
    """A start with a stagnant phase 0 before the phases of ``mobile``: no moves, entered
    from every other phase at 1e-3 /s, left at half of ``exit_max`` in all, never entered
    from the feed."""
    k = mobile.n_phases + 1
    rates = np.concatenate([np.zeros((1,) + mobile.rates.shape[1:]), mobile.rates])
    switching = np.zeros((k, k, mobile.nx, mobile.ny))
    switching[1:, 1:] = mobile.switching
    switching[1:, 0] = 1e-3
    switching[0, 1:] = 0.5 * exit_max / (k - 1)
    entry = np.concatenate([np.zeros((2, 1)), mobile.entry], axis=1)
    return PhaseTransport(rates, switching, entry, mobile.interval_s)


def refined(model: PhaseTransport, refine: int) -> PhaseTransport:
    """``model`` on ``refine`` slices per slice (NY = 1): each slice's moves at ``refine``
    times its rates, so that a particle crosses a slice as fast as before, and no backward
    move out of the first sub-slice; switching and entry as they were. A start for
    :func:`fit`'s ``refine``, not a model of its own: the EM refits every rate."""
    if model.ny != 1 or refine < 1:
        raise ValueError(f"refine {refine!r} of a {model.nx}x{model.ny} model: expected NY = 1 and refine >= 1")
    rates = np.repeat(model.rates, refine, axis=2) * refine
    rates[:, 1, 0] = 0.0
    switching = np.repeat(model.switching, refine, axis=2)
    return PhaseTransport(rates, switching, model.entry, model.interval_s)


def _ordered(model: PhaseTransport, occupancy: np.ndarray) -> tuple[PhaseTransport, np.ndarray]:
    """``model`` with its phases sorted by :func:`coupling.phases.mobility`, slowest first,
    and ``occupancy`` (K, NX, NY) sorted alike."""
    order = np.argsort(phase_model.mobility(model.rates, occupancy), kind="stable")
    return (
        PhaseTransport(
            model.rates[order], model.switching[order][:, order], model.entry[:, order], model.interval_s, model.attrs
        ),
        occupancy[order],
    )


def _ctmc_em_steps(
    counts: np.ndarray,
    moves: dict,
    start: dict[str, np.ndarray],
    interval_s: float,
    steps: int,
    max_rate_x_interval: float = PHASE_MAX_RATE_X_INTERVAL,
    project=None,
) -> np.ndarray:
    """``steps`` EM updates of the rates of a chain observed at ``counts`` (expected
    transitions per interval): each move's rate becomes its expected number of jumps over
    the expected time spent in its source state, both read off the gradient of
    :func:`dem.rates.log_likelihood` (for a move i -> j, rate * dL/dQ_ij is the expected
    number of jumps and dL/dQ_ii the expected time in i, given the endpoints of every
    interval). One Frechet derivative per update, against tens of evaluations for L-BFGS;
    every update increases the likelihood. Capped at ``max_rate_x_interval`` / interval;
    ``project`` (rates -> rates, the moves' order) imposes constraints after each update
    (:func:`_stagnant_projection`)."""
    src = np.concatenate([t[0] for t in moves.values()])
    dst = np.concatenate([t[1] for t in moves.values()])
    rates = np.concatenate([np.asarray(start[key], dtype=float) for key in moves])
    # EM never moves a rate off 0: start every move slightly off it
    rates = np.maximum(rates, 1e-4 / interval_s)
    cap = max_rate_x_interval / interval_s
    n = counts.shape[0]
    for _ in range(steps):
        q = np.zeros((n, n))
        q[src, dst] = rates
        q[np.arange(n), np.arange(n)] = -q.sum(axis=1)
        _value, d_q = rate_fit.log_likelihood(q, counts, interval_s)
        dwell = d_q[src, src]
        jumps = rates * d_q[src, dst]
        rates = np.where(dwell > 0, np.minimum(jumps / np.maximum(dwell, 1e-300), cap), rates)
        if project is not None:
            rates = project(rates)
    return rates


def _em(
    model: PhaseTransport,
    data: PhaseData,
    max_iterations: int,
    tol: float,
    m_step_iterations: int,
    m_step: str = "em",
    max_rate_x_interval: float = PHASE_MAX_RATE_X_INTERVAL,
    stagnant_exit_max: float | None = None,
) -> tuple[PhaseTransport, float, int, bool, np.ndarray]:
    """EM from ``model`` (module docstring); returns the model, its log-likelihood, the
    iterations, whether it converged and the expected time per (compartment, phase) of
    the model's grid, which may refine the data's slices (:func:`fit`'s ``refine``).
    ``stagnant_exit_max``: phase 0 is stagnant (:func:`fit`)."""
    nx, ny, k, interval = model.nx, model.ny, model.n_phases, data.interval_s
    hidden = _refinement(model, data) * k  # hidden states per observed compartment
    moves, _sizes = _moves(nx, ny, k)
    project = None if stagnant_exit_max is None else _stagnant_projection(moves, stagnant_exit_max)
    previous = -math.inf
    converged = False
    dwell = np.zeros(nx * ny * k)
    iteration = 0
    initial = initial_distribution(model, data)
    for iteration in range(1, max_iterations + 1):  # noqa: B007 -- the count is reported after the loop
        p = expm(model.generator() * interval)
        expected = forward_backward(p, initial, data, hidden)
        # the likelihood is that of the model before this M-step
        gain = (expected.log_likelihood - previous) / max(data.n_steps, 1)
        if gain < tol:
            converged = True
            break
        previous = expected.log_likelihood
        updated = expected.entry / np.maximum(expected.entry.sum(axis=1, keepdims=True), 1e-300)
        missing = expected.entry.sum(axis=1) <= 0  # a group without particles keeps its row
        initial = np.where(missing[:, None], initial, updated)
        entry = initial[:2].reshape(2, -1, k).sum(axis=1)  # over the sub-slices it entered
        counts = expected.counts.copy()
        counts[-1] = 0.0
        if m_step == "lbfgs":
            values, _fit = rate_fit.fit_pattern(counts, moves, _move_rates(model), interval, m_step_iterations)
        else:
            values = _ctmc_em_steps(
                counts, moves, _move_rates(model), interval, m_step_iterations, max_rate_x_interval, project
            )
        split = np.cumsum([src.size for src, _d, _c in moves.values()])[:-1]
        per_move = dict(zip(moves, np.split(values, split)))
        model = phase_model.from_move_rates(per_move, nx, ny, k, entry, interval, model.attrs)
        dwell = counts[:-1].sum(axis=1)
    return model, previous if not converged else expected.log_likelihood, iteration, converged, dwell


@single_threaded_blas()
def fit(
    data: PhaseData,
    n_phases: int,
    starts: int = 3,
    seed: int = 0,
    max_iterations: int = 200,
    tol: float = 1e-6,
    m_step_iterations: int = 20,
    base: PhaseTransport | None = None,
    m_step: str = "em",
    max_rate_x_interval: float = PHASE_MAX_RATE_X_INTERVAL,
    refine: int = 1,
    stagnant_exit_max: float | None = None,
) -> PhaseFit:
    """Fit the K = ``n_phases`` chain to ``data`` by EM from ``starts`` starts (module
    docstring); stop when the log-likelihood gains less than ``tol`` nats per
    particle-step, or after ``max_iterations``. ``base``: the one-phase fit to start from
    (default: fitted here, by the same EM with K = 1). ``max_rate_x_interval``: the bound
    on every rate x the observation interval (:data:`PHASE_MAX_RATE_X_INTERVAL`).

    ``refine`` = r > 1 (axial data, NY = 1): the chain has r slices in each observed one,
    and the sub-slice a particle is in is hidden beside its phase (r K hidden states per
    observed slice, the same forward-backward). Such a chain is fitted to observations
    coarse enough to be Markov in the phases and is itself on a finer grid (``pbmdem study
    phases --observed-nx``): the observations time the crossing of an observed slice but
    do not say where in it the particles are, so the split of the hold-up between its
    sub-slices is not identified.

    ``stagnant_exit_max`` [1/s]: phase 0 of the K is stagnant, a dead zone: it makes no
    move (nor leaves over the weir), is never entered from the feed, and is left at this
    rate at most in each compartment; the other K - 1 phases start as a (K - 1)-phase fit
    does. Without the bound, maximum likelihood spends an immobile phase on the short
    pauses of the slow bed; with it (e.g. one over the mean residence time) the phase holds
    what the DEM's longest stays are, particles parked for tens of seconds in the corners
    at the inlet wall and under the weir (``pbmdem study phases --stagnant``).

    Raises ValueError for K < 1 (K < 2 with a stagnant phase), starts < 1, a bound that is
    not > 0 or refine < 1."""
    if not isinstance(refine, (int, np.integer)) or refine < 1 or (refine > 1 and (data.ny != 1 or m_step != "em")):
        raise ValueError(
            f"refine = {refine!r} on {data.nx}x{data.ny} data with m_step {m_step!r}: expected an integer >= 1, "
            "and > 1 only on axial data (NY = 1) with the EM M-step"
        )
    if not isinstance(n_phases, (int, np.integer)) or n_phases < 1:
        raise ValueError(f"n_phases = {n_phases!r}: expected an integer >= 1")
    if starts < 1:
        raise ValueError(f"starts = {starts!r}: expected at least one start")
    if not (math.isfinite(max_rate_x_interval) and max_rate_x_interval > 0):
        raise ValueError(f"max_rate_x_interval = {max_rate_x_interval!r}: expected a finite bound > 0")
    if stagnant_exit_max is not None and (
        n_phases < 2 or refine > 1 or m_step != "em" or not (math.isfinite(stagnant_exit_max) and stagnant_exit_max > 0)
    ):
        raise ValueError(
            f"stagnant_exit_max = {stagnant_exit_max!r} with K = {n_phases}, refine {refine}, m_step {m_step!r}: "
            "expected a finite rate > 0 [1/s], K >= 2 (the stagnant phase and at least one that moves), "
            "refine 1 and the EM M-step"
        )
    wall0 = time.perf_counter()
    if base is None:
        base = one_phase(data)
    if refine > 1 and base.nx == data.nx:
        base = refined(base, refine)
    if (base.nx, base.ny) != (data.nx * refine, data.ny):
        raise ValueError(
            f"base grid {base.nx}x{base.ny} is not refine = {refine} times the data's {data.nx}x{data.ny} along x"
        )
    rng = np.random.default_rng(seed)
    results = []
    mobile = n_phases if stagnant_exit_max is None else n_phases - 1
    for start in range(starts if n_phases > 1 else 1):
        first = _initial(base, mobile, None if start == 0 else rng, max_rate_x_interval)
        if stagnant_exit_max is not None:
            first = _with_stagnant(first, stagnant_exit_max)
        results.append(
            _em(first, data, max_iterations, tol, m_step_iterations, m_step, max_rate_x_interval, stagnant_exit_max)
        )
    best = max(results, key=lambda r: r[1])
    model, log_likelihood, iterations, converged, dwell = best
    occupancy = dwell.reshape(model.nx, model.ny, n_phases).transpose(2, 0, 1)
    model, occupancy = _ordered(model, occupancy)
    model = PhaseTransport(
        model.rates,
        model.switching,
        model.entry,
        model.interval_s,
        {
            "method": "EM (forward-backward on the phases, dem.rates M-step)",
            "n_particles": data.n_particles,
            "n_steps": data.n_steps,
            "log_likelihood": log_likelihood,
            "grid": [model.nx, model.ny],
            "observed_grid": [data.nx, data.ny],
            **({} if stagnant_exit_max is None else {"stagnant_exit_max_per_s": float(stagnant_exit_max)}),
        },
    )
    return PhaseFit(
        model,
        log_likelihood,
        data.n_particles,
        data.n_steps,
        iterations,
        converged,
        tuple(float(r[1]) for r in results),
        time.perf_counter() - wall0,
        occupancy,
    )


@single_threaded_blas()
def one_phase(data: PhaseData, max_iterations: int = 2000) -> PhaseTransport:
    """The K = 1 chain: the measured rates of :mod:`dem.rates` (maximum likelihood of the
    observed moves, pooled over ``data``), entry phase trivially 0."""
    counts = data.counts().astype(float)
    counts[-1] = 0.0
    nx, ny = data.nx, data.ny
    moves, _sizes = _moves(nx, ny, 1)
    start = rate_fit.naive_rates(counts, nx, ny, data.interval_s)
    start_moves = {f"{key}/0": start[key].ravel()[moves[f"{key}/0"][2]] for key in rate_fit.RATE_KEYS}
    values, _fit = rate_fit.fit_pattern(counts, moves, start_moves, data.interval_s, max_iterations)
    split = np.cumsum([src.size for src, _d, _c in moves.values()])[:-1]
    return phase_model.from_move_rates(
        dict(zip(moves, np.split(values, split))), nx, ny, 1, np.ones(1), data.interval_s
    )


# ----------------------------------------------------------------------------- synthetic data
def simulate_sequences(
    model: PhaseTransport,
    entering: np.ndarray,
    n_particles: int,
    n_dumps: int,
    rng: np.random.Generator,
    entry_every: int = 1,
) -> CompartmentSequences:
    """Sequences of ``n_particles`` particles of the chain ``model`` observed every
    ``model.interval_s`` (exact: each step draws from expm(Q interval)), for tests with a
    known answer. Particle p enters at dump p // (``n_particles`` / (n_dumps / entry_every))...
    precisely: entries are spread evenly over the first half of the ``n_dumps`` dumps, each
    into a compartment drawn from ``entering`` (2, S) (rows: feed A, B; half the particles
    each) and a phase drawn from the model's entry distribution; the record ends at dump
    ``n_dumps`` - 1 (later particles are censored there)."""
    k, s = model.n_phases, model.n_cells
    p = expm(model.generator() * model.interval_s)
    cdf = np.cumsum(p, axis=1)
    cdf[:, -1] = 1.0
    feeder = np.arange(n_particles) % 2
    start = (np.arange(n_particles) * (n_dumps // 2) // max(n_particles, 1)).astype(np.int64)
    entering = np.asarray(entering, float)
    cells = np.empty(n_particles, np.int64)
    phases = np.empty(n_particles, np.int64)
    for f in (0, 1):
        chosen = feeder == f
        cells[chosen] = rng.choice(s, size=int(chosen.sum()), p=entering[f] / entering[f].sum())
        phases[chosen] = rng.choice(k, size=int(chosen.sum()), p=model.entry[f])
    state = cells * k + phases
    obs = np.full((n_particles, n_dumps), -1, np.int16)
    for t in range(n_dumps):
        inside = (start <= t) & (state < s * k)
        entering_now = start == t
        stepping = inside & ~entering_now
        if stepping.any():
            u = rng.random(int(stepping.sum()))
            rows = state[stepping]
            state[stepping] = (u[:, None] > cdf[rows]).sum(axis=1)
        recorded = start <= t
        just_out = (
            recorded & (state == s * k) & (obs[:, t - 1] < s) & (obs[:, t - 1] >= 0)
            if t
            else np.zeros(n_particles, bool)
        )
        obs[inside & (state < s * k), t] = (state[inside & (state < s * k)] // k).astype(np.int16)
        obs[just_out, t] = s
    return sequences_from_padded(
        obs, start, feeder + 1, np.arange(n_dumps) * model.interval_s, model.interval_s, model.nx, model.ny
    )


def sequences_from_padded(
    obs: np.ndarray,
    start: np.ndarray,
    component: np.ndarray,
    snapshot_t: np.ndarray,
    interval_s: float,
    nx: int,
    ny: int,
) -> CompartmentSequences:
    """:class:`CompartmentSequences` from a (P, T) matrix of states at absolute dumps (-1:
    not in the record), each row one contiguous sequence starting at ``start``."""
    rows, cols = np.nonzero(obs >= 0)
    state = obs[rows, cols]
    new = np.ones(rows.size, bool)
    new[1:] = rows[1:] != rows[:-1]
    run_start = new.copy()
    run_start[1:] |= state[1:] != state[:-1]
    starts = np.flatnonzero(run_start)
    present = np.unique(rows)
    particle_of_run = np.searchsorted(present, rows[starts])
    offsets = np.searchsorted(particle_of_run, np.arange(present.size + 1)).astype(np.int64)
    return CompartmentSequences(
        ids=present.astype(np.int64) + 1,
        component=np.asarray(component)[present].astype(np.int8),
        start=np.asarray(start)[present].astype(np.int32),
        run_offsets=offsets,
        run_state=state[starts].astype(np.int16),
        run_length=np.diff(np.append(starts, rows.size)).astype(np.int32),
        snapshot_t=np.asarray(snapshot_t, float),
        interval_s=float(interval_s),
        nx=nx,
        ny=ny,
    )


# ----------------------------------------------------------------------------- discrete time
@dataclass(frozen=True)
class DiscretePhaseFit:
    """The alternative to a generator: a transition matrix over one dump interval on the
    (compartment, phase) states, every compartment move seen in the data allowed between
    every pair of phases. ``transition`` (S*K+1, S*K+1), row = from, last state discharged;
    ``entry`` (2, K); ``log_likelihood`` [nats]; ``n_parameters`` free entries."""

    transition: np.ndarray
    entry: np.ndarray
    log_likelihood: float
    n_parameters: int
    iterations: int
    interval_s: float


@single_threaded_blas()
def fit_discrete(
    data: PhaseData, n_phases: int, start: PhaseTransport, max_iterations: int = 200, tol: float = 1e-6
) -> DiscretePhaseFit:
    """Baum-Welch of the discrete-time chain at the dump interval (closed-form M-step:
    expected transitions over their row sums), started from ``start``'s expm(Q interval)
    restricted to the allowed entries."""
    k, s = n_phases, data.n_cells
    m = s * k + 1
    seen = data.counts() > 0  # (S+1, S+1) compartment moves observed at all
    allowed = np.zeros((m, m), bool)
    allowed[: s * k, : s * k] = np.kron(seen[:s, :s], np.ones((k, k), bool))
    allowed[: s * k, s * k] = np.repeat(seen[:s, s], k)
    allowed[-1, -1] = True
    t_matrix = np.where(allowed, expm(start.generator() * data.interval_s), 0.0)
    t_matrix /= t_matrix.sum(axis=1, keepdims=True)
    initial = initial_distribution(start, data)
    previous, iteration = -math.inf, 0
    for iteration in range(1, max_iterations + 1):  # noqa: B007 -- the count is reported after the loop
        expected = forward_backward(t_matrix, initial, data, k)
        if (expected.log_likelihood - previous) / max(data.n_steps, 1) < tol:
            previous = expected.log_likelihood
            break
        previous = expected.log_likelihood
        rows = expected.counts.sum(axis=1, keepdims=True)
        updated = np.where(allowed, expected.counts, 0.0) / np.maximum(rows, 1e-300)
        keep = rows[:, 0] <= 0  # states never visited keep their row
        t_matrix = np.where(keep[:, None], t_matrix, updated)
        t_matrix[-1] = 0.0
        t_matrix[-1, -1] = 1.0
        updated = expected.entry / np.maximum(expected.entry.sum(axis=1, keepdims=True), 1e-300)
        initial = np.where(expected.entry.sum(axis=1, keepdims=True) <= 0, initial, updated)
    entry = initial[:2]
    n_parameters = int(allowed[:-1].sum() - (m - 1) + 2 * (k - 1))
    return DiscretePhaseFit(t_matrix, entry, previous, n_parameters, iteration, data.interval_s)


def generator_from_transition(fit_d: DiscretePhaseFit, nx: int, ny: int) -> PhaseTransport:
    """The discrete chain turned into a generator: the principal matrix logarithm over the
    interval, kept on the nearest-neighbour and switching moves of
    :func:`coupling.phases.transitions`, negative entries set to 0 (what a generator must
    be; the difference is what the discrete chain cannot be as a PBM)."""
    from scipy.linalg import logm

    k = fit_d.entry.shape[1]
    log_t = np.real(logm(fit_d.transition)) / fit_d.interval_s
    values = {
        name: np.clip(log_t[src, dst], 0.0, None) for name, (src, dst, _c) in phase_model.transitions(nx, ny, k).items()
    }
    return phase_model.from_move_rates(
        values,
        nx,
        ny,
        k,
        fit_d.entry,
        fit_d.interval_s,
        {"method": "discrete-time Baum-Welch, projected matrix logarithm"},
    )


# ----------------------------------------------------------------------------- into the table
def steady_window(sequences: CompartmentSequences, steady_time_s: float | None) -> tuple[float, float]:
    """(steady-state time, last dump) [s]: the particles the model is fitted to are those
    first seen in between. Raises ValueError when the run never became steady."""
    if steady_time_s is None or not math.isfinite(steady_time_s):
        raise ValueError("the run has no steady-state time: the phase model is fitted to the steady period")
    return float(steady_time_s), float(sequences.snapshot_t[-1])


def with_transverse(axial: PhaseTransport, transverse: PhaseTransport) -> PhaseTransport:
    """The model on the table's NX x NY grid: the K-phase axial chain ``axial`` (fitted on
    the NX x 1 slices) and, in every compartment, the transverse rates of the one-phase
    model ``transverse`` on the full grid (:func:`steady_transverse`), the same in every phase.

    Axial moves and phase switching do not depend on j, so the chain lumped onto
    (slice, phase) is exactly ``axial``: the RTD and the slice hold-ups are those of the
    fit, and the transverse rates only carry particles across y (the composition). A
    phase fit on the full grid would tie the phases to the transverse cells as well: on the
    validation run's first 60 s it cost 35 s (K = 2) to 445 s (K = 3) against 3 to 38 s on
    the slices, and its RTD was further from the DEM's (variance 270 s^2 with slice
    hold-ups 19 % off at K = 2, 231 s^2 at K = 3; ``workflows/studies/phases.py``)."""
    if axial.ny != 1 or transverse.n_phases != 1 or axial.nx != transverse.nx:
        raise ValueError(
            f"expected an NX x 1 axial model and a one-phase model on NX x NY with the same NX; got "
            f"{axial.nx}x{axial.ny} (K = {axial.n_phases}) and {transverse.nx}x{transverse.ny} "
            f"(K = {transverse.n_phases})"
        )
    k, ny = axial.n_phases, transverse.ny
    rates = np.empty((k, len(phase_model.DIRECTIONS), axial.nx, ny))
    rates[:, :2] = axial.rates[:, :2]  # broadcast over j
    rates[:, 2:] = transverse.rates[0, 2:][None]
    switching = np.repeat(axial.switching, ny, axis=3)
    attrs = {
        **axial.attrs,
        "grid": [axial.nx, ny],
        "axial_grid": [axial.nx, 1],
        "transverse": "one-phase rates of the full grid, the same in every phase",
    }
    return PhaseTransport(rates, switching, axial.entry, axial.interval_s, attrs)


def steady_transverse(table, steady_time_s: float) -> PhaseTransport:
    """The one-phase transverse rates of the table's grid: its measured ``rate_y_pos`` and
    ``rate_y_neg`` (:mod:`dem.rates`, fitted to the same particles' moves window by window)
    averaged over the windows from ``steady_time_s`` on, weighted by the particles each
    window saw; a compartment measured in none of them takes its slice's mean. Its axial
    rates are 0 (:func:`with_transverse` reads only the transverse ones). A maximum-
    likelihood fit on the full grid would give the same rates at a cost that grows with the
    cube of NX * NY (201 x 201 matrix exponentials at NX = 20, minutes per fit)."""
    if not table.has_rates:
        raise ValueError("the table carries no measured rates to take the transverse rates from")
    steady = table.t >= steady_time_s - 1e-9 * table.window_s
    if not steady.any():
        raise ValueError(f"no velocity window starts after the steady-state time {steady_time_s:g} s")
    weight = (table.count_A + table.count_B)[steady]
    rates = np.zeros((1, len(phase_model.DIRECTIONS), table.nx, table.ny))
    for d, name in ((2, "rate_y_pos"), (3, "rate_y_neg")):
        values = getattr(table, name)[steady]
        known = np.isfinite(values)
        total = np.where(known, weight, 0.0).sum(axis=0)
        mean = np.where(known, values * weight, 0.0).sum(axis=0) / np.where(total > 0, total, 1.0)
        mean = np.where(total > 0, mean, np.nan)
        by_slice = np.array([np.nanmean(row) if np.isfinite(row).any() else 0.0 for row in mean])[:, None]
        rates[0, d] = np.where(np.isfinite(mean), mean, by_slice)
    return PhaseTransport(rates, np.zeros((1, 1, table.nx, table.ny)), np.ones((2, 1)), float("nan"))


def axial_part(model: PhaseTransport) -> PhaseTransport:
    """The NX x 1 chain of a :func:`with_transverse` model (its lumping onto the slices)."""
    if np.ptp(model.rates[:, :2], axis=3).max(initial=0.0) > 0 or np.ptp(model.switching, axis=3).max(initial=0.0) > 0:
        raise ValueError("the model's axial rates or switching vary across y: it does not lump onto the slices")
    rates = model.rates[:, :, :, :1].copy()
    rates[:, 2:] = 0.0
    return PhaseTransport(rates, model.switching[:, :, :, :1], model.entry, model.interval_s, dict(model.attrs))


def size_classes(diameters: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(class of each particle, -1 where the diameter is unknown; mean diameter of each
    class [m], ascending). Distinct diameters are the classes; more than
    :data:`MAX_CLASSES` of them (a continuous distribution) are grouped into
    :data:`QUANTILE_CLASSES` classes of about equal counts. Raises ValueError when no
    diameter is known."""
    d = np.asarray(diameters, dtype=float)
    known = np.isfinite(d) & (d > 0)
    if not known.any():
        raise ValueError("no particle has a known diameter")
    labels = np.full(d.size, -1, np.int64)
    distinct = np.unique(np.round(d[known] / SAME_DIAMETER_M))
    if distinct.size <= MAX_CLASSES:
        labels[known] = np.searchsorted(distinct, np.round(d[known] / SAME_DIAMETER_M))
    else:
        edges = np.quantile(d[known], np.linspace(0, 1, QUANTILE_CLASSES + 1)[1:-1])
        labels[known] = np.searchsorted(edges, d[known], side="right")
    n = int(labels.max()) + 1
    centres = np.array([d[labels == c].mean() if np.any(labels == c) else math.nan for c in range(n)])
    return labels, centres


def _first_seen_in(sequences: CompartmentSequences, window: tuple[float, float]) -> np.ndarray:
    """Whether each particle was first seen in ``window`` = (t0, t1] [s] (:func:`prepare`'s rule)."""
    tol = 1e-6 * sequences.interval_s
    return (sequences.entry_t > window[0] + tol) & (sequences.entry_t <= window[1] + tol)


def little_residence_time(sequences: CompartmentSequences, window: tuple[float, float]) -> float:
    """Little's law over ``window`` = (t0, t1] [s]: the particle-seconds spent inside over
    its dumps (each dump standing for one dump interval) per particle first seen in it [s].
    Raises ValueError when no particle entered in the window."""
    t = sequences.snapshot_t
    tol = 1e-6 * sequences.interval_s
    dumps = np.flatnonzero((t > window[0] + tol) & (t <= window[1] + tol))
    entering = int(_first_seen_in(sequences, window).sum())
    if not dumps.size or not entering:
        raise ValueError(f"no particle entered in {window} s: Little's law needs an inflow")
    inside_until = sequences.start + sequences.lengths - sequences.discharged  # one past the last dump inside
    change = np.zeros(t.size + 1)
    np.add.at(change, sequences.start, 1.0)
    np.add.at(change, inside_until, -1.0)
    count = np.cumsum(change)[:-1]
    return float(count[dumps].sum() * sequences.interval_s / entering)


def mean_residence_time(model: PhaseTransport, entering: np.ndarray) -> float:
    """The mean time [s] to discharge of particles entering as ``entering`` (2, S) says
    (feed A and B into each compartment, any unit), in the model's entry phases: its
    steady hold-up over its feed (Little's law of the chain)."""
    return float(steady_occupancy(model, entering).sum() / entering.sum())


def zone_held_to_little(model: PhaseTransport, data: PhaseData, residence_s: float) -> PhaseTransport:
    """``model`` (its phase 0 a dead zone, :func:`fit`'s ``stagnant_exit_max``) with the
    rates into the zone scaled by the one factor that makes its mean residence time from
    where ``data``'s particles entered (:func:`first_compartments`) ``residence_s`` (the
    sequences' :func:`little_residence_time`), or leaves it as fitted where even that is
    short of it: the zone only shrinks (its size is what the likelihood saw at most; in a
    class that hardly parks, the largest, a grown zone would be a tail the DEM lacks), and
    there is none when the moving phases alone stay longer. The likelihood sizes the zone
    by the exchange it sees inside the window and leaves the hold-up free: with the zone
    left at most once per 2 residence times, the reduced run's steady hold-up came out 2265
    against the DEM's 2250 [2238, 2263], and 2248 once held (:data:`ZONE_RESIDENCES`). The
    factor is kept in the model's attributes (``zone_entry_scale``)."""
    entering = first_compartments(data)

    def with_scale(c: float) -> PhaseTransport:
        switching = model.switching.copy()
        switching[1:, 0] *= c
        return dataclasses.replace(model, switching=switching)

    def excess(c: float) -> float:
        return mean_residence_time(with_scale(c), entering) - residence_s

    if excess(1.0) <= 0:
        scale = 1.0
    elif excess(0.0) >= 0:
        scale = 0.0
    else:
        scale = float(brentq(excess, 0.0, 1.0, xtol=1e-6))
    held = with_scale(scale)
    return dataclasses.replace(held, attrs={**held.attrs, "zone_entry_scale": scale})


def kinds_by_size(
    sequences: CompartmentSequences,
    diameters: np.ndarray,
    window: tuple[float, float],
    minimum: int = MIN_KIND_PARTICLES,
    min_share: float = MIN_KIND_SHARE,
) -> list[np.ndarray]:
    """The sequences' rows of each size class (:func:`size_classes` of ``diameters``, one
    per sequence, NaN unknown), a class with fewer than ``minimum`` particles first seen in
    ``window`` = (t0, t1], or less than ``min_share`` of them, merged into its neighbour in
    size (the smaller of the two) until none is; smallest size first. Particles of unknown
    size are in none."""
    labels, _centres = size_classes(diameters)
    entering = _first_seen_in(sequences, window)
    groups = [np.flatnonzero(labels == c) for c in range(int(labels.max()) + 1)]
    groups = [g for g in groups if g.size]
    count = lambda g: int(entering[g].sum())  # noqa: E731
    least = max(minimum, min_share * sum(count(g) for g in groups))
    while len(groups) > 1 and min(count(g) for g in groups) < least:
        small = min(range(len(groups)), key=lambda c: count(groups[c]))
        neighbours = [c for c in (small - 1, small + 1) if 0 <= c < len(groups)]
        other = min(neighbours, key=lambda c: count(groups[c]))
        a, b = sorted((small, other))
        groups[a : b + 1] = [np.sort(np.concatenate([groups[a], groups[b]]))]
    return groups


def table_with_phases(
    table,
    sequences: CompartmentSequences,
    steady_time_s: float | None,
    n_phases: int = 3,
    starts: int = 2,
    seed: int = 0,
    max_iterations: int = 200,
    entered_s: tuple[float, float] | None = None,
    diameters: np.ndarray | None = None,
    zone_residences: float | None = ZONE_RESIDENCES,
):
    """``table`` (a :class:`coupling.tables.VelocityTable` on the sequences' grid) carrying
    the K = ``n_phases`` model fitted to the particles first seen after ``steady_time_s``
    and to the moves after it of those already inside (:func:`prepare`'s residents: without
    them the slow particles of the last slices are missing from the window's first mean
    residence times, and the outlet slice's hold-up came out 10 % low), observed every
    :data:`PHASE_LAG_S`: the phases on the axial slices, the table's measured transverse
    rates over the steady windows (:func:`steady_transverse`) in every phase
    (:func:`with_transverse`); a schema-3 table that ``pbm`` runs with ``rates =
    "phases"``. ``entered_s`` = (t0, t1): fit to the particles first seen then instead
    (and those inside at t0). ``diameters`` (one per sequence [m], NaN unknown): each
    size class (:func:`kinds_by_size` over the whole steady window, whatever ``entered_s``
    fits, :data:`MIN_KIND_PARTICLES`) gets its own K-phase chain, and the table carries their population (:func:`coupling.phases.population`,
    K per class, fed in the classes' shares among the particles entering in the window,
    feeder by feeder); one class, or none known, fits one chain as without. A class's chain
    has a dead zone beside its K moving phases (phase 0 of K + 1, left at most once per
    ``zone_residences`` of the window's :func:`little_residence_time`,
    :data:`ZONE_RESIDENCES`; None: no zone), its size then held to the class's own
    Little's law (:func:`zone_held_to_little`). Returns
    (table, fits of the axial phases, one per class). Raises ValueError when the run has
    no steady state or no particle entered after it."""
    if (table.nx, table.ny) != (sequences.nx, sequences.ny):
        raise ValueError(f"table grid {table.nx}x{table.ny} differs from the sequences' {sequences.nx}x{sequences.ny}")
    run_window = steady_window(sequences, steady_time_s)
    window = run_window if entered_s is None else entered_s
    lag = max(1, round(PHASE_LAG_S / sequences.interval_s))
    kinds = [np.arange(sequences.n_particles)]
    if diameters is not None and np.isfinite(np.asarray(diameters, float)).any():
        # The run's classes, whatever part of it is fitted: counted on a half window, the
        # feed x0.5 run's three classes fell below MIN_KIND_PARTICLES and merged into one
        # chain without a zone, whose mean was 2.6 s above both halves' DEM.
        kinds = kinds_by_size(sequences, diameters, run_window)
    one = len(kinds) == 1
    zone = {}
    if not one and zone_residences is not None:
        if not (math.isfinite(zone_residences) and zone_residences > 0):
            raise ValueError(
                f"zone_residences = {zone_residences!r}: expected a number of residence times > 0, or None"
            )
        zone = {"stagnant_exit_max": 1.0 / (zone_residences * little_residence_time(sequences, window))}
    fits = []
    for rows in kinds:
        part = sequences if one else sequences.subset(rows)
        axial_data = prepare(part, window, grid=(sequences.nx, 1), lag=lag, residents=True)
        fitted = fit(axial_data, n_phases + bool(zone), starts, seed, max_iterations, tol=PHASE_TOL, **zone)
        if zone:
            held = zone_held_to_little(fitted.transport, axial_data, little_residence_time(part, window))
            fitted = dataclasses.replace(fitted, transport=held)
        fits.append(fitted)
    if one:
        axial = fits[0].transport
    else:
        entering = _first_seen_in(sequences, window)
        shares = np.array(
            [[np.sum(entering[rows] & (sequences.component[rows] == f)) for rows in kinds] for f in FEEDERS], float
        )
        axial = phase_model.population([f.transport for f in fits], shares)
        sizes = [float(np.nanmean(np.asarray(diameters, float)[rows])) for rows in kinds]
        axial = dataclasses.replace(
            axial,
            attrs={**axial.attrs, "diameters_m": sizes, "phases_per_kind": fits[0].n_phases, "moving_phases": n_phases},
        )
    transverse = steady_transverse(table, window[0]) if sequences.ny > 1 else None
    model = axial if transverse is None else with_transverse(axial, transverse)
    return table.replace(phases=model), tuple(fits)


#: The phases a finer grid gets when it needs them (:func:`choose_phases`).
PHASES_FINE = PHASES + 2

#: :func:`choose_phases`' bar [nats per held-out particle-step] on what two more phases must
#: add to one chain's held-out score. Measured with ``pbmdem study phases --grids NXx1
#: --ks 3,5 --starts 1``: on 10 axial slices the eight shipped runs gain 0.0023-0.0053 (their
#: RTD variance unchanged within 1-3 %, or nearer the DEM's); on 20 slices the reduced run and
#: the validation baseline gain 0.0127 and 0.0137, and K = 3 lost 11 % and 10 % of their
#: variance against 10 slices, K = 5 2.4 % and 4.5 %. The bar sits between the two groups; it
#: rests on two fine-grid runs.
PHASE_GAIN_MIN = 0.008

#: :func:`choose_phases` scores the held-out particles in this many blocks of entry time, and
#: takes the finer K only when the gain, less two standard errors over the blocks, still
#: clears half the bar.
GAIN_BLOCKS = 8


def choose_phases(sequences: CompartmentSequences, steady_time_s: float | None, seed: int = 0) -> tuple[int, float]:
    """(K, gain): the moving phases per chain for the sequences' axial grid, and the held-out
    gain behind the choice. One chain of :data:`PHASES` and one of :data:`PHASES_FINE` phases
    are fitted to the particles that entered in the first half of the steady window's
    entries (with its residents, as :func:`table_with_phases` fits) and scored on those that
    entered in the second;
    :data:`PHASES_FINE` when it gains at least :data:`PHASE_GAIN_MIN` per particle-step.
    A finer grid resolves more of the blades' short-range exchange, and the phases that
    carry the long memory are then too few. Raises ValueError when a half holds too few
    particles to fit."""
    t0, t1 = steady_window(sequences, steady_time_s)
    first_seen = sequences.snapshot_t[sequences.start]
    entered = first_seen[(first_seen > t0) & (first_seen <= t1)]
    if entered.size == 0:
        raise ValueError(f"no particle entered in ({t0:g}, {t1:g}] s to choose the phases on")
    middle = 0.5 * (t0 + float(entered.max()))  # the entries' halves
    grid = (sequences.nx, 1)
    lag = max(1, round(PHASE_LAG_S / sequences.interval_s))
    # the held-out particles in blocks of entry time: the gain per block, paired, so that a
    # gain the held-out data cannot tell from noise (a small run) keeps the default
    edges = np.linspace(middle, float(entered.max()), GAIN_BLOCKS + 1)
    blocks = [prepare(sequences, (a, b), grid=grid, lag=lag) for a, b in zip(edges[:-1], edges[1:])]
    blocks = [block for block in blocks if block.n_steps]
    if not blocks:
        raise ValueError("no particle entered in the second half of the steady window to score the phases on")
    train = prepare(sequences, (t0, middle), grid=grid, lag=lag, residents=True)
    fits = {k: fit(train, k, starts=1, seed=seed, tol=PHASE_TOL) for k in (PHASES, PHASES_FINE)}
    gains = [(fits[PHASES_FINE].score(block) - fits[PHASES].score(block)) / block.n_steps for block in blocks]
    gains_a, weights = np.asarray(gains), np.asarray([block.n_steps for block in blocks], float)
    gain = float(np.average(gains_a, weights=weights))
    if gains_a.size < 2:
        return PHASES, gain
    spread = float(np.sqrt(np.average((gains_a - gain) ** 2, weights=weights) / (gains_a.size - 1)))
    clear = gain - 2.0 * spread >= PHASE_GAIN_MIN / 2
    return (PHASES_FINE if gain >= PHASE_GAIN_MIN and clear else PHASES), gain


def phases_per_kind(model: PhaseTransport) -> int:
    """The phases of each kind of a population (:func:`table_with_phases` by size), or all
    of a model fitted as one chain."""
    return int(model.attrs.get("phases_per_kind", model.n_phases))


def moving_phases(model: PhaseTransport) -> int:
    """The K that :func:`table_with_phases` was asked for to fit ``model``, so that a refit
    fits the same way: a chain per size class has its dead zone beside the K."""
    return int(model.attrs.get("moving_phases", phases_per_kind(model)))


def fits_record(fits: tuple[PhaseFit, ...], model: PhaseTransport) -> dict:
    """What a results summary keeps of :func:`table_with_phases`' fits: one fit's record
    (:func:`fit_record`), or for a chain per size class the classes' records with their
    diameters, and the totals (phases, wall time) beside them."""
    if len(fits) == 1:
        return fit_record(fits[0])
    return {
        "n_phases": model.n_phases,
        "phases_per_kind": fits[0].n_phases,
        "grid": [model.nx, 1],
        "observed_grid": [model.nx, 1],
        "iterations": int(sum(f.iterations for f in fits)),
        "wall_time_s": float(sum(f.wall_time_s for f in fits)),
        "by_size": [{"diameter_m": d, **fit_record(f)} for d, f in zip(model.attrs.get("diameters_m", []), fits)],
    }


def fit_record(fit: PhaseFit) -> dict:
    """What a results summary keeps of a phase fit (the model itself lives in the table)."""
    model = fit.transport
    return {
        "n_phases": fit.n_phases,
        "grid": [model.nx, model.ny],
        "observed_grid": list(model.attrs.get("observed_grid", [model.nx, model.ny])),
        "log_likelihood": fit.log_likelihood,
        "n_particles": fit.n_particles,
        "n_steps": fit.n_steps,
        "iterations": fit.iterations,
        "converged": fit.converged,
        "start_log_likelihoods": list(fit.start_log_likelihoods),
        "wall_time_s": fit.wall_time_s,
        "entry_phase_A": model.entry[0].tolist(),
        "entry_phase_B": model.entry[1].tolist(),
        "implied_timescales_s": fit.implied_timescales().tolist(),
        **{
            key: float(model.attrs[key])
            for key in ("stagnant_exit_max_per_s", "zone_entry_scale")
            if key in model.attrs
        },
    }
