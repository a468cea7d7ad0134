"""The feeders study: on synthetic tracers of known distributions the per-feeder moments
are the sample's and the A - B interval finds a real difference and none where there is
none; the pooling over runs is the inverse-variance mean; on the shipped reduced run the
phase model's two feeders, each fed alone, add up to its pooled RTD of both."""

import json

import numpy as np
import pytest

from coupling.intervals import Interval
from pbm.rtd import pooled_rtd
from workflows.cli.main import main
from workflows.pipeline.results import load_results, pbm_config_for
from workflows.shipped import REDUCED_RUN
from workflows.studies.feeders import FeederRtds, dem_feeder_intervals, pooled_difference


def tracers(scale_a: float, scale_b: float, n: int = 6000, seed: int = 3):
    """Feeders 1 and 2 alternating, entering uniformly over (0, 100] s, exponential
    residence times of the given means; every tracer leaves within 200 s but a few."""
    rng = np.random.default_rng(seed)
    component = np.tile([1, 2], n // 2)
    entry = rng.uniform(0.0, 100.0, n)
    tau = rng.exponential(np.where(component == 1, scale_a, scale_b))
    return component, entry, entry + tau


def test_per_feeder_moments_are_the_sample_moments_and_the_difference_is_found_where_it_is():
    component, entry, exit_ = tracers(10.0, 10.0)
    stats, counts = dem_feeder_intervals(component, entry, exit_, (0.0, 100.0), 200.0, 5.0)
    tau = exit_ - entry
    for name, code in (("A", 1), ("B", 2)):
        mine = tau[(component == code) & (tau <= 200.0)]
        assert counts[name] == mine.size
        assert stats[f"mean_{name}"].estimate == pytest.approx(mine.mean(), rel=1e-12)
        assert stats[f"variance_{name}"].estimate == pytest.approx(mine.var(), rel=1e-12)
    same = stats["variance_difference"]
    assert same.low < 0.0 < same.high

    component, entry, exit_ = tracers(13.0, 10.0)  # variance 169 against 100
    differ, _ = dem_feeder_intervals(component, entry, exit_, (0.0, 100.0), 200.0, 5.0)
    assert differ["variance_difference"].low > 0.0
    assert differ["mean_difference"].estimate == pytest.approx(3.0, abs=0.8)


def _row(estimate: float, half_width: float) -> FeederRtds:
    d = Interval(estimate, estimate - half_width, estimate + half_width)
    return FeederRtds("f", "run", 1.0, {"A": 1, "B": 1}, {"variance_difference": d}, {}, {})


def test_pooling_over_runs_is_the_inverse_variance_mean():
    rows = [_row(-10.0, 1.959964), _row(20.0, 2 * 1.959964)]  # standard errors 1 and 2
    pooled = pooled_difference(rows)
    assert pooled.mean_s2 == pytest.approx((-10.0 + 20.0 / 4) / 1.25)
    assert pooled.high_s2 - pooled.mean_s2 == pytest.approx(1.959964 / np.sqrt(1.25))
    assert (pooled.positive, pooled.excluding_zero) == (1, 2)


def test_the_phase_models_feeders_alone_add_up_to_its_pooled_rtd(tmp_path, capsys):
    assert main(["study", "feeders", "--results", str(REDUCED_RUN), "--out", str(tmp_path)]) == 0
    assert "| reduced |" in capsys.readouterr().out
    (run,) = json.loads((tmp_path / "feeders.json").read_text())["runs"]
    results, config = load_results(REDUCED_RUN)
    spec = results.summary.pooled_rtd
    pbm_config = pbm_config_for(config, results.table, None).model_copy(update={"rates": "phases"})
    both = pooled_rtd(results.table, pbm_config, entry_window=spec.entry_window_s, horizon_s=spec.horizon_s)
    # linear in the tracer: both feeders' RTD is the feed-weighted mixture of each alone
    rate = {"A": pbm_config.feed_rate_a_per_s, "B": pbm_config.feed_rate_b_per_s}
    share = {f: r / sum(rate.values()) for f, r in rate.items()}
    mean = sum(share[f] * run["pbm_mean_s"][f] for f in rate)
    second = sum(share[f] * (run["pbm_variance_s2"][f] + run["pbm_mean_s"][f] ** 2) for f in rate)
    # each alone is its own: the feeders enter in their own phases (A's mean is 0.2 s longer)
    assert abs(run["pbm_mean_s"]["A"] - run["pbm_mean_s"]["B"]) > 0.05
    assert both.mean_s == pytest.approx(mean, rel=1e-3)
    assert both.variance_s2 == pytest.approx(second - mean**2, rel=1e-3)
    assert run["dem"]["variance_A"]["low"] < run["dem"]["variance_A"]["value"] < run["dem"]["variance_A"]["high"]
    assert (tmp_path / "feeders.png").stat().st_size > 5_000


def test_a_file_without_a_phase_model_is_refused_by_name(tmp_path, capsys):
    import dataclasses

    from coupling.cache import load_entry, save_entry

    entry = load_entry(REDUCED_RUN)
    plain = tmp_path / "plain.h5"
    save_entry(plain, dataclasses.replace(entry, table=entry.table.replace(phases=None)))
    assert main(["study", "feeders", "--results", str(plain), "--out", str(tmp_path)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(plain) in err[0] and "no phase model" in err[0]
