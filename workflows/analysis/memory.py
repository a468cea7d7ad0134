"""Is the fitted transport Markov? The phase model of a DEM run checked against the DEM's
own particle sequences, beside the memoryless chain (K = 1) fitted to the same particles.

The model the post-processing fitted (:func:`dem.phases.table_with_phases`) lumps exactly
onto the axial slices, so it is tested there, on the particles that entered during the
steady period (the ones it was fitted to):

* the Chapman-Kolmogorov test (:func:`dem.phases.chapman_kolmogorov`): from each slice,
  the observed fraction of particles in every slice, and discharged, after 1, 2, 5 and
  10 s against the model's probability; a Markov model of the data passes at every lag;
* the implied timescales of each chain;
* the log-likelihood per particle-step of each chain on those particles.

The held-out choice of K (fit on the first half of the steady period, score the second)
and the grids are the phase study's (``pbmdem study phases``); this check costs one
one-phase fit and two CK tests, so every comparison carries it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dem import phases
from dem.phases import CkTest
from dem.post import DemResults

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


@dataclass(frozen=True)
class MemoryCheck:
    """The memoryless chain and the phase model, each checked (module docstring)."""

    chains: tuple[ChainCheck, ...]
    fit_window_s: tuple[float, float]
    n_particles: int
    n_steps: int

    def record(self) -> dict[str, Any]:
        return {
            "fit_window_s": list(self.fit_window_s),
            "n_particles": self.n_particles,
            "n_steps": self.n_steps,
            "chains": [c.record() for c in self.chains],
        }


def memory_check(results: DemResults) -> MemoryCheck | None:
    """:class:`MemoryCheck` of the DEM results' phase model; None when the table carries
    none (no steady state, or results made before the compartment sequences)."""
    table, sequences = results.table, results.sequences
    if not table.has_phases or sequences is None:
        return None
    window = phases.steady_window(sequences, results.summary.steady_time)
    data = phases.prepare(sequences, window, grid=(sequences.nx, 1))
    lags = tuple(max(1, round(s / data.interval_s)) for s in LAG_SECONDS)
    chains = []
    for model in (phases.one_phase(data), phases.axial_part(table.phases)):
        fit = phases.PhaseFit(model, float("nan"), data.n_particles, data.n_steps, 0, True)
        chains.append(
            ChainCheck(
                model.n_phases,
                fit.chapman_kolmogorov(data, lags),
                tuple(float(t) for t in fit.implied_timescales(3)),
                fit.score(data) / max(data.n_steps, 1),
            )
        )
    return MemoryCheck(tuple(chains), window, data.n_particles, data.n_steps)
