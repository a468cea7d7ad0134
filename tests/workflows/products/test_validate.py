"""The validation campaign's pure parts: its configurations, the predicted tables (speed
scaling, table library), and the verdict rule on rows with known answers."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from coupling.errors import ConfigError
from coupling.tables import make_table
from pbm.studies import interpolate_tables, scale_speed
from workflows.analysis.agreement import MODES, AgreementRow, ModeValue
from workflows.analysis.validation import FILL_SOURCES, feed_library, judge, prediction_tables, verdict_text
from workflows.products.campaign import load_campaign
from workflows.products.validate import campaign_configs

X, Y = np.linspace(0, 0.33, 6), np.linspace(-0.05, 0.05, 5)


def table(v: float, rates: bool = True, x_edges=X):
    rate = {f"rate_{k}": 2 * v for k in ("x_pos", "x_neg", "y_pos", "y_neg")} if rates else {}
    return make_table(
        t=[0.0, 5.0],
        x_edges=x_edges,
        y_edges=Y,
        vx_pos=v,
        vx_neg=v / 2,
        vy_pos=v / 4,
        vy_neg=v / 4,
        count_A=10 * v,
        count_B=10 * v,
        **rate,
    )


def test_campaign_changes_one_factor_at_a_time_and_keeps_the_blade_spacing():
    configs = campaign_configs()
    assert list(configs) == [c.name for c in load_campaign().changes]
    base = configs["baseline"]
    spacing = lambda g: (g.last_blade_x_m - g.first_blade_x_m) / (g.blade_stations - 1)  # noqa: E731
    longer = configs["length_x1.25"].dem.geometry
    assert longer.length_m == pytest.approx(1.25 * base.dem.geometry.length_m)
    assert spacing(longer) == pytest.approx(spacing(base.dem.geometry))
    assert configs["rpm_150"].dem.operation.impeller_rpm == 150
    assert configs["feed_x2"].dem.operation.feed_rate_total_per_s == pytest.approx(2 * 73.7)
    assert configs["feed_x0.5"].dem.operation.feed_rate_total_per_s == pytest.approx(0.5 * 73.7)
    assert configs["feed_x1.5"].dem.operation.feed_rate_total_per_s == pytest.approx(1.5 * 73.7)
    # everything else as the baseline: same particles, numerics, and duration but where half
    # the feed needs longer for its pooled RTD
    for name, config in configs.items():
        assert config.dem.particles == base.dem.particles and config.dem.numerics == base.dem.numerics
        longer = 320.0 if name == "feed_x0.5" else base.dem.operation.duration_s
        assert config.dem.operation.duration_s == longer


def test_scale_speed_scales_velocities_and_rates():
    scaled = scale_speed(table(0.04), 0.6)
    assert np.allclose(scaled.vx_pos, 0.024) and np.allclose(scaled.vy_neg, 0.006)
    assert np.allclose(scaled.rate_x_pos, 0.048)
    assert np.allclose(scaled.count_A, table(0.04).count_A)  # the bed is unchanged
    with pytest.raises(ConfigError, match="speed factor"):
        scale_speed(table(0.04), 0.0)


def test_interpolation_is_linear_between_the_bracketing_tables_and_refuses_to_extrapolate():
    library = [(150, table(0.02)), (350, table(0.06)), (500, table(0.10))]
    mid = interpolate_tables(library, 250)
    assert np.allclose(mid.vx_pos, 0.04) and np.allclose(mid.rate_y_pos, 0.08) and np.allclose(mid.count_A, 0.4)
    assert np.allclose(interpolate_tables(library, 350).vx_pos, 0.06)
    assert np.allclose(interpolate_tables(library, 425).vx_pos, 0.08)
    with pytest.raises(ConfigError, match="outside the table library's range 150..500"):
        interpolate_tables(library, 100)
    with pytest.raises(ConfigError, match="differ in grid"):
        interpolate_tables([(150, table(0.02)), (350, table(0.06, x_edges=np.linspace(0, 0.4, 6)))], 250)
    # rates survive only when both ends have them
    assert not interpolate_tables([(150, table(0.02, rates=False)), (350, table(0.06))], 250).has_rates


def test_prediction_tables_from_the_baseline_and_the_library():
    configs = campaign_configs()
    speeds = {"baseline": 0.04, "length_x1.25": 0.05, "rpm_150": 0.02, "rpm_350": 0.06, "feed_x2": 0.03}
    sides = {name: SimpleNamespace(table=table(v)) for name, v in speeds.items()}
    tables = prediction_tables(sides, configs)
    assert set(tables["baseline"]) == {"self", "library"}  # 250 rpm left out, from 150 and 350
    assert np.allclose(tables["baseline"]["library"].table.vx_pos, 0.04)
    assert np.allclose(tables["rpm_150"]["baseline"].table.vx_pos, 0.04 * 150 / 250)
    assert "outside the table library's range" in tables["rpm_150"]["library"]
    assert np.allclose(tables["length_x1.25"]["baseline"].table.x_edges, 1.25 * X)
    assert np.allclose(tables["feed_x2"]["baseline"].table.vx_pos, 0.04)  # the paper's linear assumption
    assert tables["feed_x2"]["baseline"].rate_law == "table"
    assert "library" not in tables["feed_x2"]  # no other run differs from it only in rpm
    # the feed library: the baseline's own law, and no library law from one other run
    own_law = tables["feed_x2"]["baseline + fill law"]
    assert own_law.rate_law == "fill" and own_law.table is sides["baseline"].table and not own_law.exponents
    assert "a law needs two" in tables["feed_x2"]["library + fill law"]
    assert "baseline + fill law" not in tables["rpm_150"]
    assert set(feed_library(configs)) == {"baseline", "feed_x2", "feed_x0.5", "feed_x1.5"}


def row(key, dem, low, high, velocity, measured):
    """An agreement row; the overlap's interval is its noise band [noise low, 1] per mode."""
    noise = low if key == "rtd_overlap" else None
    return AgreementRow(
        key,
        key,
        "-",
        dem,
        low,
        high,
        {"velocity": ModeValue(velocity, None, None, noise), "measured": ModeValue(measured, None, None, noise)},
    )


