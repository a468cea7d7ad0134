"""Transport with memory: the compartment chain whose particles carry a hidden mobility phase.

This is the neutral description both sides share: the DEM side fits it to every particle's
compartment sequence (:mod:`dem.phases`), the velocity table carries it (schema 3,
:mod:`coupling.tables`), the PBM solves it (``rates = "phases"``, :mod:`pbm.model`).

State. A particle is in compartment c = i * NY + j (the tables' grid) and in one of K
phases h = 0..K-1; the flat state is ``c * K + h``, and ``S * K`` (S = NX * NY) is
"discharged" (absorbing). K = 1 is the measured-rate chain of :mod:`dem.rates`.

Moves (per particle, 1/s), all constant in time (fitted over the steady period):

* in phase h, from (i, j) to (i+1, j) at ``rates[h, 0, i, j]`` (from the last slice: the
  discharge), to (i-1, j) at ``rates[h, 1]``, to (i, j+1) at ``rates[h, 2]``, to (i, j-1)
  at ``rates[h, 3]`` (the order of :data:`coupling.tables.RATE_NAMES`); the phase is kept;
* inside compartment (i, j), from phase h to phase g at ``switching[h, g, i, j]``.

Nothing crosses the inlet wall or the side walls (those entries are ignored and stored 0).
Feed of component A (row 0) and B (row 1) enters in phase h with probability
``entry[row, h]``; where it enters (which compartments) is the PBM's feed distribution.

Phases are ordered by mobility, slowest first (:func:`mobility`): the hidden phase has no
name of its own, and without an order two fits of the same data could differ by a
relabelling. A population of kinds that never change (:func:`population`: a chain per size
class) orders its phases kind by kind, each kind's by mobility.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from coupling.errors import TableError

#: The bound of every measured rate, a phase's move or switch and a velocity table's rate
#: alike [1/s]: above 1 / the DEM timestep (2e4 /s at 5e-5 s), so no simulation can observe
#: a faster transition (:mod:`coupling.tables` bounds its rates by it).
MAX_RATE_PER_S = 1e5

#: directions of the phase-keeping moves, in the order of ``PhaseTransport.rates[:, d]``
DIRECTIONS = ("x_pos", "x_neg", "y_pos", "y_neg")


@dataclass(frozen=True)
class PhaseTransport:
    """A fitted hidden-phase compartment chain (module docstring for the meaning).

    ``rates`` (K, 4, NX, NY) [1/s], ``switching`` (K, K, NX, NY) [1/s] (diagonal 0),
    ``entry`` (2, K) [-] (rows sum to 1: feed A, feed B), ``interval_s`` [s] the dump
    interval the model was fitted at (provenance), ``attrs``: free provenance (JSON-able).
    """

    rates: np.ndarray
    switching: np.ndarray
    entry: np.ndarray
    interval_s: float = float("nan")
    attrs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        validate(self)

    @property
    def n_phases(self) -> int:
        return int(self.rates.shape[0])

    @property
    def nx(self) -> int:
        return int(self.rates.shape[2])

    @property
    def ny(self) -> int:
        return int(self.rates.shape[3])

    @property
    def n_cells(self) -> int:
        return self.nx * self.ny

    def generator(self) -> np.ndarray:
        """Dense generator (S*K + 1, S*K + 1), row = from, column = to, rows sum to 0; the
        last state is "discharged" (row of zeros)."""
        return generator(self.rates, self.switching)

    def phase_rates(self, h: int) -> dict[str, np.ndarray]:
        """The four (NX, NY) rate arrays of phase h, keyed like :data:`DIRECTIONS`."""
        return {key: self.rates[h, d] for d, key in enumerate(DIRECTIONS)}


def validate(model: PhaseTransport) -> None:
    """Raise TableError naming the first inconsistent field of ``model``."""
    rates, switching, entry = (np.asarray(a, dtype=float) for a in (model.rates, model.switching, model.entry))
    if rates.ndim != 4 or rates.shape[1] != len(DIRECTIONS) or min(rates.shape) < 1:
        raise TableError(f"phase rates have shape {rates.shape}; expected (K, 4, NX, NY) with K, NX, NY >= 1")
    k, _, nx, ny = rates.shape
    if switching.shape != (k, k, nx, ny):
        raise TableError(f"phase switching has shape {switching.shape}; expected (K, K, NX, NY) = {(k, k, nx, ny)}")
    if entry.shape != (2, k):
        raise TableError(f"entry-phase distribution has shape {entry.shape}; expected (2, K) = (2, {k})")
    for name, values, bound, unit in (
        ("phase rates", rates, MAX_RATE_PER_S, " /s"),
        ("phase switching", switching, MAX_RATE_PER_S, " /s"),
        ("entry-phase distribution", entry, np.inf, ""),  # its rows must sum to 1: checked below
    ):
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(values) | (values < 0) | (values > bound)
        if bad.any():
            raise TableError(
                f"{name} hold {float(values[bad][0])!r} at index {tuple(int(v) for v in np.argwhere(bad)[0])}; "
                + (
                    f"finite values in [0, {bound:g}]{unit} are valid"
                    if np.isfinite(bound)
                    else "finite values >= 0 are valid"
                )
            )
    sums = entry.sum(axis=1)
    if np.any(np.abs(sums - 1.0) > 1e-6):
        raise TableError(f"entry-phase distribution rows sum to {sums.tolist()}; each must sum to 1")


def transitions(nx: int, ny: int, n_phases: int) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every move the model allows, by kind: ``"<direction>/<h>"`` for the phase-keeping
    moves of phase h and ``"switch/<h>/<g>"`` for phase switches, each as (source state,
    target state, flat compartment) arrays of the flat (compartment, phase) states; walls
    have none. The layout of :func:`dem.rates.allowed_transitions`, phase by phase."""
    i, j = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij"))
    c = i * ny + j
    s = nx * ny
    k = n_phases
    steps = {
        "x_pos": (np.ones(c.size, bool), None),
        "x_neg": (i > 0, -ny),
        "y_pos": (j < ny - 1, 1),
        "y_neg": (j > 0, -1),
    }
    out = {}
    for h in range(k):
        for key, (ok, step) in steps.items():
            src_c = c[ok]
            if key == "x_pos":
                dst = np.where(i == nx - 1, s * k, (c + ny) * k + h)
            else:
                dst = (src_c + step) * k + h
            out[f"{key}/{h}"] = (src_c * k + h, dst, src_c)
    for h in range(k):
        for g in range(k):
            if g != h:
                out[f"switch/{h}/{g}"] = (c * k + h, c * k + g, c.copy())
    return out


