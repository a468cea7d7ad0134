"""The paper-scale probe's readers on synthetic logs and dumps with known answers, the
cluster estimate built on its shipped measurement, the probe end to end on a short real
run, and durations it could not summarise refused before LIGGGHTS starts."""

import json
import os

import numpy as np
import pytest

from coupling.errors import ConfigError
from workflows.cli.main import main
from workflows.config import dump_toml, load_preset
from workflows.shipped import measured_throughput
from workflows.studies.paper_scale import SUMMARY_FILE, dump_throughput, probe_config, summarise, thermo_rows

HEADER = "Step simtime Atoms insA insB outA outB ts[1] ts[2]"


def log_text(rows, warnings=()):
    lines = ["LIGGGHTS (Version LIGGGHTS-PUBLIC 3.8.0)", *warnings, HEADER]
    lines += [" ".join(f"{v:g}" for v in row) for row in rows]
    lines.append("Loop time of 12.5 on 2 procs for 1000 steps with 40 atoms")
    return "\n".join(lines) + "\n"


def feed_rows(rate=1990.0, dt=0.5, end=10.0, lost_at=None, out_from=None):
    rows = []
    for k, t in enumerate(np.arange(0.0, end + 1e-9, dt)):
        ins = rate * t
        out = 0.0 if out_from is None or t < out_from else 0.5 * rate * (t - out_from)
        atoms = ins - out - (3 if lost_at is not None and t >= lost_at else 0)
        rows.append([k * 100, t, atoms, ins / 2, ins / 2, out / 2, out / 2, 0.248, 0.098])
    return rows


def throughput(n=12):
    return {
        "step": np.arange(1, n + 1) * 100.0,
        "particles": np.full(n, 1000.0),
        "wall_s": np.ones(n),
        "particle_steps_per_s": np.full(n, 1e5),
    }


def test_thermo_rows_of_a_resumed_log_keep_one_row_per_step():
    rows = feed_rows(end=2.0)
    first, second = log_text(rows[:4]), log_text(rows[2:])  # the resumed part repeats steps 200, 300
    thermo = thermo_rows(first + second)
    np.testing.assert_array_equal(thermo["Step"], [r[0] for r in rows])
    with pytest.raises(ValueError, match="no thermo rows"):
        thermo_rows("nothing here\n")


def test_summary_finds_rate_losses_weir_and_warnings():
    config = probe_config()
    text = log_text(
        feed_rows(lost_at=6.0, out_from=8.0),
        ["WARNING: time-step is 30 % of Rayleigh time", "WARNING: Forced restart written (./src/output.cpp:427)"],
    )
    s = summarise(text, thermo_rows(text), throughput(), config, 2, 600.0)
    assert s["insertion"]["fitted_per_s"] == pytest.approx(1990.0)
    assert s["insertion"]["relative_error"] == pytest.approx(0.0, abs=1e-12)
    assert s["lost_max"] == 3
    assert s["first_discharge_s"] == pytest.approx(8.5) and s["sustained_discharge_s"] == pytest.approx(8.5)
    assert s["timestep_check"]["warnings"] == 1 and s["other_warnings"] == [
        "WARNING: Forced restart written (./src/output.cpp:427)"
    ]
    assert s["throughput"]["late_particle_steps_per_s_per_core"] == pytest.approx(5e4)
    clean = log_text(feed_rows())
    s = summarise(clean, thermo_rows(clean), throughput(), config, 2, 600.0)
    assert s["lost_max"] == 0 and s["first_discharge_s"] is None and s["timestep_check"]["warnings"] == 0


def test_dump_throughput_from_file_times(tmp_path):
    files = []
    for k, (step, n) in enumerate([(0, 100), (1000, 200), (2000, 300), (3000, 400)]):
        path = tmp_path / f"dump.{step}.txt"
        path.write_text(f"ITEM: TIMESTEP\n{step}\nITEM: NUMBER OF ATOMS\n{n}\n")
        os.utime(path, (1000.0 + 2.0 * k, 1000.0 + 2.0 * k))
        files.append(path)
    t = dump_throughput(files[::-1])  # any order
    np.testing.assert_allclose(t["particles"], [150, 250, 350])
    np.testing.assert_allclose(t["particle_steps_per_s"], np.array([150, 250, 350]) * 1000 / 2.0)
    bad = tmp_path / "bad.txt"
    bad.write_text("not a dump\n")
    with pytest.raises(ValueError, match="bad.txt"):
        dump_throughput([bad])


