"""The agreement table on the synthetic DEM flow of ``test_post``: every quantity has its
DEM interval, both PBM rate modes run on the DEM's own table, and every verdict is the
interval test of the numbers in its row."""

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest

from coupling.summary import ProcessSummary
from dem.post import postprocess
from pbm.config import PbmConfig
from tests.known_dumps import STEADY, config, write_synthetic
from workflows.analysis.agreement import MODES, agreement_rows, pbm_steady, run_modes


@pytest.fixture(scope="module")
def synthetic_80s(tmp_path_factory):
    cfg = config()
    directory = tmp_path_factory.mktemp("synthetic80")
    write_synthetic(directory, cfg, end_s=80.0)
    results = postprocess(str(directory / "dump.*.txt"), cfg, STEADY)
    pbm = PbmConfig(feed_rate_a_per_s=2.0, feed_rate_b_per_s=2.0)
    return results, run_modes(results.table, pbm, STEADY, results.summary)


def test_both_modes_and_every_row(synthetic_80s):
    results, modes = synthetic_80s
    assert set(modes) == set(MODES)
    assert all(m.pooled is not None for m in modes.values())
    rows = agreement_rows(results.summary, results.particles, modes)
    keys = [r.key for r in rows]
    for key in (
        "mean_residence_time_s",
        "rtd_variance_s2",
        "holdup",
        "outflow_per_s",
        "C_A",
        "rsd_outlet",
        "lacey_outlet",
        "rtd_overlap",
        "little_mean_residence_time_s",
    ):
        assert key in keys
    assert [k for k in keys if k.startswith("holdup_slice_")] == [f"holdup_slice_{i}" for i in range(1, 5)]
    for row in rows:
        for mode in MODES:
            value = row.value(mode)
            assert math.isfinite(value), (row.key, mode)
            if row.key == "rtd_overlap":
                assert row.inside(mode) == (value >= row.pbm[mode].noise_low)
            else:
                assert row.inside(mode) == (row.dem_ci_low <= value <= row.dem_ci_high)
            # the flat record summary.json holds carries the same numbers
            assert row.record()[f"pbm_{mode}"] == value and row.record()[f"inside_{mode}"] == row.inside(mode)


def test_the_verdict_follows_the_interval(synthetic_80s):
    results, modes = synthetic_80s
    pbm_outflow = agreement_rows(results.summary, results.particles, modes)
    value = next(r for r in pbm_outflow if r.key == "outflow_per_s").value("measured")
    for low, high, expected in ((value - 1, value + 1, True), (value + 1, value + 2, False)):
        steady = {**results.summary.steady, "outflow_per_s": {"value": value, "low": low, "high": high}}
        summary = dataclasses.replace(results.summary, steady=steady)
        row = next(r for r in agreement_rows(summary, results.particles, modes) if r.key == "outflow_per_s")
        assert row.inside("measured") is expected


def test_the_pbm_pooled_rtd_uses_the_dem_window(synthetic_80s):
    results, modes = synthetic_80s
    spec = results.summary.pooled_rtd
    for m in modes.values():
        assert m.pooled.bin_edges[-1] == pytest.approx(spec.horizon_s)
        assert np.all(m.pooled.entry_times_s > spec.entry_window_s[0])
        assert np.all(m.pooled.entry_times_s <= spec.entry_window_s[1])


def _mixed_pbm(ny: int = 2):
    """A PBM output whose outlet compartments all hold A and B half and half, steady from
    t = 0: what pbm_steady reads of a PbmResult."""
    times = np.arange(5.0)
    counts = np.full((times.size, 2, 3, ny), 10.0)
    flux = np.ones(times.size)
    return SimpleNamespace(
        summary=ProcessSummary(steady_state_time_s=0.0), times=times, counts=counts, outflow_A=flux, outflow_B=flux
    )


def test_the_outlet_rsd_is_sampled_at_the_dems_counts_dump_by_dump():
    """Known answers for a perfectly mixed outlet (p = 1/2 in both compartments). At one
    particle in each at every dump the RSD of the two fractions is 0 (both alike, p 1/4),
    sqrt(2) (one A, one B, p 1/2) or undefined (no A, p 1/4): its mean over the defined
    samples is sqrt(2) * (1/2) / (3/4). Dumps with one occupied compartment have no RSD
    and do not count, as in the DEM's mean; at the mean counts (0.5 and 1.5) the first
    compartment is empty and the outlet has no RSD at all."""
    pbm = _mixed_pbm()
    ones = np.ones((400, 2))
    expected = math.sqrt(2) * 0.5 / 0.75
    # (dumps, A and B, compartments): only the totals count, however the DEM's were split
    split = np.stack([ones, np.zeros_like(ones)], axis=1)
    assert pbm_steady(pbm, {}, split)["rsd_outlet"] == pytest.approx(expected, rel=0.03)
    mixed = np.vstack([ones, np.tile([[0.0, 2.0]], (400, 1))])
    split = np.stack([mixed / 2, mixed / 2], axis=1)
    assert pbm_steady(pbm, {}, split)["rsd_outlet"] == pytest.approx(expected, rel=0.03)
    at_means = pbm_steady(pbm, {"outlet_totals": mixed.mean(axis=0).tolist()})
    assert math.isnan(at_means["rsd_outlet"])
