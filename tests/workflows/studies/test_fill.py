"""``pbmdem study fill`` on the shipped feed library: leave one out in the measured rates."""

import json

from workflows.cli.main import main
from workflows.shipped import VALIDATION_DIR


def test_study_fill_predicts_each_feed_from_the_others(tmp_path, capsys):
    out = tmp_path / "fill.json"
    # a run of the same blender given as unseen is predicted from the whole library
    unseen = VALIDATION_DIR / "dem-26a744879a705d14.h5"  # feed x1.5
    args = ["study", "fill", "--modes", "measured", "--runs-root", str(tmp_path / "runs"), "--out-file", str(out)]
    assert main([*args, "--unseen", str(unseen)]) == 0
    record = json.loads(out.read_text())
    assert out.with_suffix(".png").stat().st_size > 10_000
    assert set(record["runs"]) == {"baseline", "feed_x0.5", "feed_x1.5", "feed_x2"}
    held = {
        (p["run"], p["source"].split(" (")[0]): p
        for p in record["predictions"]
        if p["quantity"] == "holdup" and p["mode"] == "measured"
    }
    assert any(p["run"].startswith(unseen.name) for p in record["predictions"])
    for run in ("feed_x0.5", "feed_x1.5", "feed_x2"):
        library, linear = held[run, "library law"], held[run, "linear"]
        # the law of the other feeds' steady points holds the hold-up to 2 %; the linear PBM misses by 35-70 %
        assert abs(library["pbm"] / library["dem"] - 1) < 0.02, library
        assert abs(linear["pbm"] / linear["dem"] - 1) > 0.3, linear


def test_study_fill_refuses_an_unseen_run_of_another_blender(tmp_path, capsys):
    longer = VALIDATION_DIR / "dem-110115e4ee2e888e.h5"  # the campaign's length x1.25
    code = main(
        ["study", "fill", "--modes", "measured", "--unseen", str(longer), "--out-file", str(tmp_path / "f.json")]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "differs beyond the feed" in err
