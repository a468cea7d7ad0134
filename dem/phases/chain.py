"""What a phase chain (:class:`coupling.phases.PhaseTransport`) says about the data it is
fitted to: the initial phase distribution of each group of particles, the steady
occupancy for a feed, the mean residence time.
"""

from __future__ import annotations

import numpy as np

from coupling.phases import PhaseTransport
from dem.phases.data import PhaseData, first_compartments


def check_grid(model: PhaseTransport, data: PhaseData) -> None:
    """Raises ValueError when ``model`` is not on ``data``'s grid."""
    if (model.nx, model.ny) != (data.nx, data.ny):
        raise ValueError(f"model grid {model.nx}x{model.ny} differs from the data's {data.nx}x{data.ny}")


def initial_distribution(model: PhaseTransport, data: PhaseData) -> np.ndarray:
    """(2 + S, K) initial phase distribution of each group of :class:`PhaseData`: the
    entry distributions of the two feeders, then for the particles already inside, the
    model's steady phase distribution in their first compartment (what the EM starts
    from and what a held-out score assumes; the EM refits those rows).

    A model ``r`` times finer along x than the data (:attr:`dem.phases.PhaseSettings.refine`) hides the
    sub-slice too: (2 + S, r K) over (sub-slice, phase), the feed spread evenly over the
    sub-slices of the compartment it is first seen in."""
    refine = refinement(model, data)
    first = np.maximum(first_compartments(data), 0.0) + 1e-12
    if refine == 1:
        occupancy = steady_occupancy(model, first)
        entry = model.entry
    else:
        occupancy = steady_occupancy(model, np.repeat(first / refine, refine, axis=1)).reshape(data.n_cells, -1)
        entry = np.repeat(model.entry[:, None, :] / refine, refine, axis=1).reshape(2, -1)
    given_cell = occupancy / np.maximum(occupancy.sum(axis=1, keepdims=True), 1e-300)
    return np.vstack([entry, given_cell])


def refinement(model: PhaseTransport, data: PhaseData) -> int:
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


def mean_residence_time(model: PhaseTransport, entering: np.ndarray) -> float:
    """The mean time [s] to discharge of particles entering as ``entering`` (2, S) says
    (feed A and B into each compartment, any unit), in the model's entry phases: its
    steady hold-up over its feed (Little's law of the chain)."""
    return float(steady_occupancy(model, entering).sum() / entering.sum())
