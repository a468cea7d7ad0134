"""The phase fit's inner loops: the forward-backward pass over the K phases of every
particle-step (the E-step) and the Chapman-Kolmogorov test's tallies, each a numba kernel
with a plain-Python twin it is tested against.

Cost: the forward-backward is a loop over particles and dumps with K^2 work per step.
Vectorised over particles with numpy it took 1.0 s for 3.1e5 particle-steps (K = 2);
compiled with numba (:func:`_fb_kernel_python`, identical to 1e-10) 0.04 s, so numba pays
25x and the E-step is no longer the cost: the matrix exponentials of the M-step are.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from dem.phases.data import PhaseData


@functools.cache
def _compiled(kernel):
    """``kernel`` compiled by numba (cached on disk), or None without numba: the numpy
    versions are the reference (module docstring). numba is imported when a kernel is
    first wanted, not with this module: a prediction reads the law's classes and never runs
    an E-step (``pbmdem predict``'s 2 s)."""
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency; kept importable without it
        return None
    return numba.njit(cache=True, nogil=True)(kernel)


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
        compiled = _compiled(_fb_kernel_python) is not None
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


def _forward_backward_compiled(
    p: np.ndarray, entry: np.ndarray, data: PhaseData, k: int, backward: bool
) -> Expectations:
    s = data.n_cells
    blocks = _blocks(p, s, k)
    log_likelihood, counts4, entry_sums = _compiled(_fb_kernel_python)(
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


def ck_counts(*args):
    """:func:`_ck_counts_python`, compiled by numba when it is there."""
    return (_compiled(_ck_counts_python) or _ck_counts_python)(*args)
