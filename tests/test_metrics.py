"""The CQAs both sides compute through coupling.metrics: RSD and its empty rule, the
random-mixture floor, C_A, the steady-state rule; and the DEM and PBM agreeing on them
when handed the same counts."""

import math

import numpy as np
import pytest

from coupling.errors import ConfigError
from coupling.metrics import EMPTY_BELOW, SteadyStateRule, outflow_fraction_a, random_mixture_rsd, rsd


def test_rsd_sample_statistic_and_empty_compartments():
    a = np.array([1.0, 3.0, 0.0, 2.0])
    b = np.array([3.0, 1.0, 0.0, 2.0])  # fractions 0.25, 0.75, (empty), 0.5
    assert rsd(a, b) == pytest.approx(np.std([0.25, 0.75, 0.5], ddof=1) / 0.5)
    assert np.isnan(rsd(np.array([1.0, 0.0]), np.array([1.0, 0.0])))  # one occupied compartment
    assert np.isnan(rsd(np.array([0.0, 0.0]), np.array([2.0, 2.0])))  # no A: undefined
    # fewer than EMPTY_BELOW (one) particle expected counts as empty
    assert EMPTY_BELOW == 1.0
    assert rsd(np.array([0.3, 1.0, 3.0]), np.array([0.0, 3.0, 1.0])) == pytest.approx(
        np.std([0.25, 0.75], ddof=1) / 0.5)


def test_rsd_along_an_axis_equals_one_call_per_row(rng):
    a = rng.integers(0, 5, size=(7, 10)).astype(float)
    b = rng.integers(0, 5, size=(7, 10)).astype(float)
    along = rsd(a, b, axis=1)
    for k in range(7):
        assert along[k] == pytest.approx(float(rsd(a[k], b[k])), nan_ok=True)
    floors = random_mixture_rsd(a.T, b.T, axis=0)
    for k in range(7):
        assert floors[k] == pytest.approx(float(random_mixture_rsd(a[k], b[k])), nan_ok=True)


def test_random_mixture_floor_is_the_binomial_sampling_noise():
    # Monte-Carlo check of the analytic floor (seeded): mean sample variance of binomial fractions
    rng = np.random.default_rng(7)
    n = np.array([3, 5, 8, 13, 21])
    p = 0.3
    x = rng.binomial(n, p, size=(200_000, n.size))
    var = np.mean(np.var(x / n, axis=1, ddof=1))
    assert float(random_mixture_rsd(p * n, (1 - p) * n)) == pytest.approx(math.sqrt(var) / p, rel=5e-3)
    assert math.isnan(float(random_mixture_rsd([1, 0], [0, 0])))  # one non-empty compartment


def test_outflow_fraction():
    assert outflow_fraction_a(np.array([1.0, 0.0]), np.array([3.0, 0.0]))[0] == 0.25
    assert np.isnan(outflow_fraction_a(np.array([1.0, 0.0]), np.array([3.0, 0.0]))[1])


def test_steady_state_rule():
    t = np.arange(1.0, 201.0)
    rule = SteadyStateRule(window_s=10.0, rel_tol=0.02)
    assert rule.time(t, 100 * t) is None  # a linear rise never passes
    holdup = 1000 * (1 - np.exp(-t / 20))
    found = rule.time(t, holdup)

    def change(s):  # |m1 - m0| / m1 over the windows (s-10, s] and (s-20, s-10]
        m1 = holdup[(t > s - 10) & (t <= s)].mean()
        m0 = holdup[(t > s - 20) & (t <= s - 10)].mean()
        return abs(m1 - m0) / m1

    assert found is not None and change(found) <= 0.02 < change(found - 1)
    # unknown values (before the first DEM dump) spoil only the windows that hold them
    early_nan = holdup.copy()
    early_nan[:3] = np.nan
    assert rule.time(t, early_nan) == found


@pytest.mark.parametrize("kwargs", [{"window_s": 0.0}, {"window_s": math.inf}, {"rel_tol": 1.0}, {"rel_tol": math.nan}])
def test_steady_state_rule_refuses_bad_values(kwargs):
    with pytest.raises(ConfigError, match="steady_state"):
        SteadyStateRule(**kwargs)


def test_dem_and_pbm_give_the_same_cqas_for_the_same_counts(tmp_path):
    """A DEM snapshot and a PBM state holding the same particles report the same RSDs."""
    from coupling.tables import make_table
    from dem.config import DemConfig, TablesConfig
    from dem.dumps import format_snapshot
    from dem.post import postprocess
    from pbm import PbmConfig, simulate

    cfg = DemConfig(tables=TablesConfig(nx=2, ny=2, window_s=1.0, sample_interval_s=1.0, min_samples=1))
    # slice 1 (x > L/2): 3 A + 1 B at j = 0, 1 A + 1 B at j = 1; slice 0: 2 A at j = 1
    rows = [(1, 1, 0.2, -0.02), (2, 1, 0.2, -0.02), (3, 1, 0.2, -0.02), (4, 2, 0.2, -0.02),
            (5, 1, 0.2, 0.02), (6, 2, 0.2, 0.02), (7, 1, 0.05, 0.02), (8, 1, 0.05, 0.02)]
    data = np.array([(i, t, x, y, 0, 0, 0, 0, 0.003) for i, t, x, y in rows], dtype=float)
    step = int(round(1.0 / cfg.timestep_s))
    columns = ("id", "type", "x", "y", "z", "vx", "vy", "vz", "radius")
    (tmp_path / f"dump.{step}.txt").write_bytes(format_snapshot(step, columns, data))
    dem = postprocess(str(tmp_path / "dump.*.txt"), cfg).summary

    counts = np.zeros((2, 2, 2))
    counts[0, 1] = [3, 1]
    counts[1, 1] = [1, 1]
    counts[0, 0, 1] = 2
    table = make_table([0.0], [0, 0.165, 0.33], [-0.05, 0, 0.05], 0, 0, 0, 0)
    pbm = simulate(table, PbmConfig(feed_rate_a_per_s=0, feed_rate_b_per_s=0, duration_s=1.0),
                   initial_counts=counts).summary
    assert pbm["final_rsd_outlet"] == pytest.approx(dem["final_rsd_outlet"])
    assert pbm["final_rsd_blender"] == pytest.approx(dem["final_rsd_blender"])