def generator(rates: np.ndarray, switching: np.ndarray) -> np.ndarray:
    """Dense generator of the flat (compartment, phase) chain: see :class:`PhaseTransport`."""
    k, _, nx, ny = rates.shape
    n = nx * ny * k + 1
    q = np.zeros((n, n))
    for name, (src, dst, comp) in transitions(nx, ny, k).items():
        parts = name.split("/")
        if parts[0] == "switch":
            values = switching[int(parts[1]), int(parts[2])].ravel()[comp]
        else:
            values = rates[int(parts[1]), DIRECTIONS.index(parts[0])].ravel()[comp]
        q[src, dst] += values
    q[np.arange(n), np.arange(n)] = -q.sum(axis=1)
    return q


def from_move_rates(
    values: dict[str, np.ndarray],
    nx: int,
    ny: int,
    n_phases: int,
    entry: np.ndarray,
    interval_s: float = float("nan"),
    attrs: dict[str, Any] | None = None,
) -> PhaseTransport:
    """A :class:`PhaseTransport` from one rate per move of :func:`transitions` (``values``
    maps each of its keys to the rates of its moves, in its order)."""
    k = n_phases
    rates = np.zeros((k, len(DIRECTIONS), nx, ny))
    switching = np.zeros((k, k, nx, ny))
    for name, (_src, _dst, comp) in transitions(nx, ny, k).items():
        parts = name.split("/")
        target = (
            switching[int(parts[1]), int(parts[2])]
            if parts[0] == "switch"
            else rates[int(parts[1]), DIRECTIONS.index(parts[0])]
        )
        target.reshape(-1)[comp] = values[name]
    entry = np.asarray(entry, dtype=float)
    if entry.ndim == 1:
        entry = np.stack([entry, entry])
    return PhaseTransport(rates, switching, entry, float(interval_s), dict(attrs or {}))


def mobility(rates: np.ndarray, occupancy: np.ndarray) -> np.ndarray:
    """Mobility of each phase [1/s]: its forward axial rate averaged over the compartments
    with weights ``occupancy`` (K, NX, NY) (how much of the particles' time each phase spends
    there). The order of the phases is ascending mobility."""
    weights = occupancy / np.maximum(occupancy.sum(axis=(1, 2), keepdims=True), 1e-300)
    return (rates[:, 0] * weights).sum(axis=(1, 2))


def scaled(
    model: PhaseTransport, axial: float = 1.0, transverse: float = 1.0, switching: float = 1.0
) -> PhaseTransport:
    """``model`` with its axial rates times ``axial``, its transverse rates times
    ``transverse`` and its phase switching times ``switching`` (the table studies' rules:
    longer cells, a faster impeller)."""
    rates = model.rates.copy()
    rates[:, :2] *= axial
    rates[:, 2:] *= transverse
    attrs = {**model.attrs, "scaled": {"axial": axial, "transverse": transverse, "switching": switching}}
    return PhaseTransport(rates, model.switching * switching, model.entry, model.interval_s, attrs)


