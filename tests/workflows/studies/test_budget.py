"""``pbmdem study budget`` end to end on the shipped reduced run, at two budgets instead
of seven (about 25 s against 220 s): a budget of the whole run is the whole run's PBM,
and 90 s of DEM (35 % of the run) already give the measured-rate and phase PBMs every
quantity but the slice hold-ups within the DEM's interval. Bad input is one line."""

import json

import pytest

from workflows.cli.main import main
from workflows.shipped import REDUCED_RUN


def test_ninety_seconds_of_dem_hold_all_but_the_slices(tmp_path, capsys):
    assert main(["study", "budget", "--reference", str(REDUCED_RUN), "--t", "90", "260", "--out", str(tmp_path)]) == 0
    study = json.loads((tmp_path / "dem_budget.json").read_text())
    assert study["t_end_s"] == pytest.approx(260.0)
    short, whole = study["budgets"]
    assert short["t_s"] == 90.0 and short["fraction"] == pytest.approx(90 / 260)
    assert short["error"] is None and whole["error"] is None
    assert set(whole["modes"]) == {"velocity", "measured", "phases"}
    for mode, judged in whole["modes"].items():
        # the whole run's budget is the reference itself
        assert judged["all_inside"] and judged["worst_deviation"] == pytest.approx(0.0, abs=1e-9), mode
        assert study["smallest_T"][mode]["t_s"] <= 260.0, mode
    for mode in ("measured", "phases"):
        judged = short["modes"][mode]
        assert judged["all_inside_without_slices"], mode
        assert study["smallest_T_without_slices"][mode]["t_s"] == 90.0, mode
        rows = {row["key"]: row for row in judged["rows"]}
        mean = rows["mean_residence_time_s"]
        assert abs(mean["pbm_T"] - mean["pbm_whole"]) <= mean["half_width"]
    assert (tmp_path / "dem_budget.png").stat().st_size > 5_000
    assert "without the slice hold-ups, measured rates: 90 s (35% of the run)" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("extra", "message"),
    [(["--reference", "missing.h5"], "missing.h5"), (["--t", "60", "0"], "--t 0: expected DEM budgets in seconds > 0")],
)
def test_bad_input_is_one_line(tmp_path, capsys, extra, message):
    argv = ["study", "budget", "--reference", str(REDUCED_RUN), *extra, "--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "out").exists()
