"""``pbmdem bench frequency`` end to end on the synthetic table: the blender passes slow
feeder changes and damps fast ones, the time-domain checks agree with the transfer
function, and so does the noise ensemble with the frequency domain's prediction."""

import json

import numpy as np
import pytest

from workflows.cli.main import main


def test_benchmark_agrees_with_its_checks(tmp_path):
    out = tmp_path / "frequency.json"
    assert main(["bench", "frequency", "--points", "7", "--timing-points", "100", "--out-file", str(out)]) == 0
    record = json.loads(out.read_text())
    sweep = record["sweep"]
    for feeder in ("A", "B"):
        gain = np.asarray(sweep[f"abs_H_{feeder}"])
        # a mass balance passes a slow change whole and damps a fast one, monotonically
        assert gain[0] == pytest.approx(1.0, abs=0.01) and gain[-1] < 1e-4
        assert np.all(np.diff(gain) < 0)
        assert max(record["time_domain_check"][feeder]["relative_error"]) < 1e-8
    # white noise is damped most, slow noise least; no noise is ever amplified
    vrr = [row["vrr_A"] for row in record["noise_vrr"]]
    assert vrr == sorted(vrr, reverse=True) and vrr[-1] > 1
    mrt = record["scenario"]["mean_residence_time_s"]["A"]
    assert record["rtd_route"]["rtd_mean_s"] == pytest.approx(mrt, rel=0.05)
    for row in record["ensemble_check"]:  # 10 000 members: within a few per cent (measured 0.4 %)
        assert abs(row["relative_difference"]) < 0.03