def blend(a: PhaseTransport, b: PhaseTransport, w: float) -> PhaseTransport | None:
    """(1 - w) ``a`` + w ``b`` (a table library between two runs): rate by rate when the two
    models have the same grid and number of phases (phases are ordered by mobility, slowest
    first, so phase h of one run is matched with phase h of the other); otherwise, on one
    grid, the mixture of the two chains (:func:`population`: a share 1 - w of the particles
    follows ``a``, w ``b``), since phases of different structures (one chain for every size
    against a chain per size class) have no one-to-one match; None on different grids."""
    if a.rates.shape != b.rates.shape:
        if (a.nx, a.ny) != (b.nx, b.ny):
            return None
        if w <= 0.0 or w >= 1.0:
            return a if w <= 0.0 else b
        mixed = population([a, b], [1.0 - w, w])
        return PhaseTransport(mixed.rates, mixed.switching, mixed.entry, a.interval_s, {"mixture": float(w)})
    mix = lambda x, y: (1 - w) * x + w * y  # noqa: E731
    return PhaseTransport(
        mix(a.rates, b.rates),
        mix(a.switching, b.switching),
        mix(a.entry, b.entry),
        a.interval_s,
        {**a.attrs, "interpolated": float(w)},
    )


def population(models: list[PhaseTransport], shares) -> PhaseTransport:
    """One chain for particles of several kinds that never change kind (sizes): the phases
    of ``models`` side by side, no switching between the kinds', the feed entering kind m
    with probability ``shares[m]`` (normalised; or ``shares[f, m]`` per feeder f, A then
    B) and then its phases as ``models[m]`` enters them. Raises ValueError for models on
    different grids or shares that are not >= 0 with a positive sum per feeder."""
    given = np.asarray(shares, dtype=float)
    shares = np.broadcast_to(given, (2, len(models))) if given.ndim == 1 else given
    if (
        not models
        or given.ndim not in (1, 2)
        or given.shape[-1] != len(models)
        or shares.shape != (2, len(models))
        or np.any(~np.isfinite(shares) | (shares < 0))
        or np.any(shares.sum(axis=1) <= 0)
    ):
        raise ValueError(
            f"shares {given.tolist()} for {len(models)} models: expected one share >= 0 per model (or per "
            "feeder and model), with a positive sum"
        )
    grids = {(m.nx, m.ny) for m in models}
    if len(grids) != 1:
        raise ValueError(f"models on grids {sorted(grids)}: a population needs one grid")
    nx, ny = grids.pop()
    k = sum(m.n_phases for m in models)
    switching = np.zeros((k, k, nx, ny))
    entry = np.zeros((2, k))
    fractions = shares / shares.sum(axis=1, keepdims=True)
    first = 0
    for index, m in enumerate(models):
        kind = slice(first, first + m.n_phases)
        switching[kind, kind] = m.switching
        entry[:, kind] = fractions[:, index, None] * m.entry
        first += m.n_phases
    return PhaseTransport(
        np.concatenate([m.rates for m in models]),
        switching,
        entry,
        models[0].interval_s,
        {"population": [m.attrs for m in models], "shares": fractions.tolist()},
    )


def kinds(model: PhaseTransport) -> list[PhaseTransport]:
    """The chains of a population's kinds (the inverse of :func:`population` for a model
    whose attributes name its kinds: ``phases_per_kind`` and ``diameters_m``), each fed as
    the kind's particles are; [model] for a model of one kind. A kind a feeder does not
    feed enters as the other feeder's particles of that kind do."""
    k = int(model.attrs.get("phases_per_kind", model.n_phases))
    count = len(model.attrs.get("diameters_m", [])) or 1
    if k * count != model.n_phases:
        raise ValueError(f"a model of {model.n_phases} phases is not {count} kinds of {k} phases")
    out = []
    for m in range(count):
        kind = slice(m * k, (m + 1) * k)
        entry = model.entry[:, kind]
        sums = entry.sum(axis=1)
        entry = np.where(
            sums[:, None] > 0, entry / np.maximum(sums[:, None], 1e-300), entry[::-1] / max(sums.max(), 1e-300)
        )
        out.append(PhaseTransport(model.rates[kind], model.switching[kind, kind], entry, model.interval_s))
    return out


def to_arrays(model: PhaseTransport) -> dict[str, np.ndarray]:
    """The datasets of a schema-3 table (:mod:`coupling.tables`)."""
    return {"phase_rates": model.rates, "phase_switching": model.switching, "phase_entry": model.entry}


def from_arrays(
    arrays: dict[str, np.ndarray], interval_s: float, attrs: dict[str, Any] | None = None
) -> PhaseTransport:
    """The inverse of :func:`to_arrays`."""
    return PhaseTransport(
        np.asarray(arrays["phase_rates"], float),
        np.asarray(arrays["phase_switching"], float),
        np.asarray(arrays["phase_entry"], float),
        float(interval_s),
        dict(attrs or {}),
    )
