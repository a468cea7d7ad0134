"""The full comparison: feed mapping, where the DEM stage finds results (cache, shipped
reference, no solver installed), and the smoke preset end to end with the real LIGGGHTS
(DEM -> tables -> PBM -> report)."""

import json
import tomllib

import numpy as np
import pandas as pd
import pytest

from coupling.cache import cache_path, load_entry, save_entry
from coupling.compartments import feed_zone_weights, inlet_weights
from coupling.errors import ConfigError
from workflows.cli.main import main
from workflows.config import config_from_dict, load_preset
from workflows.pipeline.results import pbm_config_for
from workflows.pipeline.stages import dem_stage, post_hash, results_key
from workflows.shipped import UNSEEN_DIR


def test_feed_weights_are_the_overlap_in_y():
    edges = np.linspace(-0.05, 0.05, 11)
    w = inlet_weights(edges, 0.005, 0.035)
    # [5, 10] mm, [10, 20], [20, 30], [30, 35]: overlaps 5, 10, 10, 5 of 30 mm.
    np.testing.assert_allclose(w, [0] * 5 + [1 / 6, 1 / 3, 1 / 3, 1 / 6, 0], atol=1e-12)
    with pytest.raises(ConfigError, match="outside the compartments"):
        inlet_weights(edges, 0.06, 0.07)


def test_a_feed_zone_wider_than_the_first_slice_feeds_the_next_one():
    from coupling.tables import make_table
    from pbm.model import feed_distribution

    y = np.linspace(-0.05, 0.05, 11)
    # inside the first of 10 slices of 33 mm: the first slice's NY weights, as in y alone
    assert feed_zone_weights(np.linspace(0, 0.33, 11), y, (0.006, 0.030), (0.005, 0.035)) == inlet_weights(
        y, 0.005, 0.035
    )
    # 6-30 mm over slices of 16.5 mm: 10.5 of 24 mm in the first, 13.5 in the second
    x = np.linspace(0, 0.33, 21)
    w = np.asarray(feed_zone_weights(x, y, (0.006, 0.030), (0.005, 0.035))).reshape(20, 10)
    np.testing.assert_allclose(w.sum(axis=1)[:3], [10.5 / 24, 13.5 / 24, 0], atol=1e-12)
    np.testing.assert_allclose(w[1] / w[1].sum(), inlet_weights(y, 0.005, 0.035), atol=1e-12)
    # the PBM feeds those compartments; a list of neither NY nor NX * NY entries is refused
    table = make_table([0.0], x, y, 0.01, 0, 0.1, 0.1)
    feed = feed_distribution(table, w.ravel().tolist(), None)
    np.testing.assert_allclose(feed[:, 0], w.ravel(), atol=1e-12)
    with pytest.raises(ConfigError, match="needs NY = 10 .* or NX \\* NY = 200"):
        feed_distribution(table, [1.0] * 20, None)
    with pytest.raises(ConfigError, match="feed zone x in .* lies outside the compartments"):
        feed_zone_weights(x, y, (0.4, 0.5), (0.005, 0.035))


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
    code = main(
        [
            "compare",
            "--preset",
            "smoke",
            "--runs-dir",
            str(smoke_runs_root),
            "--out",
            str(results_dir),
            "--noise-members",
            "20",
            "--no-progress",
        ]
    )
    assert code == 0, capsys.readouterr().err
    report = results_dir / "report.html"
    out = report.parent
    summary = json.loads((out / "summary.json").read_text())
    dem, metrics = summary["dem_summary"], summary["metrics"]

    # DEM substance: particles discharged, accounting closed, tables non-trivial.
    assert dem["discharged"] > 50
    assert dem["lost"] == 0 and dem["accounting_mismatch"] == 0
    table = load_entry(next(smoke_runs_root.glob("cache/dem-*.h5"))).table
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
    for name in (
        "rtd.png",
        "rsd_axial.png",
        "rsd_time.png",
        "c_a.png",
        "outflow.png",
        "holdup.png",
        "study_length.png",
        "study_diameter.png",
        "study_noise.png",
    ):
        assert (out / name).stat().st_size > 10_000, name
        assert name in page
    assert "3.8.0" in page and summary["provenance"]["dem_source"] in ("LIGGGHTS ran now", "cache")
    # written through meshio, with or without the `render` extra
    assert (out / "paraview" / "compartments.pvd").is_file() and (out / "paraview" / "particles.pvd").is_file()

    # Agreement: both rate modes judged against the DEM's intervals, by the numbers; the grid
    # sensitivity from the same run binned at twice the NX (no new solver run).
    rows = {row["key"]: row for row in summary["agreement"]}
    assert {"holdup", "outflow_per_s", "C_A"} <= set(rows)
    for row in rows.values():
        for mode in ("velocity", "measured"):
            low, high, value = row["dem_ci_low"], row["dem_ci_high"], row[f"pbm_{mode}"]
            if row["key"] != "rtd_overlap" and None not in (low, high, value):
                assert row[f"inside_{mode}"] == (low <= value <= high)
    assert summary["pbm_modes"].keys() == {"velocity", "measured"}
    assert summary["nx_sensitivity"]["nx"] == [10, 20]
    assert "Agreement" in page


