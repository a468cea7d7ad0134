"""Bad inputs raise named errors; ensembles; output files and the ``pbmdem pbm`` CLI."""

import csv
import json

import numpy as np
import pytest

from coupling.errors import ConfigError, TableError
from coupling.tables import make_table, write_table
from pbm import PbmConfig, noise_ensemble, noise_study, simulate, synthetic_table, write_outputs
from pbm.plots import FIGURES
from workflows.cli.main import main
from workflows.config import config_from_dict, load_preset


@pytest.fixture(scope="module")
def small_table():
    return synthetic_table(nx=5, ny=4, n_windows=6, window_s=5.0, seed=21)


@pytest.mark.parametrize(
    ("pbm", "message"),
    [
        ({"feed_rate_a_per_s": -1.0}, "'pbm.feed_rate_a_per_s' = -1.0"),
        ({"feed_rate_b_per_s": float("nan")}, "'pbm.feed_rate_b_per_s'"),
        ({"output_interval_s": 0.0}, "'pbm.output_interval_s' = 0.0"),
        ({"noise_interval_s": -2.0}, "'pbm.noise_interval_s' = -2.0"),
        ({"duration_s": 0.0}, "'pbm.duration_s' = 0.0"),
        ({"feed_weights_a": [1.0, -1.0]}, "weights must be finite and >= 0, got -1.0"),
        ({"feed_weights_b": [0.0, 0.0]}, "at least one weight must be > 0"),
        ({"feed_weights_b": []}, "got an empty list"),
        ({"rtd_bin_s": 0.0}, "'pbm.rtd_bin_s' = 0.0"),
        ({"steady_window_s": 5.0}, "unknown key 'pbm.steady_window_s'"),  # one rule, in [steady_state]
        ({"method": "rk4"}, "'pbm.method' = 'rk4'"),
        ({"rates": "dem"}, "'pbm.rates' = 'dem'"),
        ({"rtd_pulse_s": -1.0}, "'pbm.rtd_pulse_s' = -1.0"),
        ({"feed_rate_a": 1.0}, "did you mean 'feed_rate_a_per_s'"),
    ],
)
def test_bad_config_values_raise_config_error(pbm, message):
    with pytest.raises(ConfigError) as err:
        config_from_dict({"pbm": pbm})
    assert message in str(err.value)


def test_settings_the_table_cannot_satisfy_raise_config_error(small_table):
    with pytest.raises(ConfigError, match=r"RTD pulse time 40.0 s must lie in \[0, 30.0\) s"):
        simulate(small_table, rtd_pulse_s=40.0)
    with pytest.raises(ConfigError, match="feed_weights_b has 3 entries; .* NY = 4"):
        simulate(small_table, PbmConfig(feed_weights_b=[1.0, 1.0, 1.0]))
    with pytest.raises(ConfigError, match="shorter than output_interval_s"):
        simulate(small_table, PbmConfig(duration_s=0.5))
    with pytest.raises(ConfigError, match=r"initial_counts must be .* \(2, 5, 4\)"):
        simulate(small_table, initial_counts=np.zeros((2, 4, 4)))
    with pytest.raises(ConfigError, match="members must be an integer >= 1, got 0"):
        noise_ensemble(small_table, members=0)
    with pytest.raises(ConfigError, match="noise sigma must be a finite number >= 0, got -0.1"):
        noise_ensemble(small_table, sigma=-0.1)


def test_bad_tables_raise_table_error(tmp_path):
    with pytest.raises(TableError, match="vx_pos"):
        make_table(t=[0.0], x_edges=[0, 1], y_edges=[0, 1], vx_pos=-1.0, vx_neg=0, vy_pos=0, vy_neg=0)
    empty = make_table(
        t=[0.0], x_edges=[0, 1], y_edges=[-1, 1], vx_pos=1.0, vx_neg=0, vy_pos=0, vy_neg=0, n_samples=0, min_samples=1
    )
    with pytest.raises(TableError, match="no compartment-window"):
        simulate(empty)


