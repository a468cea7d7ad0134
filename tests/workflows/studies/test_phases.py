"""The hidden-phase study end to end on known dumps: A particles cross the synthetic blender
in 4 s and B particles in 6 s, so the DEM carries two hidden mobility classes; two phases
must score better out of sample than one, and the PBM's mean residence time must follow
the DEM's (5 s). Its command line refuses what it cannot study, in one line."""

import json

import pytest

from coupling.cache import save_entry
from dem.post import postprocess
from tests.known_dumps import STEADY, config, write_synthetic
from workflows.cli.main import main
from workflows.config import Config, dump_toml
from workflows.shipped import REDUCED_RUN
from workflows.studies.phases import phase_study


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
    study = phase_study(results_file, grids=((4, 1),), ks=(1, 2), starts=1, log=lambda message: None)
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