@pytest.fixture(scope="module")
def some_results(tmp_path_factory):
    from dem.post import postprocess
    from tests.known_dumps import STEADY, config, write_synthetic

    directory = tmp_path_factory.mktemp("dumps")
    write_synthetic(directory, config())
    return postprocess(str(directory / "dump.*.txt"), config(), STEADY)


def _entry_for(config, key, results):
    """A cache entry claiming to hold ``config``'s DEM results under ``key``."""
    from dem.run import prepare_run

    inputs = prepare_run(config.dem)
    provenance = {"key": key, "deck_hash": inputs.deck_hash, "post_hash": post_hash(config), "created": "test"}
    return results.to_cache_entry(provenance), inputs


def test_dem_stage_takes_the_reference_in_place_and_rebuilds_nothing_corrupt(tmp_path, some_results):
    config = load_preset("smoke")
    reference = tmp_path / "reference"
    _, inputs = _entry_for(config, "x", some_results)
    if inputs.key is None:
        pytest.fail("LIGGGHTS is not installed (make setup installs it)")
    key = results_key(inputs.key, post_hash(config))
    save_entry(cache_path(reference, key), _entry_for(config, key, some_results)[0])
    dem = dem_stage(config, runs_root=tmp_path / "runs", reference_dir=reference)
    assert dem.source == "reference" and dem.key == key and dem.cache_file.parent == reference
    # a corrupt cache file of the same key is not trusted: the reference is used instead
    cache_path(tmp_path / "runs" / "cache", key).parent.mkdir(parents=True, exist_ok=True)
    cache_path(tmp_path / "runs" / "cache", key).write_text("garbage")
    messages = []
    dem = dem_stage(config, runs_root=tmp_path / "runs", reference_dir=reference, log=messages.append)
    assert dem.source == "reference" and any("not usable" in m for m in messages)
    # changing how the dumps are binned changes the key: the cached table is not served
    finer = config_from_dict({**config.to_dict(), "dem": {**config.to_dict()["dem"], "tables": {"nx": 20}}})
    assert post_hash(finer) != post_hash(config)


def test_without_liggghts_results_of_the_same_deck_are_found(tmp_path, some_results):
    data = load_preset("smoke").to_dict()
    data["dem"]["run"]["liggghts"] = "no-such-liggghts-executable"
    config = config_from_dict(data)
    entry, inputs = _entry_for(config, "made-elsewhere", some_results)
    assert inputs.key is None
    save_entry(cache_path(tmp_path / "reference", "made-elsewhere"), entry)
    dem = dem_stage(config, runs_root=tmp_path / "runs", reference_dir=tmp_path / "reference")
    assert dem.source == "reference" and dem.key == "made-elsewhere"


def test_shipped_reference_covers_the_reduced_preset(tmp_path):
    """A fresh clone's `make full-comparison` must not need LIGGGHTS: the shipped data match
    the current deck and post-processing of the reduced preset. (Run as if no solver were
    installed, so that a mismatch fails here instead of starting a 40-minute run.)"""
    data = load_preset("reduced").to_dict()
    data["dem"]["run"]["liggghts"] = "no-such-liggghts-executable"
    dem = dem_stage(config_from_dict(data), runs_root=tmp_path / "runs")
    assert dem.source == "reference", dem.cache_file


