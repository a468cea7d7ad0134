"""Is the fitted chain Markovian at the observation interval? The answers of Markov state
models: the Chapman-Kolmogorov test (the chain's predictions from each slice at growing
lags against the observed fractions), the implied timescales, and the log-likelihood of
data held out of the fit.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from coupling.phases import PhaseTransport
from dem.phases.chain import check_grid, initial_distribution, steady_occupancy
from dem.phases.data import PhaseData, as_runs, first_compartments
from dem.phases.kernels import ck_counts, forward_backward


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


def chapman_kolmogorov(
    model: PhaseTransport, data: PhaseData | Sequence[PhaseData], lags: tuple[int, ...], z_limit: float = 4.0
) -> CkTest:
    """The Chapman-Kolmogorov test (:class:`CkTest`) of ``model`` on ``data``, one run or
    several (their start points pooled, each run censored at its own last dump).

    Start points: every particle-dump at index t of a particle's sequence, in a
    compartment, such that the run lasts at least ``lag`` dumps more (so that no outcome is
    censored by the end of the run); a sequence censored otherwise (lost particle) before
    t + lag is left out. Outcome: the slice at t + lag, or discharged."""
    runs = as_runs(data)
    for run in runs:
        check_grid(model, run)
    first = runs[0]
    s, nx, ny, k = first.n_cells, first.nx, first.ny, model.n_phases
    occupancy = steady_occupancy(model, np.sum([first_compartments(run) for run in runs], axis=0))
    phase_given_cell = occupancy / np.maximum(occupancy.sum(axis=1, keepdims=True), 1e-300)
    q = model.generator()
    slice_of = np.append(np.arange(s) // ny, nx)  # discharged -> column NX
    lag_array = np.asarray(lags, np.int64)
    tallies = [
        ck_counts(run.flat, run.offsets, run.start.astype(np.int64), int(run.last_dump), slice_of, lag_array, nx, s)
        for run in runs
    ]
    cell_counts, sums, n_squared, particles = (np.sum([tally[n] for tally in tallies], axis=0) for n in range(4))
    aggregate = np.zeros((s * k + 1, nx + 1))
    aggregate[np.arange(s * k + 1), np.append(np.repeat(slice_of[:-1], k), nx)] = 1.0
    # the model from each compartment in slice i, its phases at their steady distribution there
    predicted = np.zeros((len(lags), nx, nx + 1))
    for n, lag in enumerate(lags):
        from_cell = (expm(q * lag * first.interval_s) @ aggregate)[:-1].reshape(s, k, nx + 1)
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
        np.asarray(lags, float) * first.interval_s, observed, predicted, error, starts, particles, float(z_limit)
    )


def implied_timescales(model: PhaseTransport, count: int = 5) -> np.ndarray:
    """The ``count`` longest relaxation times [s] of the chain, -1/Re(lambda) over the
    eigenvalues of Q restricted to the transient states (a continuous-time chain's are
    the same at every lag; the observed chain's, fitted at growing lags, are not when
    the compartments alone are not Markovian)."""
    q = model.generator()[:-1, :-1]
    eigenvalues = np.linalg.eigvals(q)
    times = np.sort(-1.0 / eigenvalues.real[eigenvalues.real < 0])[::-1]
    return times[:count]


def log_likelihood(model: PhaseTransport, data: PhaseData | Sequence[PhaseData]) -> float:
    """Log-likelihood [nats] of ``data`` (one run or several, e.g. held out of the fit)
    under ``model``, each run's residents in the model's steady phases where first seen."""
    total = 0.0
    for run in as_runs(data):
        check_grid(model, run)
        p = expm(model.generator() * run.interval_s)
        total += forward_backward(
            p, initial_distribution(model, run), run, model.n_phases, backward=False
        ).log_likelihood
    return total
