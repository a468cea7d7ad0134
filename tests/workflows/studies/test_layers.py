"""The layered-compartment study (workflows/study_layers.py): its grid, its binning, and its
chain fit and RTD on chains with known answers."""

import numpy as np
import pytest

from dem.rates import allowed_transitions, simulate_observations
from workflows.studies.layers import Snapshots, chain_data, chain_rtd, fit_chain, parse_grid, states

DT = 0.1


def test_parse_grid():
    assert parse_grid("10x10") == (10, 10, 1)
    assert parse_grid("10X1x3") == (10, 1, 3)
    for bad in ("10", "10x0", "axb", "1x2x3x4"):
        with pytest.raises(ValueError, match="NXxNY"):
            parse_grid(bad)


def test_layered_pattern_reduces_to_the_tables_grid():
    flat, layered = allowed_transitions(4, 3), allowed_transitions(4, 3, 1)
    assert set(flat) == set(layered) == {"x_pos", "x_neg", "y_pos", "y_neg"}
    for key in flat:
        for a, b in zip(flat[key], layered[key]):
            np.testing.assert_array_equal(a, b)
    three = allowed_transitions(2, 1, 3)
    assert set(three) == {"x_pos", "x_neg", "y_pos", "y_neg", "z_pos", "z_neg"}
    src, dst, _ = three["z_pos"]
    assert list(zip(src, dst)) == [(0, 1), (1, 2), (3, 4), (4, 5)]  # no move up out of the top layer
    src, dst, _ = three["x_pos"]
    assert list(zip(src, dst)) == [(0, 3), (1, 4), (2, 5), (3, 6), (4, 6), (5, 6)]  # every layer discharges


def test_states_bin_by_slice_side_and_layer():
    xyz = np.array([[0.01, 0.29, 0.31, -0.01], [-0.04, 0.04, 0.0, 0.0], [-0.045, 0.02, 0.0, 0.0]])
    s = states(xyz, 0.3, 0.1, (3, 2, 2), np.array([-0.03]))
    # (i * NY + j) * NZ + l: bottom-left of slice 0; top-right of slice 2; past the weir; upstream
    assert s.tolist() == [0, (2 * 2 + 1) * 2 + 1, 12, -1]


def _layered_truth(nx, nz):
    transitions = allowed_transitions(nx, 1, nz)
    rates = {"x_pos": 1.5, "x_neg": 0.6, "y_pos": 0.0, "y_neg": 0.0, "z_pos": 4.0, "z_neg": 6.0}
    q = np.zeros((nx * nz + 1,) * 2)
    for key, (src, dst, _) in transitions.items():
        q[src, dst] = rates[key] * (1 + 2 * (src % nz)) if key.startswith("x") else rates[key]  # faster on top
    q[np.diag_indices_from(q)] = -q.sum(axis=1)
    return q


def test_fit_chain_recovers_a_layered_generator(rng):
    nx, nz = 4, 3
    truth = _layered_truth(nx, nz)
    counts = simulate_observations(truth, np.full(nx * nz, 60_000), 20, DT, rng)
    q, fit = fit_chain(counts, (nx, 1, nz), DT)
    assert fit["converged"]
    moved = truth > 0
    error = np.abs(q[moved] - truth[moved]) / truth[moved]
    assert error.max() < 0.05, f"worst rate error {error.max():.3f}"


def test_chain_rtd_of_one_tank_is_exponential():
    k = 0.5
    q = np.array([[-k, k], [0.0, 0.0]])
    rtd = chain_rtd(q, np.array([1.0]), horizon_s=60.0, step_s=0.01)
    # truncated at 30 mean residence times: mean 1/k and variance 1/k^2, to the midpoint rule
    assert rtd["recovered_fraction"] == pytest.approx(1.0, abs=1e-10)
    assert rtd["mean_s"] == pytest.approx(1 / k, rel=1e-3)
    assert rtd["variance_s2"] == pytest.approx(1 / k**2, rel=1e-3)


def _write_dump(path, step, atoms):
    lines = [
        "ITEM: TIMESTEP",
        str(step),
        "ITEM: NUMBER OF ATOMS",
        str(len(atoms)),
        "ITEM: BOX BOUNDS ff ff ff",
        "-0.1 0.5",
        "-0.1 0.1",
        "-0.1 0.1",
        "ITEM: ATOMS id type x y z",
    ]
    lines += [f"{pid} 1 {x} {y} {z}" for pid, x, y, z in atoms]
    path.write_text("\n".join(lines) + "\n")


def test_chain_data_counts_moves_and_discharges_from_dumps(tmp_path):
    # 2 slices x 1 side x 2 layers split at z = 0: states 0 / 1 (slice 0 bottom / top),
    # 2 / 3 (slice 1), 4 outside
    low, high = -0.02, 0.02
    _write_dump(tmp_path / "dump.0.txt", 0, [(1, 0.05, 0, low), (2, 0.2, 0, low), (3, 0.2, 0, high)])
    _write_dump(tmp_path / "dump.100.txt", 100, [(1, 0.05, 0, high), (4, 0.05, 0, low)])
    _write_dump(tmp_path / "dump.200.txt", 200, [(1, 0.2, 0, high), (4, 0.05, 0, low)])
    snaps = Snapshots(str(tmp_path / "dump.*.txt"), 1e-3)
    assert snaps.t.tolist() == [0.0, 0.1, 0.2]
    # particle 2 was discharged, particle 3 lost (not counted), particle 4 entered at 0.1 s
    counts, first = chain_data(snaps, (2, 1, 2), np.array([0.0]), 0.3, 0.1, 0.0, discharged=np.array([2]))
    expected = np.zeros((5, 5), int)
    expected[0, 1] = expected[1, 3] = expected[2, 4] = expected[0, 0] = 1
    np.testing.assert_array_equal(counts, expected)
    assert first[1:5].tolist() == [0, 2, 3, 0]
