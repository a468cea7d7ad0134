"""The loops numba compiles, in a module of their own that is imported only where they run.

numba's import and a kernel's load from its cache take half a second, which a
command that neither marches nor solves the bulk under the fill law (`pbmdem design`,
a parser) need not pay; :mod:`pbm.action` and :mod:`pbm.fill` import this module in the
functions that call it.

* :func:`action_march`, :func:`action_series`, :func:`action_product` -- the exact step's action by
  uniformization (:mod:`pbm.action` describes the method and its buffers). They are
  compiled with reassociation and contraction allowed (:data:`SUMS`), which lets the
  compiler vectorise the sums and fuse the multiply-adds: the paper scenario ran in 15-18
  ms against 20-21 without (`pbmdem bench pbm`), its states agreeing with the dense path
  to 5e-12 as before. NaN and infinity keep their meaning (no finite-math assumption).
* :func:`bulk_flows` -- the bulk populations' flows under the fill law (:mod:`pbm.fill`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: The floating-point liberties of the uniformization kernels (module docstring).
SUMS = {"reassoc", "contract"}


@numba.njit(cache=True, nogil=True, fastmath=SUMS)
def action_product(offsets, values_w, outflow_w, rate, v, t, source, pad, n):
    """t = B v on the padded buffers (populations at [pad, pad + n), then OUT, INT1, INT2)."""
    tv = t[pad : pad + n]
    for i in range(n):
        tv[i] = source[i]
    for d in range(offsets.size):
        dv = values_w[d]
        sv = v[pad + offsets[d] : pad + offsets[d] + n]
        for i in range(n):
            tv[i] += dv[i] * sv[i]
    pop = v[pad : pad + n]
    out = 0.0
    total = 0.0
    for i in range(n):
        out += outflow_w[i] * pop[i]
        total += pop[i]
    a = pad + n + pad
    t[a] = v[a] + out
    t[a + 1] = v[a + 1] + total / rate
    t[a + 2] = v[a + 2] + v[a + 1] / rate


@numba.njit(cache=True, nogil=True, fastmath=SUMS)
def action_series(offsets, values_w, outflow_w, rate, means, v, t, results, source, pad, n, tail):
    """results[j] = exp(G tau_j) applied to the padded state v, for lam tau_j = ``means[j]``
    (increasing): one series serves every output, each weighting the same powers B^k v
    by its own Poisson probabilities. v and t are work buffers (v is overwritten)."""
    g = means.size
    size = v.size
    weights = np.empty(g)
    left = np.empty(g)
    used = np.empty(g)
    for j in range(g):
        weights[j] = math.exp(-means[j])
        left[j] = 1.0 - weights[j]
        used[j] = weights[j]
        for i in range(size):
            results[j, i] = weights[j] * v[i]
    k = 0
    while left[g - 1] > tail and k < 1000000:
        k += 1
        action_product(offsets, values_w, outflow_w, rate, v, t, source, pad, n)
        v, t = t, v
        for j in range(g):
            if left[j] <= tail:
                continue
            weights[j] *= means[j] / k
            left[j] -= weights[j]
            w = weights[j]
            if w > 1e-300:
                used[j] += w
                for i in range(size):
                    results[j, i] += w * v[i]
    # Divided by the weight summed, as if the tail left out were spread like the terms
    # kept: the error stays below TAIL, and the populations plus the discharge keep their
    # total to rounding (B conserves it), so a still blender loses no tracer to the cut.
    for j in range(g):
        for i in range(size):
            results[j, i] /= used[j]


@numba.njit(cache=True, nogil=True, fastmath=SUMS)
def action_march(
    offsets,
    values,
    outflow,
    rates,
    pad,
    feed,
    windows,
    steps,
    feed_rates,
    feed_key,
    z0,
    inject_at,
    inject,
    tail,
    max_mean,
):
    m, c = z0.shape
    n = m - 3
    size = pad + n + pad + 3
    a = pad + n + pad
    n_steps = steps.size
    out = np.empty((n_steps + 1, m, c))
    z = z0.copy()
    if inject_at[0] >= 0:
        z += inject[inject_at[0]]
    out[0] = z
    v = np.zeros(size)
    t = np.zeros(size)
    start = np.zeros(size)
    source = np.zeros(n)
    s = 0
    while s < n_steps:
        # a group: the steps that share the window and the feed, with no pulse between
        # them, up to a Poisson mean of max_mean: one series gives all their ends
        w = windows[s]
        rate = rates[w]
        e = s + 1
        total = rate * steps[s]
        while (
            e < n_steps
            and windows[e] == w
            and feed_key[e] == feed_key[s]
            and inject_at[e] < 0
            and total + rate * steps[e] <= max_mean
        ):
            total += rate * steps[e]
            e += 1
        g = e - s
        count = 1
        if g == 1:
            count = max(1, int(math.ceil(total / max_mean)))
        means = np.empty(g)
        acc = 0.0
        for j in range(g):
            acc += rate * steps[s + j]
            means[j] = acc / count
        results = np.zeros((g, size))
        for q in range(c):
            r_a = feed_rates[feed_key[s], 0, q]
            r_b = feed_rates[feed_key[s], 1, q]
            for i in range(n):
                source[i] = (feed[i, 0] * r_a + feed[i, 1] * r_b) / rate
            for i in range(n):
                start[pad + i] = z[i, q]
            for j in range(3):
                start[a + j] = z[n + j, q]
            for _sub in range(count):
                for i in range(size):
                    v[i] = start[i]
                action_series(offsets, values[w], outflow[w], rate, means, v, t, results, source, pad, n, tail)
                for i in range(size):
                    start[i] = results[g - 1, i]
            for j in range(g):
                for i in range(n):
                    out[s + 1 + j, i, q] = results[j, pad + i]
                for i in range(3):
                    out[s + 1 + j, n + i, q] = results[j, a + i]
        for j in range(g):
            if inject_at[s + 1 + j] >= 0:
                for i in range(m):
                    for q in range(c):
                        out[s + 1 + j, i, q] += inject[inject_at[s + 1 + j], i, q]
        for i in range(m):
            for q in range(c):
                z[i, q] = out[e, i, q]
        s = e
    return out


@numba.njit(cache=True, nogil=True)
def bulk_flows(y, slice_of, ref_fill, beta, base, src, sink, scale, n, nx, floor):  # pragma: no cover - compiled
    """dy/dt without the feed: move m carries base[m] x its factor x y[src[m]] from src[m]
    to sink[m] (-1: discharged); its factor is (fill / reference)^beta of entry scale[m]
    of the flattened (NX, 2) exponents, or 1 where scale[m] < 0 (a move the law keeps);
    a slice's fill counts as at least ``floor``."""
    fill = np.zeros(nx)
    for p in range(y.size):
        fill[slice_of[p]] += y[p]
    factor = np.empty(2 * nx)
    for i in range(nx):
        ratio = max(fill[i], floor) / ref_fill[i]
        factor[2 * i] = ratio ** beta[2 * i]
        factor[2 * i + 1] = ratio ** beta[2 * i + 1]
    out = np.zeros(n)
    for m in range(base.size):
        rate = base[m] if scale[m] < 0 else base[m] * factor[scale[m]]
        flux = rate * y[src[m]]
        out[src[m]] -= flux
        if sink[m] >= 0:
            out[sink[m]] += flux
    return out
