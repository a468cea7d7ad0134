"""The uniformization kernel (pbm.action) against the dense exponential path it stands in for.

The dense path is the reference: the action kernel must give the same states to 1e-9 of
their scale (it is accurate to ~1e-12) whatever the windows, step lengths, feeds and
pulses of a march, on velocity, measured and phase-model generators.
"""

from pathlib import Path

import numpy as np
import pytest

from coupling.phases import kinds
from coupling.tables import read_table
from pbm import PbmConfig, simulate, synthetic_table
from pbm.action import MAX_MEAN, diagonals
from pbm.model import feed_distribution, filled_table, generator_matrix, generator_triplets
from pbm.solver import Propagators, breakpoints, choose_kernel, kernel_costs, march, multiples

REFERENCE = Path(__file__).resolve().parents[2] / "workflows" / "reference" / "dem-17ea4c9cc143cd3e.h5"


@pytest.fixture(scope="module")
def shipped():
    return read_table(REFERENCE)


def _march(table, rates, kernel, times, z0, feed_rates, feed_key, injections):
    filled, _ = filled_table(table, rates)
    feed = feed_distribution(table, None, None, rates)
    props = Propagators(filled, feed, rates, kernel)
    out = np.empty((times.size, *z0.shape))
    out[0] = z0 + injections.get(0, 0.0)
    for b, z in march(props, times, z0, feed_rates, feed_key, injections):
        out[b] = z
    return out


