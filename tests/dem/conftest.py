"""Fixtures of the DEM tests: the synthetic two-phase chain's sequences and fit, shared by
the phase tests (one fit per session: it is the slow part)."""

import numpy as np
import pytest

from dem import phases
from tests.dem.phase_chains import fit_chain, inlet, two_phase_model


@pytest.fixture(scope="session")
def synthetic_two_phase():
    model = two_phase_model()
    sequences = phases.simulate_sequences(model, inlet(), 6000, 2400, np.random.default_rng(7))
    data = phases.prepare(sequences)
    return model, sequences, data, fit_chain(data, 2, starts=2, seed=1)