def test_shipped_reference_covers_the_grid_sensitivity(tmp_path):
    """The comparison's NX sensitivity bins the same reduced run at twice the NX: shipped
    too, so a fresh clone never needs the dumps; found without starting any solver."""
    data = load_preset("reduced").to_dict()
    data["dem"]["run"]["liggghts"] = "no-such-liggghts-executable"
    data["dem"]["tables"]["nx"] = 2 * data["dem"]["tables"]["nx"]
    dem = dem_stage(config_from_dict(data), runs_root=tmp_path / "runs", solver=False)
    assert dem.source == "reference" and dem.table.nx == 20 and dem.table.has_rates


@pytest.mark.parametrize("config", ["200rpm-x1.25.toml", "300rpm-mono-a30.toml"])
def test_shipped_reference_covers_the_runs_outside_the_campaign(tmp_path, config):
    """The runs at operating points the campaign does not hold ship with their configs and
    their 20-slice twins: their comparisons need no solver either."""
    data = tomllib.loads((UNSEEN_DIR / config).read_text())
    data["dem"]["run"]["liggghts"] = "no-such-liggghts-executable"
    dem = dem_stage(config_from_dict(data), runs_root=tmp_path / "runs", solver=False)
    assert dem.source == "reference" and dem.table.has_phases and dem.results.sequences is not None
    data["dem"]["tables"] = {**data["dem"].get("tables", {}), "nx": 2 * dem.table.nx}
    twin = dem_stage(config_from_dict(data), runs_root=tmp_path / "runs", solver=False)
    assert twin.source == "reference" and twin.table.nx == 2 * dem.table.nx


def test_without_a_solver_run_nothing_is_started(tmp_path):
    data = load_preset("smoke").to_dict()
    data["dem"]["tables"]["nx"] = 7  # binned as nothing cached or shipped is
    with pytest.raises(LookupError, match="no cached or shipped DEM results"):
        dem_stage(config_from_dict(data), runs_root=tmp_path / "runs", solver=False)
    assert not any((tmp_path / "runs").glob("*/in.blender"))


def test_paper_hold_up_is_scaled_from_the_shipped_reduced_run():
    """The reduced preset's inlet margin and blade clearance do not change the vessel: its
    shipped run still sets the paper preset's hold-up for the cost estimate."""
    from workflows.shipped import reference_holdup

    held, source = reference_holdup(load_preset("paper").dem)
    assert "dem-" in source and 30_000 < held < 45_000


def test_the_grid_check_feeds_the_finer_grid_where_the_zone_lands(tmp_path, monkeypatch):
    """On 20 slices of 16.5 mm the feeders' zones (x = 6-30 mm) span the first two: the
    grid check's PBM gets the zone mapped onto the finer table's own compartments (both
    slices, by overlap), not the coarse run's first-slice weights."""
    from workflows.products import compare

    config = load_preset("reduced")
    data = config.to_dict()
    data["dem"]["run"]["liggghts"] = "no-such-liggghts-executable"
    config = config_from_dict(data)
    dem = dem_stage(config, runs_root=tmp_path / "runs", solver=False)
    coarse = pbm_config_for(config, dem.table, None)
    assert len(coarse.feed_weights_a) == dem.table.ny  # inside the first of 10 slices
    seen = {}

    def capture(table, pbm_config, *_args, **_kwargs):
        seen["table"], seen["config"] = table, pbm_config
        return {}

    monkeypatch.setattr(compare, "nx_sensitivity", capture)
    compare.grid_sensitivity(config, dem, coarse, ("phases",), tmp_path / "runs", lambda _line: None)
    fine, fed = seen["table"], seen["config"]
    assert fine.nx == 2 * dem.table.nx
    for weights in (fed.feed_weights_a, fed.feed_weights_b):
        by_slice = np.asarray(weights).reshape(fine.nx, fine.ny).sum(axis=1)
        assert by_slice[0] > 0 and by_slice[1] > 0 and by_slice[2:].sum() == 0
        assert by_slice[1] / by_slice.sum() == pytest.approx(13.5 / 24, rel=0.05)