def test_judge_compares_the_prediction_with_the_self_built_pbm_plus_the_dem_interval():
    own = [
        row("holdup", 100, 98, 102, 110, 101),
        row("rtd_overlap", 1, 0.95, 1, 0.80, 0.97),
        row("rtd_recovered_fraction", 0.99, 0.98, 1, 0.5, 0.5),
    ]
    predicted = [
        row("holdup", 100, 98, 102, 112, 104),
        row("rtd_overlap", 1, 0.95, 1, 0.78, 0.90),
        row("rtd_recovered_fraction", 0.99, 0.98, 1, 0.1, 0.1),
    ]
    verdict = judge(predicted, own)
    velocity = {r.key: r for r in verdict["velocity"].rows}
    # |112 - 100| = 12 <= |110 - 100| + 2; overlap: 0.22 <= 0.20 + 0.05 (one-sided band)
    assert velocity["holdup"].judged.tolerance == pytest.approx(12) and velocity["holdup"].ok
    assert velocity["rtd_overlap"].ok and verdict["velocity"].predicts
    assert "rtd_recovered_fraction" not in velocity  # a diagnostic, not judged
    # measured: |104 - 100| = 4 > 1 + 2 fails; overlap 0.10 > 0.03 + 0.05 fails
    assert verdict["measured"].failing == ["holdup", "rtd_overlap"] and not verdict["measured"].predicts
    assert verdict_text(verdict) == "the hybrid predicts this (velocity rates)"
    both_fail = judge([row("holdup", 100, 98, 102, 130, 130)], own)
    assert verdict_text(both_fail) == (
        "this needs a new DEM run (nearest: velocity rates, 1 of 1 quantities outside tolerance: holdup)"
    )
    slices = judge(
        [row(f"holdup_slice_{i}", 10, 9, 11, 20, 20) for i in (1, 2)],
        [row(f"holdup_slice_{i}", 10, 9, 11, 10, 10) for i in (1, 2)],
    )
    assert verdict_text(slices).endswith("2 of 2 quantities outside tolerance: hold-up of 2 axial slices)")


def test_judge_is_calibrated_on_the_baseline_not_on_a_poor_self_built_pbm():
    baseline = [row("holdup", 100, 98, 102, 110, 100)]  # the hybrid: 10 % off (velocity), exact (measured)
    own = [row("holdup", 200, 196, 204, 400, 200)]  # on the new run the velocity PBM is 100 % off
    verdict = judge([row("holdup", 200, 196, 204, 230, 203)], own, baseline)
    velocity, measured = verdict["velocity"].rows[0], verdict["measured"].rows[0]
    assert velocity.judged.tolerance == pytest.approx(0.10 * 200 + 4) and not velocity.ok  # 30 > 24
    assert measured.judged.tolerance == pytest.approx(4) and measured.ok  # 3 <= 0 + 4
    assert velocity.self_value == 400  # reported, not the yardstick


