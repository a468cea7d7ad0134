"""The hidden-phase study end to end on known dumps: A particles cross the synthetic blender
in 4 s and B particles in 6 s, so the DEM carries two hidden mobility classes; two phases
must score better out of sample than one, and the PBM's mean residence time must follow
the DEM's (5 s). Its command line refuses what it cannot study, in one line."""

import json

import pytest

from coupling.cache import save_entry
from dem.phases import PhaseSettings
from dem.post import postprocess
from tests.known_dumps import STEADY, config, write_synthetic
from workflows.cli.main import main
from workflows.config import Config, dump_toml
from workflows.shipped import REDUCED_RUN
from workflows.studies.phases import add_arguments, phase_study, settings_of

ONE_START = PhaseSettings(starts=1)


@pytest.fixture(scope="module")
def results_file(tmp_path_factory):
    directory = tmp_path_factory.mktemp("phases")
    cfg = config()
    write_synthetic(directory, cfg, end_s=80.0)
    results = postprocess(str(directory / "dump.*.txt"), cfg, STEADY)
    assert results.sequences is not None
    provenance = {"key": "synthetic", "config_toml": dump_toml(Config(dem=cfg, steady_state=STEADY))}
    path = directory / "dem.h5"
    save_entry(path, results.to_cache_entry(provenance))
    return path


def test_two_phases_for_two_hidden_classes(results_file):
    study = phase_study(results_file, grids=((4, 1),), ks=(1, 2), settings=ONE_START, log=lambda message: None)
    assert study.target.mean_s.value == pytest.approx(5.0, rel=1e-6)
    one, two = study.results
    assert (one.n_phases, two.n_phases) == (1, 2)
    assert two.held_out_per_step > one.held_out_per_step
    for row in study.results:
        assert row.mean_s == pytest.approx(5.0, rel=0.1)


