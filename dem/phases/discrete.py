"""The alternative to a generator: a discrete-time chain at the dump interval on the
(compartment, phase) states, fitted by Baum-Welch, and its matrix logarithm projected onto
a generator.

A discrete (S*K)^2 transition matrix has a closed-form M-step, but the PBM needs a
generator, and the logarithm of a fitted transition matrix is in general no generator
(negative off-diagonal entries, moves beyond the nearest neighbours), so it has to be
projected, which changes the very RTD it was fitted to reproduce. Measured
(``workflows.studies.phases.compare_time``; fresh validation run, particles in the blender
from 25 to 60 s, 10 x 1 slices, K = 2, 5.5e5 particle-steps): the discrete chain (216 free
entries) scores 0.010 nats per particle-step above the generator (60 rates), and its own
RTD is the generator's (21.75 s / 233 s^2 against 21.74 s / 238 s^2); but its projected
logarithm, the only way to make it a PBM, gives 9.9 s / 69 s^2. The generator is the
model (:class:`dem.phases.PhaseEstimator`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm, logm

from coupling import phases as phase_model
from coupling.blas import single_threaded_blas
from coupling.phases import PhaseTransport
from dem.phases.chain import initial_distribution
from dem.phases.data import PhaseData
from dem.phases.kernels import forward_backward
from dem.phases.settings import PhaseSettings


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
def fit_discrete(data: PhaseData, start: PhaseTransport, settings: PhaseSettings | None = None) -> DiscretePhaseFit:
    """Baum-Welch of the discrete-time chain at the dump interval (closed-form M-step:
    expected transitions over their row sums) with ``start``'s K phases, started from its
    expm(Q interval) restricted to the allowed entries; it stops as the generator's EM
    does (``settings.tol``, ``settings.max_iterations``; default :class:`PhaseSettings`)."""
    settings = PhaseSettings() if settings is None else settings
    k, s = start.n_phases, data.n_cells
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
    for iteration in range(1, settings.max_iterations + 1):  # noqa: B007 -- the count is reported after the loop
        expected = forward_backward(t_matrix, initial, data, k)
        if (expected.log_likelihood - previous) / max(data.n_steps, 1) < settings.tol:
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