def test_judge_lists_quantities_missing_on_either_side():
    verdict = judge([row("C_A", 0.5, 0.49, 0.51, float("nan"), 0.5)], [row("C_A", 0.5, 0.49, 0.51, 0.5, 0.5)])
    assert verdict["velocity"].missing == ("C_A",) and not verdict["velocity"].predicts
    assert verdict["measured"].predicts


@pytest.mark.slow
def test_the_report_rebuilds_from_the_shipped_campaign_without_liggghts(tmp_path):
    import json

    from tests.workflows.report.html_pages import broken
    from workflows.products.validate import validation_report
    from workflows.shipped import VALIDATION_DIR as REFERENCE_DIR

    if not any(REFERENCE_DIR.glob("dem-*.h5")):
        pytest.fail(f"no shipped campaign results in {REFERENCE_DIR}")
    page = validation_report(tmp_path / "out", tmp_path / "runs", solver=False)
    summary = json.loads((page.parent / "summary.json").read_text())
    # every shipped run, in the campaign's order (runs not shipped yet are left out)
    shipped = [row["run"] for row in summary["campaign"]]
    assert shipped == [c.name for c in load_campaign().changes if c.name in shipped]
    assert {"baseline", "length_x1.25", "rpm_150", "rpm_350", "feed_x2"} <= set(shipped)
    assert all(row["source"] == "reference" for row in summary["campaign"])
    walls = [row["dem_wall_time_s"] for row in summary["campaign"]]
    assert max(walls) <= summary["campaign_elapsed_s"] <= sum(walls)
    # every change is judged from the baseline, and 250 rpm from the library of 150 and 350
    judged = {(v["run"], v["source"]) for v in summary["verdicts"] if v["judged"]}
    assert {(name, "baseline") for name in shipped[1:]} | {("baseline", "library")} <= judged
    for v in summary["verdicts"]:
        assert v["verdict"].startswith(("the hybrid predicts this", "this needs a new DEM run", "not predicted"))
        for mode in MODES:
            for row in (v["judged"] or {}).get(mode, {}).get("rows", []):
                assert row["ok"] == (row["error"] <= row["tolerance"])
    # the feed library: both fill-law sources judged for every other feed, the others' law
    # nearer the DEM than the linear PBM in its best mode, and the step predicted from the
    # steady baseline's own law in every mode
    feeds = [name for name in ("feed_x0.5", "feed_x1.5", "feed_x2") if name in shipped]
    assert {(name, source) for name in feeds for source in FILL_SOURCES} <= judged
    best = {
        (v["run"], v["source"]): max(sum(r["ok"] for r in judged["rows"]) for judged in v["judged"].values())
        for v in summary["verdicts"]
        if v["judged"]
    }
    for name in feeds:
        assert best[name, "library + fill law"] > best[name, "baseline"]
    step_rows = [r for r in summary["step_response"]["rows"] if r["source"] == "baseline + fill law"]
    assert {r["mode"] for r in step_rows} == set(MODES) and all(r["predicted"] for r in step_rows)
    assert {"velocity", "measured"} <= summary["dem_budget"]["smallest_T"].keys() <= set(MODES)
    for name in ("parity.png", "profiles.png", "budget.png"):
        assert (page.parent / name).stat().st_size > 10_000
    # every figure shown with alt text, every link to a file beside the page
    assert broken(page) == []


def test_campaign_span_counts_side_by_side_runs_once_and_skips_the_days_between():
    from workflows.analysis.validation import campaign_span_s

    def side(finished, wall):
        return SimpleNamespace(provenance={"run_finished": finished, "wall_time_s": wall})

    sides = {
        "a": side("2026-11-23T10:00:00+00:00", 3600.0),  # 09:00-10:00
        "b": side("2026-11-23T10:30:00+00:00", 3600.0),  # 09:30-10:30, beside a
        "c": side("2026-12-01T12:00:00+00:00", 600.0),  # a week later
    }
    assert campaign_span_s(sides) == pytest.approx(5400.0 + 600.0)
    assert campaign_span_s({"a": side(None, 10.0)}) is None