def test_the_command_writes_its_record(results_file, tmp_path):
    out = tmp_path / "out"
    argv = ["study", "phases", "--results", str(results_file), "--grids", "4x1", "--ks", "1", "--starts", "1"]
    assert main([*argv, "--out", str(out)]) == 0
    record = json.loads((out / "phases.json").read_text())
    assert [r["n_phases"] for r in record["results"]] == [1]


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--grids", "4by1"], "--grids '4by1'"),
        (["--ks", "0"], "must be >= 1"),
        (["--target", "no-such-file.h5"], "--target no-such-file.h5"),
        (["--stagnant", "0"], "--stagnant 0.0"),
        (["--tol", "0"], "--tol 0.0: PhaseSettings.tol = 0.0: expected a gain"),
        (["--lag-s", "-1"], "--lag-s -1.0: PhaseSettings.lag_s"),
    ],
)
def test_bad_arguments_are_one_line(results_file, tmp_path, capsys, extra, message):
    argv = ["study", "phases", "--results", str(results_file), "--out", str(tmp_path), *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err


def test_results_without_sequences_are_refused_by_name(tmp_path, capsys):
    """Results made before the sequences were recorded: the shipped run with them taken out."""
    import dataclasses

    from coupling.cache import load_entry, save_entry

    entry = load_entry(REDUCED_RUN)
    arrays = {k: v for k, v in entry.arrays.items() if not k.startswith("sequences_")}
    old = save_entry(tmp_path / "old.h5", dataclasses.replace(entry, arrays=arrays))
    assert main(["study", "phases", "--results", str(old), "--out", str(tmp_path / "out")]) == 2
    assert "no compartment sequences" in capsys.readouterr().err


def test_parked_tracers_are_the_pooled_tracers_still_inside_with_their_longest_stay():
    """Three slices, one dump a second; ids 1..4. Particle 1 passes in 3 s; 2 sits 5 s in
    slice 0, then 2 s in slice 1, still inside; 3 sits 4 s in slice 2 after 1 s in slice 0
    and never leaves; 4 enters after the window. Window (-0.5, 1.5], horizon 3 s."""
    import numpy as np

    from dem import phases
    from workflows.studies.phases import parked_tracers

    out = 3  # past the weir
    obs = np.full((4, 9), -1)
    obs[0, 0:4] = [0, 1, 2, out]
    obs[1, 1:8] = [0, 0, 0, 0, 0, 1, 1]
    obs[2, 0:5] = [0, 2, 2, 2, 2]
    obs[3, 3:5] = [0, 1]
    seq = phases.sequences_from_padded(obs, np.array([0, 1, 0, 3]), np.array([1, 2, 1, 2]), np.arange(9.0), 1.0, 3, 1)
    entry = np.array([0.0, 1.0, 0.0, 3.0])
    exit_ = np.array([3.0, np.nan, np.nan, np.nan])
    parked = parked_tracers(seq, entry, exit_, np.array([1, 2, 3, 4]), (-0.5, 1.5), 3.0)
    assert (parked.n_entered, parked.n_beyond) == (3, 2)
    assert parked.longest_stay_s == (5.0, 4.0) and parked.slice_of_stay == (0, 2)


def test_the_study_reports_where_a_stagnant_phase_parks_and_how_fast_it_lets_go():
    """The dead zone of tests/dem/test_phases.py (parked at 0.08 /s in the first and last
    slices, left at 0.05 /s): the study's numbers name those slices and that rate."""
    import numpy as np

    from dem import phases
    from tests.dem.test_phases import NX, dead_zone_model, inlet
    from workflows.studies.phases import _stagnant_numbers

    truth = dead_zone_model()
    sequences = phases.simulate_sequences(truth, inlet(), 20000, 3000, np.random.default_rng(11))
    settings = PhaseSettings(n_phases=2, starts=1, tol=1e-7, stagnant_exit_max_per_s=0.2)
    fit = phases.PhaseEstimator(settings).fit(phases.prepare(sequences)).fetch_model()
    numbers = _stagnant_numbers(fit)
    assert numbers["stagnant_slices"] == (0, NX - 1)
    assert numbers["stagnant_exit_per_s"] == pytest.approx(0.05, rel=0.1)
    assert 0.0 < numbers["stagnant_share"] < 0.5


def test_a_stagnant_phase_is_left_at_most_once_per_r_residence_times(results_file):
    """``stagnant=R`` bounds phase 0's leaving rate by 1 / (R x the Little's-law mean
    residence time): the fitted rate respects it for R = 1 and R = 4."""
    for r in (1.0, 4.0):
        study = phase_study(
            results_file, grids=((4, 1),), ks=(2,), settings=ONE_START, stagnant=r, log=lambda message: None
        )
        (row,) = study.results
        assert 0 < row.stagnant_exit_per_s <= 1.0 / (r * study.target.little_mean_residence_time_s) * (1 + 1e-9)


def test_the_study_takes_the_pbms_hold_up_after_its_own_steady_state():
    """A one-phase chain with a slow last slice (it fills over ~100 s) judged against a DEM
    that was steady from 1 s: the study's hold-up is the chain's stationary one (feed x
    mean residence time, to the steady rule's tolerance), not the mean of its filling."""
    import numpy as np

    from coupling.phases import PhaseTransport
    from tests.known_dumps import config
    from workflows.config import Config
    from workflows.studies.phases import DemTarget, Interval, pbm_numbers

    nx = 4
    rates = np.zeros((1, 4, nx, 1))
    rates[0, 0, :, 0] = [2.0, 2.0, 2.0, 0.02]  # forward; the last slice drains in 50 s
    model = PhaseTransport(rates, np.zeros((1, 1, nx, 1)), np.ones((2, 1)), 0.1)
    cfg = Config(dem=config())
    feed = cfg.dem.operation.feed_rate_total_per_s
    stationary = feed * (3 * 0.5 + 50.0)
    wide = Interval(0.0, 0.0, 1e9)
    target = DemTarget(wide, wide, (10.0, 300.0), 400.0, (wide,) * nx, wide, 1.0, "synthetic")
    numbers = pbm_numbers(model, cfg, target)
    assert numbers["holdup"] == pytest.approx(stationary, rel=0.03)
    assert numbers["by_slice"][-1] == pytest.approx(feed * 50.0, rel=0.03)


def test_the_study_fits_with_the_products_settings_unless_told_otherwise():
    """The command line's defaults are the product's settings, one default each; a flag
    changes its field alone."""
    import argparse

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert settings_of(parser.parse_args(["--results", "r.h5"])) == PhaseSettings()
    changed = settings_of(parser.parse_args(["--results", "r.h5", "--tol", "1e-7", "--starts", "3"]))
    assert changed == PhaseSettings(tol=1e-7, starts=3)
