"""``pbmdem library fit`` and ``pbmdem predict`` end to end on shipped runs (few EM
iterations: the files, the refusals and the round trip, not the law's accuracy)."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from coupling.errors import ConfigError
from coupling.tables import read_table
from tests.workflows.prediction.small_library import SPEEDS
from workflows.cli.main import main
from workflows.prediction.library import load_model, quantity_keys
from workflows.shipped import LIBRARY_DIR

VALIDATION = "workflows/presets/validation.toml"


def test_library_fit_writes_a_model_that_reads_back_with_a_law_left_out_per_run(library):
    model = load_model(library)
    assert [r.file for r in model.runs] == [p.name for p in SPEEDS]
    assert len(model.left_out) == 3 and model.calibration is not None
    assert set(model.calibration.whole) == set(quantity_keys())
    assert all(len(row) == 3 for row in model.calibration.left_out["holdup"])
    page = (library / "calibration.md").read_text()
    assert page.startswith("# The library's law") and "## The correction's form" in page
    assert len(list((library / "fits").glob("law-*.json"))) == 4  # the whole fit and one per run left out


def test_predict_writes_every_quantity_a_table_and_a_page(library, tmp_path, capsys):
    assert main(["predict", "--config", VALIDATION, "--library", str(library), "--out", str(tmp_path)]) == 0
    record = json.loads((tmp_path / "prediction.json").read_text())
    assert [q["key"] for q in record["quantities"]] == list(quantity_keys())
    for q in record["quantities"]:
        assert set(q) == {"key", "value", "low", "high"}
        assert q["low"] <= q["value"] <= q["high"]
    assert record["extrapolated"] is False
    table = read_table(tmp_path / "table.h5")
    assert table.phases is not None and table.operating_point.impeller_rpm == 250.0
    page = (tmp_path / "report.html").read_text()
    assert 'src="prediction.png"' in page and (tmp_path / "prediction.png").stat().st_size > 0
    assert "holdup_slice_10" in capsys.readouterr().out
    # the feeders' answer: a band about each value, the step from the feed's C_A to the doubled A's
    dynamics = record["dynamics"]
    for band in (dynamics["vrr"], dynamics["mean_delay_s"]):
        assert band["low"] <= band["value"] <= band["high"]
    c0, c1 = dynamics["ca_before_after"]
    assert c1 == pytest.approx(2 * c0 / (2 * c0 + 1 - c0))
    step = dynamics["step_ca"]
    assert step["value"][0] == pytest.approx(c0) and step["value"][-1] == pytest.approx(c1, abs=2e-3)
    assert all(lo <= v <= hi for lo, v, hi in zip(step["low"], step["value"], step["high"], strict=True))
    # the chain's time scale is the predicted residence time's: a stretch to the interval's
    # ends moves the step's mean delay by the same factor
    mrt = next(q for q in record["quantities"] if q["key"] == "mean_residence_time_s")
    delay = dynamics["mean_delay_s"]
    assert delay["high"] / delay["value"] == pytest.approx(mrt["high"] / mrt["value"], rel=2e-2)
    # the predicted RTD is a density whose mean is the predicted one, inside its band
    rtd = record["rtd"]
    t, e = np.array(rtd["times_s"]), rtd["density_per_s"]
    assert np.all(np.array(e["low"]) <= np.array(e["value"]) + 1e-12)
    assert np.all(np.array(e["value"]) <= np.array(e["high"]) + 1e-12)
    assert np.trapezoid(np.array(e["value"]) * t, t) == pytest.approx(mrt["value"], rel=0.03)
    # the page is made from prediction.json alone, as the forked process makes it
    from workflows.report.prediction import draw

    links = {"prediction.json": "prediction.json", "PBM table (HDF5)": "table.h5"}
    assert draw(record, tmp_path / "again.png", links).replace("again.png", "prediction.png") == page


def test_predict_without_a_config_is_the_validation_baseline_and_set_changes_one_setting(library, tmp_path, capsys):
    base, changed, by_file = tmp_path / "base", tmp_path / "changed", tmp_path / "file"
    run = ["predict", "--library", str(library), "--no-figures", "--out"]
    assert main([*run, str(base)]) == 0
    assert main([*run, str(changed), "--set", "dem.operation.impeller_rpm=200"]) == 0
    config = tmp_path / "rpm200.toml"
    config.write_text(
        Path(VALIDATION).read_text().replace("[dem.operation]\n", "[dem.operation]\nimpeller_rpm = 200\n")
    )
    assert main([*run, str(by_file), "--config", str(config)]) == 0
    records = [json.loads((folder / "prediction.json").read_text()) for folder in (base, changed, by_file)]
    assert records[0]["point"]["impeller_rpm"] == 250 and records[1]["point"]["impeller_rpm"] == 200
    assert records[1]["quantities"] == records[2]["quantities"]  # --set is the file with that one line
    assert records[1]["config"] == "validation with dem.operation.impeller_rpm=200"
    assert records[0]["quantities"] != records[1]["quantities"]
    capsys.readouterr()
    assert main([*run, str(tmp_path / "bad"), "--set", "dem.operation.rpm=200"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "dem.operation.rpm" in err and "impeller_rpm" in err
    assert not (tmp_path / "bad").exists()


def test_the_predict_page_draws_without_the_prediction_code():
    """The process ``predict`` forks to draw its page imports matplotlib alone, so it is
    ready before the prediction is."""
    code = (
        "import sys, workflows.report.prediction; "
        "assert not [m for m in sys.modules if m.startswith(('workflows.prediction', 'dem.', 'pbm.'))]"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_a_point_outside_the_domain_is_refused_in_one_line_and_labelled_when_extrapolated(library, tmp_path, capsys):
    config = tmp_path / "fast.toml"
    config.write_text(
        Path(VALIDATION).read_text().replace("duration_s = 200.0", "duration_s = 200.0\nimpeller_rpm = 400.0")
    )
    out = tmp_path / "out"
    assert main(["predict", "--config", str(config), "--library", str(library), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "outside the library's domain" in err and "150-350 rpm" in err
    assert not out.exists()
    assert (
        main(["predict", "--config", str(config), "--library", str(library), "--out", str(out), "--extrapolate"]) == 0
    )
    assert "EXTRAPOLATED" in capsys.readouterr().out
    record = json.loads((out / "prediction.json").read_text())
    assert record["extrapolated"] is True and record["new_layout"] is False
    assert "blade layout no library run has" not in (out / "report.html").read_text()
    # another length: its stations are a layout no run of the library has, said on the page
    longer = tmp_path / "longer"
    config = "workflows/reference/unseen/225rpm-x1.125.toml"
    assert main(["predict", "--config", config, "--library", str(library), "--out", str(longer), "--extrapolate"]) == 0
    assert "a blade layout no library run has" in capsys.readouterr().out
    assert json.loads((longer / "prediction.json").read_text())["new_layout"] is True
    assert "A blade layout no library run has" in (longer / "report.html").read_text()


def test_library_fit_refuses_a_run_given_twice(tmp_path, capsys):
    args = ["library", "fit", "--results", str(SPEEDS[0]), str(SPEEDS[0]), str(SPEEDS[1]), "--out", str(tmp_path)]
    assert main(args) == 2
    assert "is the same run as" in capsys.readouterr().err


def test_library_fit_refuses_no_process_before_writing(tmp_path, capsys):
    out = tmp_path / "lib"
    assert main(["library", "fit", "--results", *map(str, SPEEDS), "--out", str(out), "--jobs", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--jobs 0" in err
    assert not out.exists()


def test_a_library_file_that_is_not_one_is_refused_naming_it(tmp_path, capsys):
    bad = tmp_path / "library.json"
    bad.write_text(json.dumps({"format": "something else"}))
    assert main(["predict", "--config", VALIDATION, "--library", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "not a library model" in err


@pytest.mark.parametrize(
    "edit",
    [
        lambda r: r["calibration"].update(direct=None),  # parses, and would change the outlet's RSD
        lambda r: r.update(calibration="x"),
        lambda r: r["runs"][0]["dem"].update(C_A=None),
        lambda r: r.update(interval_s=-1.0),
        lambda r: r.pop("sha256"),
    ],
)
def test_a_library_file_edited_after_its_fit_is_refused_naming_it(tmp_path, capsys, edit):
    from workflows.shipped import LIBRARY_MODEL

    record = json.loads(Path(LIBRARY_MODEL).read_text())
    edit(record)
    bad = tmp_path / "library.json"
    bad.write_text(json.dumps(record))
    assert main(["predict", "--config", VALIDATION, "--library", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(bad) in err and "does not match its sha256 digest" in err
    assert not (tmp_path / "o").exists()


def test_a_library_record_of_the_wrong_shape_is_refused_in_one_line(tmp_path):
    from workflows.prediction.library import LibraryModel
    from workflows.shipped import LIBRARY_MODEL

    record = json.loads(Path(LIBRARY_MODEL).read_text())
    record["calibration"] = "x"
    with pytest.raises(ConfigError, match="here.json: library model field missing or malformed"):
        LibraryModel.from_record(record, "here.json")


def test_a_truncated_results_file_is_refused_naming_it(tmp_path, capsys):
    cut = tmp_path / "cut.h5"
    cut.write_bytes(SPEEDS[0].read_bytes()[:20000])
    assert main(["library", "check", "--results", str(cut), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert f"{cut} is not a readable HDF5 file" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_library_check_judges_a_run_the_library_does_not_hold_and_refuses_one_it_does(library, tmp_path, capsys):
    seed2 = LIBRARY_DIR / "dem-4b9d0082c53c03af.h5"  # the baseline with another seed
    argv = ["library", "check", "--library", str(library), "--results", str(seed2), "--out", str(tmp_path)]
    assert main(argv) == 0
    record = json.loads((tmp_path / "check.json").read_text())
    rows = [r for r in record["rows"] if r["run"] == seed2.name]
    assert len(rows) == len(quantity_keys()) and all(r["interpolated"] for r in rows)
    page = (tmp_path / "check.md").read_text()
    row = next(line for line in page.splitlines() if line.startswith(f"| {seed2.name} |"))
    assert "nan" not in row and " | - | " in row  # no held-out likelihood for a run it does not hold
    capsys.readouterr()
    assert main(["library", "check", "--library", str(library), "--results", str(SPEEDS[0])]) == 2
    assert "is the library's run" in capsys.readouterr().err


def test_library_check_refuses_a_run_twice_an_output_over_a_run_and_names_a_run_outside(library, tmp_path, capsys):
    seed2 = LIBRARY_DIR / "dem-4b9d0082c53c03af.h5"  # the baseline with another seed: inside the small library
    copy = tmp_path / "copy.h5"
    shutil.copy(seed2, copy)
    base = ["library", "check", "--library", str(library), "--results"]
    assert main([*base, str(seed2), str(copy)]) == 2
    assert "is a copy of" in capsys.readouterr().err
    # a results file named like the check's record: the check would write over it
    named = tmp_path / "in" / "check.json"
    named.parent.mkdir()
    shutil.copy(seed2, named)
    before = named.read_bytes()
    assert main([*base, str(named), "--out", str(named.parent)]) == 2
    assert "is one of this command's inputs" in capsys.readouterr().err
    assert named.read_bytes() == before and not (named.parent / "check.md").exists()
    longer = LIBRARY_DIR / "dem-12a6e9730151e9f1.h5"  # the x1.5 blender: beyond the small library's lengths
    assert main([*base, str(seed2), str(longer)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{longer}: the point lies outside the library's domain" in err


def test_predict_refuses_to_write_over_its_configuration_before_any_work(tmp_path, capsys):
    config = tmp_path / "prediction.json"  # a TOML file a user named like the prediction's record
    shutil.copy(VALIDATION, config)
    before = config.read_bytes()
    assert main(["predict", "--config", str(config), "--out", str(tmp_path), "--no-figures"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is one of this command's inputs" in err
    assert config.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["prediction.json"]


def test_an_empty_output_directory_is_refused(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["predict", "--out", "", "--no-figures"]) == 2
    assert "--out is empty" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_a_corrupt_cached_fit_is_refitted_and_replaced_not_trusted(library, tmp_path):
    import shutil

    out = tmp_path / "library"
    shutil.copytree(library, out)
    victim = sorted((out / "fits").glob("law-*.json"))[0]
    victim.write_text('{"n_phases": 3, "coefficients": {"x_pos/0": [1, 2]}')  # cut short
    args = ["library", "fit", "--results", *map(str, SPEEDS), "--out", str(out)]
    assert main([*args, "--iterations", "3", "--left-out-iterations", "2"]) == 0
    phases = load_model(library).law.n_phases
    assert json.loads(victim.read_text())["n_phases"] == phases  # rewritten, whole
    assert load_model(out).law.n_phases == phases


def test_another_correction_refits_no_law_and_is_recorded(library, tmp_path):
    out = tmp_path / "again"
    shutil.copytree(library / "fits", out / "fits")
    before = sorted(p.name for p in (out / "fits").iterdir())
    args = ["library", "fit", "--results", *map(str, SPEEDS), "--out", str(out), "--correction", "none"]
    assert main([*args, "--iterations", "3", "--left-out-iterations", "2"]) == 0
    assert sorted(p.name for p in (out / "fits").iterdir()) == before  # every law read from the cache
    model = load_model(out)
    assert model.calibration.covariates == () and model.settings["correction"] == []
    assert main([*args[:-1], "speed,volume"]) == 2  # refused in one line, before any fit


def test_library_fit_refuses_runs_of_another_physics(monkeypatch):
    """Runs whose friction differs are not one library: its law does not vary friction."""
    from dataclasses import replace

    import workflows.prediction.library as lib
    from coupling.errors import ConfigError

    real = lib.library_run

    def with_other_friction(path, names, *args, **kwargs):
        run = real(path, names, *args, **kwargs)
        if path == SPEEDS[1]:
            run = replace(run, physics={**run.physics, "contact.friction_particle_particle": 0.3})
        return run

    monkeypatch.setattr(lib, "library_run", with_other_friction)
    with pytest.raises(
        ConfigError, match=r"contact\.friction_particle_particle = 0\.3 where .* has 0\.5: .*one physics"
    ):
        lib.load_runs(SPEEDS, lib.FitSettings())
    monkeypatch.setattr(lib, "library_run", real)
    assert len(lib.load_runs(SPEEDS, lib.FitSettings())) == 3
