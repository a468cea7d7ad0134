"""The seed-scatter benchmark's pieces: config overrides, and the table difference that
judges a deck change (zero for identical tables, the relative RMS otherwise); and (marked
``liggghts``) the whole benchmark on two short real runs."""

import json

import numpy as np
import pytest

from coupling.errors import ConfigError
from coupling.tables import make_table
from workflows.bench.scatter import FIELDS, largest, next_prime, table_difference
from workflows.cli.main import main
from workflows.config import load_preset, override


def _table(scale=1.0, windows=5):
    return make_table(
        np.arange(windows) * 5.0,
        np.linspace(0, 0.33, 5),
        np.linspace(-0.05, 0.05, 3),
        0.1 * scale,
        0.05 * scale,
        0.02 * scale,
        0.03 * scale,
        count_A=2.0,
        count_B=3.0,
        n_samples=10,
        window_s=5.0,
    )


def test_identical_tables_differ_by_nothing_and_a_scaled_one_by_its_scale():
    a = _table()
    assert all(v == 0 for v in table_difference(a, a).values())
    diff = table_difference(a, _table(scale=1.1))
    # rms(0.1 v) / sqrt(mean((v^2 + 1.21 v^2) / 2)) = 0.1 / sqrt(1.105)
    assert diff["vx_pos"] == pytest.approx(0.1 / np.sqrt(1.105))
    assert diff["particles"] == 0


def test_a_change_and_a_seed_are_config_overrides():
    base = load_preset("smoke")
    changed = override(base, "dem.geometry.inlet_margin_m=0.005")
    assert changed.dem.geometry.inlet_margin_m == 0.005 and base.dem.geometry.inlet_margin_m == 0.12
    seed = next_prime(15486863)
    assert seed > 15486863 and override(base, f"dem.numerics.seed={seed}").dem.numerics.seed == seed
    assert override(base, "dem.geometry.inlet_margin_m=none").dem.geometry.inlet_margin_m is None
    with pytest.raises(ConfigError, match="no section 'nonsense'"):
        override(base, "dem.nonsense.x=1")
    with pytest.raises(ConfigError, match="expected PATH=VALUE"):
        override(base, "dem.geometry.inlet_margin_m")
    with pytest.raises(ConfigError, match="not prime"):
        override(base, "dem.numerics.seed=15486863")


@pytest.mark.liggghts
@pytest.mark.slow
def test_two_short_seed_runs_and_a_change_that_changes_nothing(tmp_path, capsys):
    """Two 3-s smoke runs binned in 1-s windows (the fast variant: ``--set`` changes every
    run) and, as the change, smoke's own inlet margin: the same inputs, so the first seed's
    results serve it, its difference from that seed is exactly zero and its effect is the
    seeds' scatter."""
    out = tmp_path / "scatter.json"
    short = ["dem.operation.duration_s=3", "dem.tables.window_s=1", "steady_state.window_s=1"]
    argv = ["--seeds", "2", *(a for s in short for a in ("--set", s)), "--change", "dem.geometry.inlet_margin_m=0.12"]
    assert main(["bench", "scatter", *argv, "--runs-dir", str(tmp_path / "runs"), "--out-file", str(out)]) == 0
    record = json.loads(out.read_text())
    first, second = record["seeds"]
    assert record["set"] == short and first == f"seed {load_preset('smoke').dem.numerics.seed}"
    assert record["runs"]["change"] == record["runs"][first] != record["runs"][second]
    same = record["change_vs_seeds"][f"change vs {first}"]
    # nothing is discharged in 3 s: the discharge's relative differences are undefined (NaN)
    assert all(same[name] == 0 for name in (*FIELDS, "holdup_final"))
    for name in FIELDS:
        # another seed fills another bed: the tables differ, by at most the relative RMS's bound of 2
        assert 0 < record["seed_scatter"][name] < 2
        assert record["change_effect"][name] == record["seed_scatter"][name] and record["within_scatter"][name]
    assert capsys.readouterr().out.splitlines()[-1] == f"wrote {out}"


def test_the_largest_difference_is_undefined_where_any_run_leaves_it_undefined():
    nan = float("nan")
    assert largest([0.1, 0.3, 0.2]) == 0.3
    # whichever run comes first: max() alone gives 0.3 for one order and NaN for the other
    assert np.isnan(largest([nan, 0.3])) and np.isnan(largest([0.3, nan]))
