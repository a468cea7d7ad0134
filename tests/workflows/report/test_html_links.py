"""The comparison report as a reader meets it: built from the shipped reduced DEM run (no
solver), every image and link resolves, every image has alt text, and the first screen
carries the recommended rate mode with its score and the headline table, before the
details; the solver's diagnostics come last. The recommendation's rule on synthetic
agreement tables with known answers."""

import html
import json
import math

import pytest

from tests.workflows.report.html_pages import broken, read_page
from workflows.analysis.agreement import AgreementRow, ModeValue
from workflows.config import config_from_dict, load_preset
from workflows.report.comparison import HEADLINE, fmt, recommend, split_warnings, why


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """The reduced preset's report, from the shipped DEM results (a missing solver makes a
    mismatch fail instead of starting a run)."""
    from workflows.products.compare import full_comparison

    data = load_preset("reduced").to_dict()
    data["dem"]["run"]["liggghts"] = "no-such-liggghts-executable"
    root = tmp_path_factory.mktemp("comparison")
    page = full_comparison(config_from_dict(data), root / "results", root / "runs", noise_members=20, progress=False)
    return page, json.loads((page.parent / "summary.json").read_text())


@pytest.mark.slow
def test_every_image_and_link_of_the_report_resolves(report):
    page, summary = report
    assert broken(page) == []
    parsed = read_page(page)
    linked = set(parsed.links)
    # every data file the run wrote, linked; the overview shown
    for name in ("summary.json", "dem_timeseries.csv", "pbm_timeseries.csv", "config.toml"):
        assert name in linked, name
    assert any(href.endswith(".h5") for href in linked)
    if (page.parent / "paraview").is_dir():
        assert "paraview/compartments.pvd" in linked
    written = {p.name for p in page.parent.iterdir() if p.is_file() and p.name != "report.html"}
    assert written <= linked
    assert "overview.png" in {src for src, _alt in parsed.images}


@pytest.mark.slow
def test_the_first_screen_holds_the_recommendation_and_the_headline(report):
    page, summary = report
    parsed = read_page(page)
    text = page.read_text()
    ids = parsed.ids
    assert ids["bottom-line"] < ids["headline"] < ids["details"] < ids["files"]
    # the recommended mode has the most rows inside, counted afresh from the agreement records
    rows = summary["agreement"]
    counts = {
        mode: sum(r[f"inside_{mode}"] is True for r in rows)
        for mode in ("velocity", "measured", "phases")
        if any(r[f"inside_{mode}"] is not None for r in rows)
    }
    mode = summary["recommendation"]["mode"]
    assert counts[mode] == max(counts.values())
    judged = sum(r[f"inside_{mode}"] is not None for r in rows)
    first_screen = text[: text.index('id="details"')]
    assert f'rates = "{mode}"' in first_screen and f"{counts[mode]} of {judged}</b>" in first_screen
    # the headline: each quantity's DEM value and interval, the recommended mode's value and
    # verdict, as the agreement table has them
    by_key = {r["key"]: r for r in rows}
    table = parsed.tables["headline"]
    assert table[0][3] == f"PBM, {mode} rates"
    assert [cells[0] for cells in table[1:]] == [by_key[k]["quantity"] for k in HEADLINE]
    for key, cells in zip(HEADLINE, table[1:]):
        r = by_key[key]
        assert cells[2] == f"{fmt(r['dem'])} [{fmt(r['dem_ci_low'])}, {fmt(r['dem_ci_high'])}]"
        assert cells[3] == fmt(r[f"pbm_{mode}"])
        assert cells[4] == ("inside" if r[f"inside_{mode}"] else "outside")
    # one definition: no second metrics table; the curves are the recommended mode's
    assert not any(h.startswith("Metrics") for h in parsed.headings)
    assert summary["provenance"]["pbm_rates_shown"] == mode
    # the solver's diagnostics at the end only
    end = text.index('id="diagnostics"')
    for line in summary["solver_diagnostics"]:
        assert html.escape(line) not in text[:end] and html.escape(line) in text[end:]


def test_a_page_with_a_missing_image_a_bare_image_and_a_dead_link_is_broken(tmp_path):
    (tmp_path / "there.png").write_bytes(b"png")
    (tmp_path / "data.csv").write_text("a\n1\n")
    page = tmp_path / "report.html"
    page.write_text(
        '<html><body><h2 id="files">Files</h2><img src="there.png" alt="a figure"><img src="there.png">'
        '<img src="gone.png" alt="gone"><a href="data.csv">data</a><a href="nothing.json">x</a>'
        '<a href="#files">up</a><a href="#nowhere">?</a><a href="https://example.org/x">web</a></body></html>'
    )
    assert broken(page) == [
        "image 'there.png' has no alt text",
        "image 'gone.png' is not a file beside the page",
        "link 'nothing.json' leads to no file",
        "link '#nowhere' leads to no element",
    ]