def _scenario(table, m, columns=3, seed=0):
    """Breakpoints off every grid (windows, outputs at 0.7 s, a 1.3-s noise grid), a noisy
    feed per column, and pulses in the last column at the start and at a breakpoint mid-run."""
    rng = np.random.default_rng(seed)
    t_end = table.t_end
    times = breakpoints(0.0, t_end, table.t, multiples(0.7, 0.0, t_end), multiples(1.3, 0.0, t_end))
    mids = 0.5 * (times[:-1] + times[1:])
    feed_key = np.floor(mids / 1.3).astype(int)
    factors = rng.uniform(0.5, 1.5, size=(feed_key.max() + 1, 2, columns))

    def feed_rates(key):
        r = 30.0 * factors[key]
        r[:, -1] = 0.0
        return r

    z0 = np.zeros((m, columns))
    z0[: m - 3, 0] = rng.uniform(0, 5, m - 3)
    pulse = np.zeros((m, columns))
    pulse[:5, -1] = 7.0
    return times, z0, feed_rates, feed_key, {0: 0.5 * pulse, times.size // 3: pulse}


def _relative(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


@pytest.mark.parametrize("rates", ["velocity", "measured", "phases"])
def test_action_equals_dense_on_the_shipped_table(shipped, rates):
    m = generator_matrix(filled_table(shipped, rates)[0], 0, rates).shape[0]
    args = _scenario(shipped, m)
    dense = _march(shipped, rates, "dense", *args)
    action = _march(shipped, rates, "action", *args)
    assert _relative(action, dense) < 1e-9
    # the discharge and both hold-up integrals, which the moments come from
    assert _relative(action[:, m - 3 :], dense[:, m - 3 :]) < 1e-9


def test_action_equals_dense_on_long_steps_and_a_still_window():
    """Steps whose lam h exceeds MAX_MEAN (cut into sub-steps) and a window where nothing
    moves (the rate floor carries the feed and the accumulators)."""
    table = synthetic_table(n_windows=4)
    scale = np.array([4, 4, 0, 4])[:, None, None]
    table = table.replace(vx_pos=table.vx_pos * scale, vx_neg=table.vx_neg * 0)
    table = table.replace(vy_pos=table.vy_pos * scale, vy_neg=table.vy_neg * scale)
    m = table.nx * table.ny + 3
    props = Propagators(table, feed_distribution(table, None, None), "velocity")
    rate = props.diagonals.rate
    assert rate[2] == 1.0 and rate.max() * table.window_s > MAX_MEAN
    times = breakpoints(0.0, table.t_end, table.t)
    z0 = np.ones((m, 2))
    z0[m - 3 :] = 0.0
    feed_key = np.zeros(times.size - 1, int)

    def feed_rates(_key):
        return np.array([[20.0, 0.0], [0.0, 5.0]])

    dense = _march(table, "velocity", "dense", times, z0, feed_rates, feed_key, {})
    action = _march(table, "velocity", "action", times, z0, feed_rates, feed_key, {})
    assert _relative(action, dense) < 1e-9


def test_diagonals_rebuild_the_uniformized_generator(shipped):
    for rates in ("measured", "phases"):
        filled, _ = filled_table(shipped, rates)
        windows = np.arange(1 if rates == "phases" else 3)
        diag = diagonals(*generator_triplets(filled, windows, rates))
        for w in windows:
            g = generator_matrix(filled, w, rates)
            n = g.shape[0] - 3
            b = np.eye(n) + g[:n, :n] / diag.rate[w]
            rebuilt = np.zeros((n, n))
            for j, offset in enumerate(diag.offsets):
                rows = np.arange(max(0, -offset), min(n, n - offset))
                rebuilt[rows, rows + offset] = diag.values[w, j, rows]
            np.testing.assert_allclose(rebuilt, b, rtol=0, atol=1e-15)
            np.testing.assert_allclose(diag.outflow[w], g[n, :n] / diag.rate[w], rtol=0, atol=1e-15)
            assert diag.rate[w] == pytest.approx(-np.diag(g).min())
            assert np.all(diag.values[w] >= 0)


def test_diagonals_refuse_a_generator_of_another_form():
    table = synthetic_table(n_windows=1)
    rows, cols, vals, m = generator_triplets(table, np.arange(1), "velocity")
    # an accumulator feeding back into a population is not the model's form
    assert diagonals(np.append(rows, 0), np.append(cols, m - 1), np.append(vals, [[1.0]], axis=1), m) is None


@pytest.mark.parametrize("rates", ["measured", "phases"])
def test_simulate_gives_the_same_run_with_either_kernel(shipped, rates):
    results = {
        kernel: simulate(shipped, PbmConfig(rates=rates, kernel=kernel, noise_sigma=0.05), rtd_pulse_s=40.0)
        for kernel in ("dense", "action")
    }
    for name in ("holdup_A", "holdup_B", "discharged_A", "discharged_B", "counts", "rtd_E"):
        assert _relative(getattr(results["action"], name), getattr(results["dense"], name)) < 1e-9, name
    for name in ("mean_residence_time_s", "rtd_variance_s2", "holdup_final"):
        assert getattr(results["action"].summary, name) == pytest.approx(
            getattr(results["dense"].summary, name), rel=1e-9
        )


def test_the_cheaper_kernel_is_chosen(shipped):
    """Few columns on a time-varying grid: the action; many columns (an ensemble's unit
    responses), or one operator of 300 states reused all run long (a K = 3 phase model):
    the dense path; the shipped chain per size class (3 x 3 phases, 900 states): the
    action again, its exponentials costing more than all the run's products."""
    t_end = shipped.t_end
    times = breakpoints(0.0, t_end, shipped.t, multiples(1.0, 0.0, t_end))
    steps = np.diff(times)
    one_class = shipped.replace(phases=kinds(shipped.phases)[-1])
    cases = (
        (shipped, "measured", 3, "action"),
        (shipped, "measured", 500, "dense"),
        (one_class, "phases", 3, "dense"),
        (shipped, "phases", 3, "action"),
    )
    for table, rates, columns, expected in cases:
        filled, _ = filled_table(table, rates)
        props = Propagators(filled, feed_distribution(table, None, None, rates), rates)
        windows = props.schedule.windows(times)
        assert choose_kernel(props, windows, steps, columns) == expected, (
            table.phases.n_phases,
            rates,
            columns,
            kernel_costs(props, windows, steps, columns),
        )


def test_unknown_kernel_is_refused():
    table = synthetic_table(n_windows=1)
    with pytest.raises(Exception, match="valid: auto, dense, action"):
        Propagators(table, feed_distribution(table, None, None), "velocity", "sparse")


def test_dense_march_with_live_columns_equals_the_full_march(shipped):
    """Columns that are zero and fed nothing until their step stay zero: propagating only
    the leading live ones gives the full march's states exactly (to rounding)."""
    rates = "measured"
    filled, _ = filled_table(shipped, rates)
    props = Propagators(filled, feed_distribution(shipped, None, None, rates), rates, "dense")
    times = breakpoints(0.0, shipped.t_end, shipped.t, multiples(1.0, 0.0, shipped.t_end))
    feed_key = np.floor(0.5 * (times[:-1] + times[1:]) / 4.0).astype(int)
    columns = 2 * (feed_key.max() + 1)

    def unit_feed(key):
        r = np.zeros((2, columns))
        r[0, 2 * key] = r[1, 2 * key + 1] = 1.0
        return r

    z0 = np.zeros((props.n_states, columns))
    live = 2 * (np.maximum.accumulate(feed_key) + 1)
    full = [z.copy() for _, z in march(props, times, z0, unit_feed, feed_key)]
    lean = [z.copy() for _, z in march(props, times, z0, unit_feed, feed_key, live=live)]
    assert live[0] < columns and len(full) == len(lean)
    assert max(_relative(a, b) for a, b in zip(lean, full)) < 1e-13


def test_a_forked_process_gets_a_pool_of_its_own():
    """A forked process inherits the marches' pool without its threads: work
    queued on it there must still run (it would wait forever on the parent's)."""
    import multiprocessing

    from pbm.solver import shared_pool

    assert shared_pool().submit(int, 1).result() == 1  # the parent's pool has its thread

    def child(queue):
        queue.put(shared_pool().submit(int, 2).result(timeout=20))

    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    process = context.Process(target=child, args=(queue,))
    process.start()
    process.join(30)
    alive = process.is_alive()
    if alive:
        process.kill()
    assert not alive and process.exitcode == 0 and queue.get(timeout=5) == 2
