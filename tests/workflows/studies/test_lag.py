"""The lag study on the shipped run's compartment sequences (no dumps shipped): each fit
stopped after a few iterations keeps it fast, and the study's finding stands at that
cost. Rates fitted ten dumps apart carry more of the DEM's dispersion than rates one dump
apart, yet less than the DEM has. A missing results file is one line."""

import json

import pytest

from coupling.cache import load_entry
from dem.summary import DemSummary
from workflows.cli.main import main
from workflows.shipped import REDUCED_RUN


def test_longer_lags_carry_more_of_the_dems_dispersion(tmp_path, capsys):
    out = tmp_path / "lag.json"
    argv = ["study", "lag", "--results", str(REDUCED_RUN), "--lags", "1,10", "--max-iterations", "10"]
    assert main([*argv, "--out-file", str(out)]) == 0
    record = json.loads(out.read_text())
    dem = DemSummary.from_record(load_entry(REDUCED_RUN).summary).pooled_rtd
    assert record["dem_mean_s"]["value"] == pytest.approx(dem.mean_residence_time_s.value)
    dem_variance = record["dem_variance_s2"]["value"]
    one, ten = record["lags"]["1"], record["lags"]["10"]
    # the shipped run is dumped every 0.1 s
    assert one["interval_s"] == pytest.approx(0.1, rel=1e-3) and ten["interval_s"] == pytest.approx(1.0, rel=1e-3)
    for lag in (one, ten):
        # a chain fitted to the run's own moves keeps its mean residence time within 10 %
        assert lag["mean_s"] == pytest.approx(record["dem_mean_s"]["value"], rel=0.1)
        assert lag["unconverged_windows"] > 0  # 10 iterations do stop the fits early
    # measured on the shipped run: 127 s^2 at lag 1, 136 s^2 at lag 10, the DEM 165 s^2
    assert one["variance_s2"] < ten["variance_s2"] < record["dem_variance_s2"]["low"] < dem_variance
    assert "lag  10 (1.0 s)" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--results", "missing.h5"], "missing.h5"),
        (["--lags", "0,2"], "--lags '0,2'"),
        (["--max-iterations", "0"], "--max-iterations 0"),
    ],
)
def test_bad_input_is_one_line(tmp_path, capsys, extra, message):
    argv = ["study", "lag", "--results", str(REDUCED_RUN), *extra, "--out-file", str(tmp_path / "lag.json")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "lag.json").exists()