def test_ensemble_member_zero_is_the_single_run_and_sigma_zero_collapses(small_table):
    config = PbmConfig(noise_sigma=0.2, duration_s=30.0, seed=99)
    ens = noise_ensemble(small_table, config, members=16)
    single = simulate(small_table, config, rtd_pulse_s=0.0)
    np.testing.assert_allclose(ens.C_A_members[0], single.C_A, rtol=1e-10)
    np.testing.assert_allclose(ens.rsd_outlet_members[0], single.rsd_outlet, rtol=1e-8)
    assert np.all(ens.C_A_p05 <= ens.C_A_mean + 1e-12) and np.all(ens.C_A_mean <= ens.C_A_p95 + 1e-12)
    assert np.max(ens.C_A_p95 - ens.C_A_p05) > 1e-3  # noise really spreads the members
    study = noise_study(small_table, config, sigmas=(0.0, 0.1), members=4)
    flat = study[0.0]
    deterministic = simulate(small_table, config.model_copy(update={"noise_sigma": 0.0}), rtd_pulse_s=0.0)
    np.testing.assert_allclose(flat.C_A_p05, flat.C_A_p95)
    np.testing.assert_allclose(flat.C_A_mean, deterministic.C_A, rtol=1e-10)
    np.testing.assert_allclose(flat.rsd_by_slice_mean, deterministic.rsd_by_slice_final, rtol=1e-8)


def test_write_outputs_files_and_columns(small_table, tmp_path):
    result = simulate(small_table, PbmConfig(duration_s=30.0))
    paths = write_outputs(result, tmp_path / "out")
    with open(paths["timeseries"]) as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == [
        "t_s",
        "outflow_A_per_s",
        "outflow_B_per_s",
        "C_A",
        "rsd_outlet",
        "rsd_blender",
        "holdup_A",
        "holdup_B",
    ]
    assert len(rows) == 31 and float(rows[1][0]) == 1.0
    with open(paths["rtd"]) as fh:
        assert next(csv.reader(fh)) == ["t_s", "E_per_s"]
    summary = json.loads(paths["summary"].read_text())
    for key in (
        "mean_residence_time_s",
        "rtd_variance_s2",
        "rtd_recovered_fraction",
        "steady_outflow_per_s",
        "steady_C_A",
        "final_rsd_outlet",
        "final_rsd_by_slice",
        "holdup_final",
        "wall_time_s",
    ):
        assert key in summary
    assert len(summary["final_rsd_by_slice"]) == 5
    for name in FIGURES:
        assert (tmp_path / "out" / f"{name}.png").stat().st_size > 1000


def test_cli_synth_then_run(tmp_path, capsys):
    table_path = tmp_path / "t.h5"
    assert main(["pbm", "synth", "--out-file", str(table_path), "--nx", "4", "--ny", "4", "--windows", "4"]) == 0
    out = tmp_path / "run"
    assert (
        main(
            [
                "pbm",
                "run",
                "--tables",
                str(table_path),
                "--preset",
                "smoke",
                "--rtd-pulse",
                "2",
                "--out",
                str(out),
                "--no-figures",
            ]
        )
        == 0
    )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["rtd_pulse_s"] == 2.0 and summary["rtd_pulse_rule"] == "given"
    # The smoke preset's feed reaches the PBM.
    smoke = load_preset("smoke").pbm
    fed = smoke.feed_rate_a_per_s + smoke.feed_rate_b_per_s
    ts = np.genfromtxt(out / "timeseries.csv", delimiter=",", names=True)
    assert ts["holdup_A"][0] + ts["holdup_B"][0] == pytest.approx(fed * 1.0, rel=0.05)
    assert "PBM (velocity rates) 4x4" in capsys.readouterr().out
    # a synthetic table has no measured rates: asking for them is refused before writing
    assert main(["pbm", "run", "--tables", str(table_path), "--rates", "measured", "--out", str(tmp_path / "m")]) == 2
    assert "no measured rates" in capsys.readouterr().err and not (tmp_path / "m").exists()