def test_measured_throughput_only_for_the_same_particles(tmp_path):
    path = tmp_path / "summary.json"
    path.write_text(
        json.dumps(
            {
                "config_toml": dump_toml(probe_config()),
                "np": 2,
                "simulated_s": 12.0,
                "throughput": {"late_particle_steps_per_s_per_core": 1.7e6, "late_particles_mean": 22000.0},
            }
        )
    )
    rate, source, ranks = measured_throughput(load_preset("paper").dem, path)
    assert rate == 1.7e6 and "paper scale" in source and ranks == 2
    assert measured_throughput(load_preset("smoke").dem, path) is None
    assert measured_throughput(load_preset("paper").dem, tmp_path / "absent.json") is None
    path.write_text("{broken")
    with pytest.raises(ConfigError, match="summary.json"):
        measured_throughput(load_preset("paper").dem, path)


def test_shipped_measurement_drives_the_paper_estimate(tmp_path, capsys):
    summary = json.loads(SUMMARY_FILE.read_text())
    assert summary["lost_max"] == 0 and summary["timestep_check"]["warnings"] == 0
    assert abs(summary["insertion"]["relative_error"]) < 0.01
    assert main(["dem", "slurm", "--preset", "paper", "--np", "2", "--out", str(tmp_path / "run")]) == 0
    out = capsys.readouterr().out
    assert "measured at paper scale" in out and "at 100% parallel efficiency" in out  # measured on 2 ranks


@pytest.mark.liggghts
def test_a_short_real_probe_inserts_at_the_configured_rate_and_loses_nothing(tmp_path, capsys):
    """The probe end to end on a real LIGGGHTS run: the ``smoke`` preset's first 1.5 s
    (the shortest it can fit an insertion rate from) on 2 ranks, about 15 s of wall time
    (the paper preset's 1.5 s take 1.5 to 3 min on two shared cores). What it writes is what
    ``pbmdem dem slurm`` reads, for runs of the probed particles only."""
    out, figure = tmp_path / "out", tmp_path / "probe.png"
    argv = ["study", "paper-scale", "--preset", "smoke", "--duration", "1.5", "--runs-dir", str(tmp_path / "runs")]
    assert main([*argv, "--out", str(out), "--figure", str(figure)]) == 0
    summary = json.loads((out / SUMMARY_FILE.name).read_text())
    assert summary["preset"] == "smoke" and summary["state"] == "completed" and summary["np"] == 2
    assert not summary["stopped_at_wall_limit"] and summary["simulated_s"] == pytest.approx(1.5, abs=0.01)
    # measured: 72 /s fitted against 73.7 configured; per feeder 34 and 38 /s against 36.85
    # (two thermo rows 0.5 s apart, a few particles per batch)
    insertion = summary["insertion"]
    assert abs(insertion["relative_error"]) < 0.05
    assert insertion["fitted_A_per_s"] + insertion["fitted_B_per_s"] == pytest.approx(insertion["fitted_per_s"])
    for feeder in "AB":
        assert insertion[f"fitted_{feeder}_per_s"] == pytest.approx(73.7 / 2, rel=0.2)
    assert summary["lost_max"] == 0
    assert summary["particles_at_end"] + summary["discharged"] == insertion["inserted"]
    check = summary["timestep_check"]
    assert check["warnings"] == 0 and check["max_rayleigh_fraction"] <= check["rayleigh_limit"]
    rows = np.genfromtxt(out / "thermo.csv", delimiter=",", names=True)
    assert rows["simtime"][-1] == pytest.approx(1.5, abs=0.01) and np.all(np.diff(rows["Atoms"]) >= 0)
    rate, _source, ranks = measured_throughput(load_preset("smoke").dem, out / SUMMARY_FILE.name)
    assert rate == summary["throughput"]["late_particle_steps_per_s_per_core"] > 0 and ranks == 2
    assert measured_throughput(load_preset("paper").dem, out / SUMMARY_FILE.name) is None
    assert figure.stat().st_size > 5_000
    assert "lost particles: 0" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--duration", "1.2"], "duration 1.2 s is too short to fit an insertion rate: expected >= 1.5 s"),
        (["--duration", "0"], "the probe's duration must be > 0 s, got 0.0"),
        (["--max-wall-min", "0"], "max_wall_s must be > 0 s"),
    ],
)
def test_a_probe_that_cannot_be_summarised_is_refused_before_the_solver_starts(tmp_path, capsys, extra, message):
    runs = tmp_path / "runs"
    assert main(["study", "paper-scale", *extra, "--runs-dir", str(runs), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not runs.exists() and not (tmp_path / "out").exists()
