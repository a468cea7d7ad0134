"""Known chains and helpers shared by the tests of the hidden-phase transport
(``tests/dem/test_phases*.py`` and the studies' tests): synthetic chains with a known
answer, their exact RTD moments, and the fits the tests run."""

import dataclasses

import numpy as np

from coupling.phases import PhaseTransport
from coupling.tables import make_table
from dem.phases import PhaseEstimator, PhaseFit, PhaseSettings
from dem.tracking import CompartmentSequences

INTERVAL = 0.1
NX = 10

#: The synthetic tests' fits: three starts, stopped at 1e-6 nats per particle-step, tighter
#: than the product's PHASE_TOL; their tolerances were set for that stop.
TEST_SETTINGS = PhaseSettings(starts=3, tol=1e-6)
#: the product's settings from one start (what the table tests fit with)
ONE_START = PhaseSettings(starts=1)


def fit_chain(data, n_phases: int, base: PhaseTransport | None = None, **changes) -> PhaseFit:
    """The K = ``n_phases`` fit of ``data`` (one run or several) with :data:`TEST_SETTINGS`
    and ``changes`` to them."""
    settings = dataclasses.replace(TEST_SETTINGS, n_phases=n_phases, **changes)
    return PhaseEstimator(settings).fit(data, base).fetch_model()


def two_phase_model(ny: int = 1) -> PhaseTransport:
    """A slow bed (forward 1.2 /s, back 0.9 /s) and a fast stream (forward 7 /s, back
    2 /s; rate x interval up to 0.7), switching slow -> fast at 0.15 /s and back at
    0.4 /s; feed A enters mostly fast, B mostly slow."""
    rates = np.zeros((2, 4, NX, ny))
    rates[0, 0], rates[0, 1] = 1.2, 0.9
    rates[1, 0], rates[1, 1] = 7.0, 2.0
    if ny > 1:
        rates[:, 2], rates[:, 3] = 3.0, 3.0
    switching = np.zeros((2, 2, NX, ny))
    switching[0, 1], switching[1, 0] = 0.15, 0.4
    return PhaseTransport(rates, switching, np.array([[0.3, 0.7], [0.6, 0.4]]), INTERVAL)


def inlet(ny: int = 1) -> np.ndarray:
    entering = np.zeros((2, NX * ny))
    entering[:, 0] = 1.0
    return entering


def exact_rtd_moments(model: PhaseTransport, entry_cells: np.ndarray, feeder_share=(0.5, 0.5)) -> tuple[float, float]:
    """Mean [s] and variance [s^2] of the time to absorption from the entry distribution
    (no truncation): from the fundamental matrix, m1 = v T 1, m2 = 2 v T^2 1, T = (-Q_tt)^-1."""
    k, s = model.n_phases, model.n_cells
    v = sum(share * (entry_cells[f][:, None] * model.entry[f][None, :]).ravel() for f, share in enumerate(feeder_share))
    v = v / v.sum()
    q = model.generator()[:-1, :-1]
    t1 = np.linalg.solve(-q, np.ones(s * k))
    t2 = np.linalg.solve(-q, t1)
    m1, m2 = v @ t1, 2 * v @ t2
    return float(m1), float(m2 - m1**2)


def dead_zone_model() -> PhaseTransport:
    """A stream (forward 3 /s, back 1 /s) that parks at 0.08 /s in a dead zone of the first
    and last slices, left at 0.05 /s; every particle is fed into the stream."""
    rates = np.zeros((2, 4, NX, 1))
    rates[1, 0], rates[1, 1] = 3.0, 1.0
    switching = np.zeros((2, 2, NX, 1))
    switching[1, 0, [0, NX - 1]] = 0.08
    switching[0, 1] = 0.05
    return PhaseTransport(rates, switching, np.array([[0.0, 1.0], [0.0, 1.0]]), 0.4)


def table_with(model: PhaseTransport | None, ny: int = 1, rates=None):
    rates = rates or {}
    return make_table(
        np.arange(0.0, 200.0, 5.0),
        np.linspace(0, 0.33, NX + 1),
        np.linspace(-0.05, 0.05, ny + 1),
        0.01,
        0.01,
        0.0,
        0.0,
        **rates,
    ).replace(phases=model)


def one_phase_chain(forward: float, backward: float) -> PhaseTransport:
    rates = np.zeros((1, 4, NX, 1))
    rates[0, 0], rates[0, 1] = forward, backward
    return PhaseTransport(rates, np.zeros((1, 1, NX, 1)), np.ones((2, 1)), INTERVAL)


def joined(a: CompartmentSequences, b: CompartmentSequences) -> CompartmentSequences:
    """The particles of two records of the same dumps in one (``b``'s ids after ``a``'s)."""
    return CompartmentSequences(
        ids=np.concatenate([a.ids, b.ids + a.ids.max()]),
        component=np.concatenate([a.component, b.component]),
        start=np.concatenate([a.start, b.start]),
        run_offsets=np.concatenate([a.run_offsets, b.run_offsets[1:] + a.run_offsets[-1]]),
        run_state=np.concatenate([a.run_state, b.run_state]),
        run_length=np.concatenate([a.run_length, b.run_length]),
        snapshot_t=a.snapshot_t,
        interval_s=a.interval_s,
        nx=a.nx,
        ny=a.ny,
    )