def row(key, dem, low, high, **modes):
    return AgreementRow(key, key, "-", dem, low, high, {m: ModeValue(v, low <= v <= high) for m, v in modes.items()})


def test_the_mode_with_the_most_rows_inside_is_recommended():
    rows = [
        row("a", 1.0, 0.9, 1.1, velocity=1.0, measured=1.05, phases=1.5),
        row("b", 1.0, 0.9, 1.1, velocity=2.0, measured=1.2, phases=1.0),
        row("c", 1.0, 0.9, 1.1, velocity=2.0, measured=1.2, phases=1.0),
    ]
    rec = recommend(rows)
    assert rec.mode == "phases" and rec.score.inside == 2 and rec.score.judged == 3 and rec.tied == ()
    assert [s.mode for s in rec.scores] == ["phases", "measured", "velocity"]
    # |1.5 - 1| / 0.1 = 5 half-widths, 0, 0
    assert rec.score.deviation == pytest.approx(5 / 3)
    assert rec.record()["scores"]["velocity"] == {"inside": 1, "judged": 3, "deviation": pytest.approx(20 / 3)}
    # why: where it is inside and the runner-up (measured) is not, and its own miss
    assert why(rec, rows) == (
        "It lies inside the DEM's interval on b and c where the runner-up, the measured rates (1 of 3 inside), "
        "lies outside; its one miss is a (5 half-widths off)."
    )


def test_a_tie_goes_to_the_nearer_mode_then_to_the_fewer_fitted():
    # one inside each; measured misses by 2 half-widths, phases by 10
    rows = [
        row("a", 1.0, 0.9, 1.1, measured=1.0, phases=1.0),
        row("b", 1.0, 0.9, 1.1, measured=1.2, phases=2.0),
    ]
    rec = recommend(rows)
    assert rec.mode == "measured" and rec.tied == ("phases",)
    # equal deviations: the earlier of velocity, measured, phases
    rows = [row("a", 1.0, 0.5, 1.5, velocity=1.25, phases=0.75)]
    assert recommend(rows).mode == "velocity"
    # a row no mode was judged on (no steady DEM state) gives no recommendation
    assert recommend([]) is None
    assert recommend([AgreementRow("a", "a", "-", math.nan, math.nan, math.nan, {})]) is None


def test_why_names_the_tie_break_that_decided():
    # equal distances: the fewer fitted parameters decide, not nearness
    rows = [row("a", 1.0, 0.5, 1.5, velocity=1.25, phases=0.75)]
    assert why(recommend(rows), rows) == (
        "It ties with the phases rates on the count and on the distance from the DEM "
        "(0.5 half-widths of the DEM's interval) and has fewer fitted parameters."
    )


def test_a_miss_on_a_point_interval_has_no_distance_in_half_widths():
    # row a's DEM interval has zero width: phases misses it, by no finite number of half-widths
    rows = [
        row("a", 1.0, 1.0, 1.0, velocity=1.0, phases=2.0),
        row("b", 1.0, 0.9, 1.1, velocity=3.0, phases=1.0),
        row("c", 1.0, 0.9, 1.1, velocity=3.0, phases=1.0),
    ]
    rec = recommend(rows)
    assert rec.mode == "phases" and rec.score.deviation == 0.0
    assert why(rec, rows).endswith("its one miss is a (– half-widths off).")


def test_solver_diagnostics_are_told_from_the_comparisons_own_warnings():
    validity, diagnostics = split_warnings(
        [
            "pooled RTD: only 80.0% of 900 particles recovered within the horizon",
            "solver thermo counters are at step 5292664, the last dump at step 5291564: not compared",
            "3 particles are still in the dumps after the time of their discharge record",
            "something nobody classified",
        ]
    )
    assert validity == [
        "pooled RTD: only 80.0% of 900 particles recovered within the horizon",
        "something nobody classified",
    ]
    assert len(diagnostics) == 2 and diagnostics[0].startswith("solver thermo")


def test_the_prediction_page_shows_its_figure_with_alt_text_and_links_its_files(tmp_path):
    from workflows.cli.main import main
    from workflows.config import preset_path

    assert main(["predict", "--config", str(preset_path("validation")), "--out", str(tmp_path)]) == 0
    assert broken(tmp_path / "report.html") == []
    assert {"prediction.json", "table.h5"} <= set(read_page(tmp_path / "report.html").links)
