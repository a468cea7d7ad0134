"""``pbmdem bench rates`` end to end on a small known chain: the maximum-likelihood fit
recovers the chain's rates, and the naive one-jump estimator is the worse the more jumps
an interval hides."""

import json

from workflows.cli.main import main


def test_small_benchmark_ranks_the_estimators(tmp_path):
    out = tmp_path / "rates.json"
    argv = ["--particles", "200000", "--steps", "10", "--min-observations", "500"]
    argv += ["--windows", "2", "--observations", "10000", "--out-file", str(out)]
    assert main(["bench", "rates", *argv]) == 0
    record = json.loads(out.read_text())
    rows = record["accuracy"]
    assert [row["rate_x_interval"] for row in rows] == [0.1, 0.3, 0.5, 1.0]
    for row in rows:
        # ~2e6 transitions over 100 compartments: every one is reported, the fit converges,
        # and its typical error is a few per cent (measured 1-2 %)
        assert row["compartments_reported"] == 100 and row["mle_converged"]
        assert row["mle"]["median"] < 0.05 and row["mle"]["max"] < 0.3
    # one jump per interval is assumed: its bias grows with rate x interval (18 % to 80 %)
    naive = [row["naive"]["median"] for row in rows]
    assert naive == sorted(naive) and naive[-1] > 0.5
    assert all(row["naive"]["median"] > 3 * row["mle"]["median"] for row in rows)
    assert [(t["nx"], t["ny"], t["states"], t["windows"]) for t in record["timing"]] == [
        (10, 10, 101, 2),
        (20, 10, 201, 2),
    ]
    assert all(t["per_window_s"] > 0 and 5e3 < t["observations_per_window"] < 2e4 for t in record["timing"])