def test_cli_runs_every_rate_mode_the_table_supports(tmp_path, capsys):
    table = synthetic_table(nx=3, ny=2, n_windows=2)
    rates = {name: table.vx_pos / table.dx[:, None] for name in ("rate_x_pos", "rate_x_neg")}
    rates.update({name: table.vy_pos / table.dy[None, :] for name in ("rate_y_pos", "rate_y_neg")})
    write_table(tmp_path / "t.h5", table.replace(**rates))
    assert (
        main(
            [
                "pbm",
                "run",
                "--tables",
                str(tmp_path / "t.h5"),
                "--rates",
                "all",
                "--out",
                str(tmp_path / "o"),
                "--no-figures",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "(velocity rates)" in out and "(measured rates)" in out
    assert (tmp_path / "o" / "velocity" / "summary.json").exists() and (
        tmp_path / "o" / "measured" / "summary.json"
    ).exists()


def test_cli_errors_exit_2_with_a_message(tmp_path, capsys):
    assert main(["pbm", "run", "--tables", str(tmp_path / "missing.h5"), "--out", str(tmp_path)]) == 2
    assert "does not exist" in capsys.readouterr().err
    table = synthetic_table(nx=3, ny=2, n_windows=2)
    write_table(tmp_path / "t.h5", table)
    assert main(["pbm", "run", "--tables", str(tmp_path / "t.h5"), "--rtd-pulse", "99", "--out", str(tmp_path)]) == 2
    assert "RTD pulse time 99.0 s" in capsys.readouterr().err


def test_studies_run_and_plot(small_table, tmp_path):
    from pbm import geometry_study, grid_study
    from pbm.plots import plot_ensemble, plot_rsd_by_slice_family, plot_rsd_time_family

    config = PbmConfig(duration_s=20.0)
    geo = geometry_study(small_table, config, length_factors=(1.0, 2.0), diameter_factors=(1.0,), rtd_pulse_s=0.0)
    # A longer blender holds the particles longer.
    assert geo["length"][2.0].summary.mean_residence_time_s > geo["length"][1.0].summary.mean_residence_time_s
    grids = grid_study(small_table, config, grids=((3, 2), (10, 8)), rtd_pulse_s=0.0)
    assert grids[(10, 8)].rsd_by_slice_final.shape == (10,)
    ens = noise_study(small_table, config, sigmas=(0.0, 0.2), members=3)
    for ax in (
        plot_ensemble(ens, "C_A"),
        plot_ensemble(ens, "rsd_outlet"),
        plot_rsd_by_slice_family(geo["length"]),
        plot_rsd_time_family(grids),
    ):
        ax.figure.savefig(tmp_path / "f.png")
    with pytest.raises(ValueError, match="quantity must be"):
        plot_ensemble(ens, "holdup")


@pytest.mark.slow
def test_bench_main_writes_json(tmp_path, capsys):

    out = tmp_path / "pbm.json"
    args = ["--repeats", "1", "--bdf-repeats", "1", "--members", "4", "--kernel-repeats", "1", "--no-loaded"]
    assert main(["bench", "pbm", *args, "--out-file", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["scenario"]["windows"] == 52 and report["ensemble"]["members"] == 4
    assert max(report["max_rel_diff_expm_vs_bdf"].values()) < 1e-5
    out = capsys.readouterr().out
    assert "speed-up vs BDF" in out and "products alone" in out
    profile = report["profile"]
    assert profile["exponentials"] == 52 and profile["dense_products"] >= 5 * 52
    kernels = sum(
        seconds for stage, seconds in profile["stages_s"].items() if "kernel" in stage or "operators" in stage
    )
    assert 0 < kernels <= profile["total_s"]
    rows = report["kernels"]["rows"]
    assert set(rows) >= {"10x10 measured", "20x10 measured", "10x10 phases K=1", "10x10 phases K=3"}
    for row in rows.values():
        assert row["action"]["max_rel_diff_vs_dense"] < 1e-9 and row["auto"]["max_rel_diff_vs_dense"] < 1e-9
        assert row["action_multiply_adds"] > 0 and row["dense_products"] >= 5
