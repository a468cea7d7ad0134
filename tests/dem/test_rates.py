"""Transfer-rate estimation (dem/rates.py) on exactly simulated chains with known rates."""

import numpy as np
import pytest
from scipy.linalg import expm, expm_frechet
from scipy.optimize import check_grad

from dem.rates import (
    RATE_KEYS,
    _Objective,
    allowed_transitions,
    fit_rates,
    fit_windows,
    generator,
    log_likelihood,
    naive_rates,
    simulate_observations,
)
from workflows.bench.rates import blender_rates

DT = 0.1


def _relative_errors(estimate, truth, mask):
    return np.concatenate(
        [np.abs(estimate[k] - truth[k])[mask & (truth[k] > 0)] / truth[k][mask & (truth[k] > 0)] for k in RATE_KEYS]
    )


def _observe(truth, nx, ny, particles, steps, rng):
    start = np.full(nx * ny, particles // (nx * ny))
    return simulate_observations(generator(truth, nx, ny), start, steps, DT, rng)


def test_generator_pattern():
    nx, ny = 3, 2
    rates = {k: np.full((nx, ny), v) for k, v in zip(RATE_KEYS, (4.0, 1.0, 2.0, 3.0))}
    q = generator(rates, nx, ny)
    s = nx * ny
    assert q.shape == (s + 1, s + 1)
    np.testing.assert_allclose(q.sum(axis=1), 0.0, atol=1e-12)
    assert not q[s].any()
    assert q[(nx - 1) * ny + 1, s] == 4.0  # the last slice discharges forward
    assert q[0, 0] == -(4.0 + 2.0)  # inlet wall and the j = 0 side wall carry nothing
    assert q[ny, 0] == 1.0 and q[1, 0] == 3.0 and q[0, 1] == 2.0


@pytest.mark.parametrize("nx, ny, particles", [(4, 3, 400_000), (10, 10, 4_000_000)])
def test_mle_recovers_known_rates_where_naive_fails(nx, ny, particles, rng):
    truth = blender_rates(nx, ny, peak_rate=1.0 / DT, rng=rng)  # largest rate x interval = 1
    counts = _observe(truth, nx, ny, particles, 30, rng)
    fit = fit_rates(counts, nx, ny, DT, min_observations=2000)
    assert fit.converged
    enough = fit.n_observations >= 2000
    assert enough[-1].all(), "the discharge rates of the last slice must be among those checked"
    errors = _relative_errors(fit.rates(), truth, enough)
    assert errors.size >= 4 * nx * ny - 2 * nx - 2 * ny  # every rate that is not a wall
    assert errors.max() < 0.05, f"worst MLE error {errors.max():.3f}"
    naive = _relative_errors(naive_rates(counts, nx, ny, DT), truth, enough)
    assert naive.max() > 0.05 and np.median(naive) > 0.05, "the naive estimator should be visibly biased here"


def test_likelihood_gradient_matches_finite_differences(rng):
    n = 6
    q = rng.uniform(0.5, 8.0, (n, n)) * (rng.random((n, n)) < 0.6)
    np.fill_diagonal(q, 0.0)
    q[np.arange(n), np.arange(n)] = -q.sum(axis=1)
    counts = rng.integers(0, 50, (n, n)).astype(float)
    _, grad = log_likelihood(q, counts, DT)
    for _ in range(5):
        direction = rng.standard_normal((n, n))
        h = 1e-6
        fd = (log_likelihood(q + h * direction, counts, DT)[0] - log_likelihood(q - h * direction, counts, DT)[0]) / (
            2 * h
        )
        assert np.sum(grad * direction) == pytest.approx(fd, rel=1e-6)


def test_finite_differences_tell_the_transpose_convention_apart(rng):
    n = 6
    q = rng.uniform(0.5, 8.0, (n, n))
    np.fill_diagonal(q, 0.0)
    q[np.arange(n), np.arange(n)] = -q.sum(axis=1)
    counts = rng.integers(1, 50, (n, n)).astype(float)
    _, grad = log_likelihood(q, counts, DT)
    g = counts / expm(q * DT)
    wrong = DT * expm_frechet(q * DT, g, compute_expm=False)
    assert not np.allclose(wrong, grad, rtol=1e-3)


def test_objective_gradient_with_chain_rule(rng):
    nx, ny = 3, 2
    truth = blender_rates(nx, ny, 8.0, rng)
    counts = _observe(truth, nx, ny, 6000, 10, rng).astype(float)
    t = allowed_transitions(nx, ny)
    src = np.concatenate([v[0] for v in t.values()])
    dst = np.concatenate([v[1] for v in t.values()])
    start = rng.uniform(0.5, 5.0, src.size)
    free = np.ones(src.size, dtype=bool)
    objective = _Objective(counts, DT, start, free, src, dst)
    z = start * objective.weight
    err = check_grad(lambda v: objective(v)[0], lambda v: objective(v)[1], z, epsilon=1e-7)
    assert err < 1e-6 * np.linalg.norm(objective(z)[1]) + 1e-9


def test_unobserved_and_sparse_compartments_are_nan(rng):
    nx, ny = 4, 3
    truth = blender_rates(nx, ny, 8.0, rng)
    counts = _observe(truth, nx, ny, 120_000, 20, rng)
    counts[5] = 0  # compartment (1, 2) never seen at a dump
    counts[7, :] = 0
    counts[7, 7] = 10  # compartment (2, 1): 10 observations, below min_observations
    fit = fit_rates(counts, nx, ny, DT, min_observations=100)
    for key in RATE_KEYS:
        rates = getattr(fit, key)
        assert np.isnan(rates[1, 2]) and np.isnan(rates[2, 1])
        others = np.ones((nx, ny), dtype=bool)
        others[1, 2] = others[2, 1] = False
        assert np.isfinite(rates[others]).all()
    assert fit.n_observations[2, 1] == 10 and fit.n_observations[1, 2] == 0


def test_zero_rate_is_estimated_as_about_zero(rng):
    nx, ny = 4, 3
    truth = blender_rates(nx, ny, 8.0, rng)
    truth["x_neg"][:] = 0.0  # no backmixing at all
    counts = _observe(truth, nx, ny, 200_000, 20, rng)
    fit = fit_rates(counts, nx, ny, DT)
    assert np.nanmax(fit.x_neg) < 1e-2  # 1/s, against forward rates of several per second
    enough = fit.n_observations >= 2000
    assert _relative_errors(fit.rates(), truth, enough).max() < 0.05


def test_fit_windows_warm_start_tracks_changing_rates(rng):
    nx, ny = 4, 3
    truths = [blender_rates(nx, ny, 10.0, rng) for _ in range(3)]
    counts = np.stack([_observe(t, nx, ny, 400_000, 20, rng) for t in truths])
    fits = fit_windows(counts, nx, ny, DT, min_observations=2000)
    assert set(fits.rates) == {f"rate_{k}" for k in RATE_KEYS} and fits.capped == 0 and not fits.unconverged
    for k, truth in enumerate(truths):
        assert fits.rates["rate_x_pos"][k].shape == (nx, ny)
        window = {key: fits.rates[f"rate_{key}"][k] for key in RATE_KEYS}
        assert _relative_errors(window, truth, np.isfinite(window["x_pos"])).max() < 0.05


def test_fit_windows_memo_refits_only_what_changed(rng, monkeypatch):
    """Windows as a run's dumps arrive: the first two, then the second grown and a third.
    The memo serves the unchanged first window and only it; every fit equals a fit without it."""
    import dem.rates as rates

    nx, ny = 3, 2
    truth = blender_rates(nx, ny, 5.0, rng)
    counts = np.stack([_observe(truth, nx, ny, 50_000, 10, rng) for _ in range(3)])
    early = counts[:2].copy()
    early[1] //= 2  # the second window half observed at the first call
    fitted = []
    real = rates.fit_rates
    monkeypatch.setattr(rates, "fit_rates", lambda window, *a, **k: fitted.append(window) or real(window, *a, **k))
    memo: dict = {}
    fit_windows(early, nx, ny, DT, min_observations=100, memo=memo)
    assert len(fitted) == 2
    grown = fit_windows(counts, nx, ny, DT, min_observations=100, memo=memo)
    assert len(fitted) == 4 and len(memo) == 4  # windows 1 (grown) and 2 fitted, window 0 served
    plain = fit_windows(counts, nx, ny, DT, min_observations=100)
    for key, values in plain.rates.items():
        np.testing.assert_array_equal(grown.rates[key], values)


def test_simulation_counts_every_live_particle_once_per_step(rng):
    nx, ny = 2, 2
    q = generator(blender_rates(nx, ny, 5.0, rng), nx, ny)
    start = np.array([100, 50, 0, 25])
    one = simulate_observations(q, start, 1, DT, rng)
    np.testing.assert_array_equal(one[:-1].sum(axis=1), start)
    assert not one[-1].any()


def test_wrong_shapes_name_the_expected_shape(rng):
    nx, ny = 4, 3
    with pytest.raises(ValueError, match=r"expected \(13, 13\)"):
        fit_rates(np.zeros((12, 12)), nx, ny, DT)
    with pytest.raises(ValueError, match=r"expected \(K, 13, 13\)"):
        fit_windows(np.zeros((13, 13)), nx, ny, DT)
    with pytest.raises(ValueError, match=r"expected \(13, 13\)"):
        naive_rates(np.zeros((2, 13, 13)), nx, ny, DT)
    rates = {k: np.ones((nx, ny)) for k in RATE_KEYS}
    rates["y_neg"] = np.ones((ny, nx))
    with pytest.raises(ValueError, match=r"expected \(nx, ny\) = \(4, 3\)"):
        generator(rates, nx, ny)
    with pytest.raises(ValueError, match="interval_s"):
        fit_rates(np.zeros((13, 13)), nx, ny, 0.0)


def test_a_window_without_observations_fits_nothing():
    fit = fit_rates(np.zeros((3 * 2 + 1, 3 * 2 + 1)), 3, 2, DT)
    assert (fit.iterations, fit.converged, fit.log_likelihood) == (0, True, 0.0)
    assert all(np.isnan(getattr(fit, key)).all() for key in RATE_KEYS)
