"""The layered-compartment study (workflows/studies/layers.py): its grid, its binning, and its
chain fit and RTD on chains with known answers; the command end to end on a run directory
of the synthetic blender (tests/known_dumps.py), and bad input in one line.

The study needs a run's dumps, which no shipped data holds, and a pooled RTD, which the
smoke preset's 40 s real run (the session's LIGGGHTS fixture) is too short to have: the
synthetic blender's dumps, discharge files and deck.json make the run directory, with a
plug flow whose answers are known."""

import json
import math

import numpy as np
import pytest

from coupling.cache import load_entry, save_entry
from dem.post import postprocess
from dem.rates import allowed_transitions, simulate_observations
from dem.summary import DemSummary
from tests.known_dumps import STEADY, L, config, write_synthetic
from workflows.cli.main import main
from workflows.config import Config, dump_toml
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


@pytest.fixture(scope="module")
def synthetic_run(tmp_path_factory):
    """(run directory, results file) of the synthetic blender over 80 s: dumps, the discharge
    files a LIGGGHTS run writes (ID and time of each particle over the weir), the deck.json
    keys the study reads, and the results post-processed from those dumps."""
    run_dir = tmp_path_factory.mktemp("layers-run")
    cfg = config()
    truth = write_synthetic(run_dir / "dumps", cfg, end_s=80.0)
    for feeder, ptype in (("A", 1), ("B", 2)):
        rows = [
            f"{pid} {exit_s:.4f} 0.006 {L} 0 0 0 0 0"
            for pid, (kind, _entry, exit_s) in truth.items()
            if kind == ptype and math.isfinite(exit_s)
        ]
        (run_dir / f"discharge_{feeder}.txt").write_text("# ID time  diameter x y z u v w\n" + "\n".join(rows) + "\n")
    deck = {
        "length_m": L,
        "timestep_s": cfg.timestep_s,
        "dump_every_steps": round(0.5 / cfg.timestep_s),
        "massflow_globs": {"A": "discharge_A.txt*", "B": "discharge_B.txt*"},
        "dump_glob": "dumps/dump.*.txt",
    }
    (run_dir / "deck.json").write_text(json.dumps(deck))
    results = postprocess(str(run_dir / "dumps" / "dump.*.txt"), cfg, STEADY, massflow_dir=run_dir)
    provenance = {"key": "synthetic", "config_toml": dump_toml(Config(dem=cfg, steady_state=STEADY))}
    return run_dir, save_entry(run_dir / "dem.h5", results.to_cache_entry(provenance))


def test_the_command_on_a_plug_flow(synthetic_run, tmp_path, capsys):
    """A crosses in 4 s, B in 6 s, equal numbers: the DEM's pooled RTD is mean 5 s,
    variance 1 s^2. No chain of memoryless compartments is that narrow: through NX
    compartments in series its variance is at least mean^2 / NX (the Erlang's, the least
    of any phase-type law of that order). Every particle at one height, layers add nothing:
    4x1x2 is 4x1. A plug flow at constant speed spends equal time in each tenth of the
    length."""
    run_dir, results = synthetic_run
    out = tmp_path / "layers.json"
    argv = ["study", "layers", "--run-dir", str(run_dir), "--results", str(results), "--grids", "4x1,4x2,4x1x2"]
    assert main([*argv, "--out-file", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["dem"]["mean_s"]["value"] == pytest.approx(5.0, rel=1e-6)
    assert record["dem"]["variance_s2"]["value"] == pytest.approx(1.0, rel=1e-5)
    grids = record["grids"]
    assert set(grids) == {"4x1x1", "4x2x1", "4x1x2"}
    for name, chain in grids.items():
        assert chain["mean_s"] == pytest.approx(5.0, rel=0.1), name  # measured 4.73 s
        assert chain["recovered_fraction"] == pytest.approx(1.0, abs=1e-3), name
        assert chain["inside"] == {"mean_s": False, "variance_s2": False}, name  # the DEM's interval is exact
    one = grids["4x1x1"]
    assert one["variance_s2"] >= one["mean_s"] ** 2 / 4  # measured 5.67 against 5.60
    for key in ("mean_s", "variance_s2"):
        assert grids["4x1x2"][key] == pytest.approx(one[key], rel=1e-6)
    assert grids["4x1x2"]["z_edges_m"] == [0.0]
    middle = record["occupancy"]["middle"]  # tau / mean 0.8 and 1.2: every tracer
    assert middle["tracers"] == DemSummary.from_record(load_entry(results).summary).pooled_rtd.n_entered > 100
    assert record["occupancy"]["fast"]["tracers"] == record["occupancy"]["slow"]["tracers"] == 0
    np.testing.assert_allclose(middle["slice_share"], 0.1, atol=0.02)
    assert "4x1x2: mean" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--run-dir", "{tmp}/no-run", "--results", "{results}"], "no deck.json"),
        (["--run-dir", "{run}", "--results", "{tmp}/missing.h5"], "missing.h5"),
        (["--run-dir", "{run}", "--results", "{results}", "--grids", "4by1"], "grid '4by1'"),
    ],
)
def test_bad_input_is_one_line(synthetic_run, tmp_path, capsys, argv, message):
    run_dir, results = synthetic_run
    values = {"tmp": tmp_path, "run": run_dir, "results": results}
    argv = [arg.format(**values) for arg in argv]
    assert main(["study", "layers", *argv, "--out-file", str(tmp_path / "layers.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "layers.json").exists()
