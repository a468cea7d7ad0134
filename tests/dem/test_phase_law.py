"""The phase law fitted jointly to a library of runs (dem.phases.law): a synthetic library
generated from a known law at several speeds and lengths, recovered; held-out points."""

import numpy as np
import pytest
from scipy.linalg import expm

from coupling.errors import ConfigError
from coupling.phases import MAX_RATE_PER_S
from dem.phases.chain import initial_distribution
from dem.phases.data import prepare, simulate_sequences
from dem.phases.kernels import forward_backward
from dem.phases.law import LawRun, fit_law, law_chain

K = 2
INTERVAL_S = 0.5
NAMES = ("1", "log_rpm", "position")
#: the true law: a slow and a fast phase whose rates grow with speed, the slow phase's
#: forward rate with position, the fast phase's backward rate falling with it
TRUE = {
    "x_pos/0": [np.log(0.08), 0.6, 0.3],
    "x_pos/1": [np.log(0.6), 1.0, 0.0],
    "x_neg/0": [np.log(0.04), 0.6, 0.0],
    "x_neg/1": [np.log(0.2), 1.0, -0.2],
    "switch/0/1": [np.log(0.1), 0.5, 0.0],
    "switch/1/0": [np.log(0.15), 0.3, 0.0],
}
TRUE = {key: np.array(value) for key, value in TRUE.items()}
ENTRY = np.array([[0.3, 0.7], [0.4, 0.6]])
#: the library (speed [rpm], axial slices: a longer blender has more) and points it never ran
LIBRARY = ((150, 6), (250, 8), (350, 10))
UNSEEN = ((200, 7), (300, 12), (175, 9))


def covariates(rpm: float, nx: int) -> np.ndarray:
    position = (np.arange(nx) + 0.5) / nx - 0.5
    return np.column_stack([np.ones(nx), np.full(nx, np.log(rpm / 250)), position])


def synthetic_run(rpm: float, nx: int, n_particles: int, rng) -> LawRun:
    model = law_chain(TRUE, ENTRY, covariates(rpm, nx), nx, 1, K, INTERVAL_S)
    entering = np.zeros((2, nx))
    entering[:, 0] = 1.0
    sequences = simulate_sequences(model, entering, n_particles, 600, rng)
    return LawRun(prepare(sequences), covariates(rpm, nx), f"{rpm} rpm, {nx} slices")


@pytest.fixture(scope="module")
def library():
    rng = np.random.default_rng(1)
    runs = [synthetic_run(rpm, nx, 10_000, rng) for rpm, nx in LIBRARY]
    return runs, fit_law(runs, K, NAMES)


def _worst_error(law, rpm: float, nx: int) -> float:
    fitted = law.chain(covariates(rpm, nx), nx, 1, INTERVAL_S)
    true = law_chain(TRUE, ENTRY, covariates(rpm, nx), nx, 1, K, INTERVAL_S)
    moving = true.rates[:, :2] > 0
    axial = np.abs(fitted.rates[:, :2][moving] / true.rates[:, :2][moving] - 1)
    off = ~np.eye(K, dtype=bool)
    switching = np.abs(fitted.switching[off] / true.switching[off] - 1)
    return float(max(axial.max(), switching.max()))


def test_the_law_of_a_synthetic_library_is_recovered_within_5_percent(library):
    _runs, law = library
    assert law.converged
    assert sorted(law.coefficients) == sorted(TRUE)  # an axial library has no transverse moves to fit
    assert law.n_parameters == 6 * 3 + 2
    # every rate of every run's chain, at the library's points and at speeds and lengths it never ran
    for rpm, nx in LIBRARY + UNSEEN:
        assert _worst_error(law, rpm, nx) < 0.05, (rpm, nx)
    assert np.allclose(law.entry, ENTRY, atol=0.02)


def test_a_held_out_run_is_scored_as_the_true_law_scores_it(library):
    _runs, law = library
    held_out = synthetic_run(200, 7, 3000, np.random.default_rng(7))
    true = law_chain(TRUE, ENTRY, held_out.covariates, 7, 1, K, INTERVAL_S)
    p = expm(true.generator() * INTERVAL_S)
    truth = forward_backward(p, initial_distribution(true, held_out.data), held_out.data, K, backward=False)
    per_step = (law.score(held_out) - truth.log_likelihood) / held_out.data.n_steps
    assert abs(per_step) < 2e-4
    # a law blind to speed fits the library worse and scores the held-out run worse
    blind_runs = [LawRun(r.data, r.covariates[:, [0, 2]], r.name) for r in _runs]
    blind = fit_law(blind_runs, K, ("1", "position"))
    assert blind.log_likelihood < law.log_likelihood
    held_blind = LawRun(held_out.data, held_out.covariates[:, [0, 2]])
    assert blind.score(held_blind) < law.score(held_out)


def test_runs_that_cannot_share_a_law_are_refused(library):
    runs, _law = library
    with pytest.raises(ConfigError, match="column 0 must be the constant 1"):
        LawRun(runs[0].data, runs[0].covariates[:, ::-1])
    with pytest.raises(ConfigError, match=r"expected \(S, P\)"):
        LawRun(runs[0].data, runs[1].covariates)
    with pytest.raises(ConfigError, match="the same P"):
        fit_law([runs[0], LawRun(runs[1].data, runs[1].covariates[:, :2])], K)
    with pytest.raises(ConfigError, match="n_phases must be an integer >= 1"):
        fit_law(runs, 0)


def test_a_grid_with_moves_the_law_never_saw_is_refused(library):
    _runs, law = library
    with pytest.raises(ConfigError, match="no rate for the moves 'y_pos/0'"):
        law.chain(np.column_stack([np.ones(8), np.zeros(8), np.zeros(8)]), 4, 2, INTERVAL_S)


def test_a_rate_the_law_extrapolates_past_the_bound_is_held_at_it():
    """A family's linear predictor beyond log(MAX_RATE_PER_S) at a run's covariates (a
    phase extrapolated where it hardly moves) gives a valid chain, that rate at the bound
    and every other rate as the law says."""
    wild = {**TRUE, "x_neg/1": np.array([np.log(0.2), 40.0, 0.0])}
    model = law_chain(wild, ENTRY, covariates(350, 6), 6, 1, K, INTERVAL_S)
    tame = law_chain(TRUE, ENTRY, covariates(350, 6), 6, 1, K, INTERVAL_S)
    # the first slice has no backward move
    assert np.all(model.phase_rates(1)["x_neg"][1:] == pytest.approx(MAX_RATE_PER_S))
    assert np.allclose(model.phase_rates(0)["x_neg"], tame.phase_rates(0)["x_neg"])
    assert np.allclose(model.phase_rates(1)["x_pos"], tame.phase_rates(1)["x_pos"])
