"""``pbmdem study vrr`` end to end on the shipped reduced run (about 35 s: no option
limits it further, the seeded bootstrap and the 2000-member ensemble are the study): the
blender filters feeder noise as a low-pass filter on both sides, the velocity-rate PBM's
noise VRR lies in the DEM's interval for both feeders and every noise colour, and each
mode's transfer function agrees with its time-domain ensemble. A missing file is one
line."""

import json

import pytest

from workflows.cli.main import main
from workflows.shipped import REDUCED_RUN


def test_the_pbm_filters_feeder_noise_as_the_shipped_run_does(tmp_path, capsys):
    assert main(["study", "vrr", "--reference", str(REDUCED_RUN), "--out", str(tmp_path)]) == 0
    record = json.loads((tmp_path / "vrr.json").read_text())
    assert set(record["pbm"]) == {"velocity", "measured", "phases"}
    for feeder in ("A", "B"):
        dem = record["dem"][feeder]
        gain = [h for h, ok in zip(dem["abs_H"]["value"], dem["resolved"]) if ok]
        assert len(gain) > 5 and gain == sorted(gain, reverse=True) and gain[0] < 1  # a low-pass filter
        noise = [n["value"] for n in dem["noise"]]
        assert noise == sorted(noise, reverse=True) and noise[0] > 1  # white noise is filtered most
        # measured on the shipped run: the velocity mode's noise VRR inside the DEM's
        # interval for both feeders at tau = 0, 1, 5 and 20 s
        assert all(n["inside"] for n in record["pbm"]["velocity"]["feeders"][feeder]["noise"])
    for mode, pbm in record["pbm"].items():
        # the SD of a 2000-member SD estimate is about 1.6 %: 5 % is three of them
        (check,) = pbm["ensemble_check"]
        assert check["sd_time_domain"] == pytest.approx(check["sd_frequency_domain"], rel=0.05), mode
        assert 0 < pbm["n_inside"] <= pbm["n_judged"], mode
    assert (tmp_path / "vrr.png").stat().st_size > 5_000
    assert "velocity: VRR(f) inside the DEM interval" in capsys.readouterr().out
