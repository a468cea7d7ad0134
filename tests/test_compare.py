"""The full comparison: feed mapping, reference seeding, and the smoke preset end to end with
the real LIGGGHTS (DEM -> tables -> PBM -> report)."""

import json
import shutil

import numpy as np
import pandas as pd
import pytest

from coupling.cache import cache_path, load_dem_results
from workflows.cli import main
from workflows.compare import feed_weights_from_zones, pbm_config_for, seed_cache_from_reference
from workflows.config import load_preset


def test_feed_weights_are_the_overlap_in_y():
    edges = np.linspace(-0.05, 0.05, 11)
    w = feed_weights_from_zones(edges, 0.005, 0.035)
    # [5, 10] mm, [10, 20], [20, 30], [30, 35]: overlaps 5, 10, 10, 5 of 30 mm.
    np.testing.assert_allclose(w, [0] * 5 + [1 / 6, 1 / 3, 1 / 3, 1 / 6, 0], atol=1e-12)
    with pytest.raises(ValueError, match="outside the compartments"):
        feed_weights_from_zones(edges, 0.06, 0.07)


def test_pbm_config_takes_the_dem_feed(rng):
    from coupling.tables import make_table

    config = load_preset("smoke")
    table = make_table([0.0], np.linspace(0, 0.33, 11), np.linspace(-0.05, 0.05, 11), 0.01, 0, 0.1, 0.1)
    pbm = pbm_config_for(config, table, rtd_pulse_s=12.0)
    assert pbm.feed_rate_a_per_s + pbm.feed_rate_b_per_s == pytest.approx(config.dem.operation.feed_rate_total_per_s)
    assert pbm.rtd_pulse_s == 12.0
    assert sum(pbm.feed_weights_a[5:]) == pytest.approx(1) and sum(pbm.feed_weights_b[:5]) == pytest.approx(1)


@pytest.mark.liggghts
@pytest.mark.slow
def test_smoke_end_to_end(smoke_runs_root, tmp_path, capsys):
    results_dir = tmp_path / "results"
    code = main(["compare", "--preset", "smoke", "--runs-dir", str(smoke_runs_root), "--results-dir", str(results_dir),
                 "--noise-members", "20", "--no-progress"])
    assert code == 0, capsys.readouterr().err
    report = next(results_dir.glob("smoke-*/report.html"))
    out = report.parent
    summary = json.loads((out / "summary.json").read_text())
    dem, metrics = summary["dem_summary"], summary["metrics"]

    # DEM substance: particles discharged, accounting closed, tables non-trivial.
    assert dem["discharged"] > 50
    assert dem["lost"] == 0 and dem["accounting_mismatch"] == 0
    table, _, _ = load_dem_results(next(smoke_runs_root.glob("cache/dem-*.h5")))
    assert table.valid.mean() > 0.5
    assert np.all(table.vx_pos[table.valid].mean() > 0) and table.vy_pos.max() > 0.01

    # PBM: conservation (fed = held + discharged) and C_A near 0.5 with equal feeds.
    ts = pd.read_csv(out / "pbm_timeseries.csv")
    assert summary["provenance"]["pbm_conservation_max_rel_error"] < 1e-9
    assert abs(metrics["steady_C_A_pbm"] - 0.5) < 0.05
    assert abs(metrics["steady_C_A_dem"] - 0.5) < 0.15
    assert ts["holdup_A"].iloc[-1] > 0

    # Report: page, every figure non-empty, provenance present.
    page = report.read_text()
    for name in ("rtd.png", "rsd_axial.png", "rsd_time.png", "c_a.png", "outflow.png", "holdup.png",
                 "study_length.png", "study_diameter.png", "study_noise.png"):
        assert (out / name).stat().st_size > 10_000, name
        assert name in page
    assert "3.8.0" in page and summary["provenance"]["dem_source"] in ("LIGGGHTS ran now", "cache")
    assert (out / "paraview" / "compartments.pvd").is_file() and (out / "paraview" / "particles.pvd").is_file()


def test_reference_seeding_copies_only_valid_files(tmp_path):
    shipped = sorted((pytest.importorskip("workflows.compare").REFERENCE_DIR).glob("dem-*.h5"))
    if not shipped:
        pytest.fail("no shipped reference data under workflows/reference/")
    key = shipped[0].name.removeprefix("dem-").removesuffix(".h5")
    assert seed_cache_from_reference(key, tmp_path / "cache")
    assert load_dem_results(cache_path(tmp_path / "cache", key), key)[2]["key"] == key
    assert not seed_cache_from_reference(key, tmp_path / "cache")  # already valid: nothing to do
    assert not seed_cache_from_reference("0" * 16, tmp_path / "other")
    # a corrupt cache file is replaced by the shipped one
    cache_path(tmp_path / "cache", key).write_text("garbage")
    assert seed_cache_from_reference(key, tmp_path / "cache")
    shutil.rmtree(tmp_path / "cache")
