"""Report: the RTD overlap metric's limits, figures and HTML from two synthetic sides."""

import numpy as np
import pandas as pd
import pytest

from dem.summary import DemSummary
from pbm.summary import PbmSummary
from workflows.report.comparison import (
    SideResults,
    Study,
    comparison_metrics,
    interval_method,
    plot_comparison,
    render_html,
    rtd_overlap,
)


def _rtd(mean, t=None):
    t = np.arange(0.5, 200, 1.0) if t is None else t
    e = np.exp(-((t - mean) ** 2) / (2 * 5.0**2))
    return pd.DataFrame({"t_s": t, "E_per_s": e / e.sum()})


def test_rtd_overlap_limits():
    assert rtd_overlap(_rtd(50), _rtd(50)) == pytest.approx(1.0)
    assert rtd_overlap(_rtd(50), _rtd(150)) == pytest.approx(0.0, abs=1e-9)
    # Two unit Gaussians one SD apart overlap by 2*Phi(-1/2) = 0.617.
    assert rtd_overlap(_rtd(50), _rtd(55)) == pytest.approx(0.617, abs=0.01)


def _side(label, rng):
    t = np.arange(0, 30.0)
    ts = pd.DataFrame(
        {
            "t_s": t,
            "outflow_A_per_s": rng.uniform(30, 40, t.size),
            "outflow_B_per_s": rng.uniform(30, 40, t.size),
            "C_A": rng.uniform(0.4, 0.6, t.size),
            "rsd_outlet": rng.uniform(0, 0.3, t.size),
            "rsd_blender": rng.uniform(0, 0.3, t.size),
            "holdup_A": np.linspace(0, 300, t.size),
            "holdup_B": np.linspace(0, 300, t.size),
        }
    )
    shared = {"mean_residence_time_s": 8.0, "rtd_variance_s2": 4.0, "steady_C_A": 0.5}
    if label == "DEM":
        summary = DemSummary(**shared, final_rsd_outlet_floor=0.1, extra={"wall_time_s": 100.0})
    else:
        summary = pbm_summary(**shared, wall_time_s=0.05)
    return SideResults(label, ts, _rtd(8.0), rng.uniform(0, 1, 10), summary)


def pbm_summary(**fields) -> PbmSummary:
    """A PBM summary of a 10 x 2 grid with ``fields`` set (the PBM-only ones made up)."""
    own = {
        "final_rsd_by_slice": (0.1,) * 10,
        "holdup_final_A": 300.0,
        "holdup_final_B": 300.0,
        "rtd_pulse_s": 10.0,
        "rtd_pulse_rule": "given",
        "filled_compartment_windows": 0,
        "nx": 10,
        "ny": 2,
        "duration_s": 30.0,
        "method": "expm",
        "rate_law": "table",
    }
    return PbmSummary(**{**own, **fields})


def test_report_writes_figures_and_page(tmp_path, rng):
    dem, pbm = _side("DEM", rng), _side("PBM", rng)
    metrics = comparison_metrics(dem, pbm, feed_rate_per_s=73.7)
    assert metrics["speedup_pbm_over_dem"] == pytest.approx(2000)
    assert metrics["mean_residence_time_rel_diff"] == 0.0
    assert metrics["final_rsd_outlet_dem_floor"] == 0.1 and metrics["steady_C_A_pbm"] == 0.5
    figures = plot_comparison(dem, pbm, tmp_path)
    for name in figures.values():
        assert (tmp_path / name).stat().st_size > 5000
    study = Study("Blender length", "length_m", "rtd.png", "RSD falls with length", [{"length_m": 0.33, "rsd": 0.1}])
    page = render_html(
        "smoke",
        bottom_line='<section id="bottom-line">the bottom line</section>',
        agreement="the agreement table",
        figures=figures,
        shown_mode="measured",
        metrics=metrics,
        provenance={"input_hash": "abc", "config_toml": "x = 1"},
        studies=[study],
        notes=["a note"],
        diagnostics=["solver thermo counters are at step 5"],
    )
    # the overview shown, each panel linked; the study's figure shown
    assert 'src="overview.png"' in page and 'href="rtd.png"' in page and page.count('src="rtd.png"') == 1
    assert "Blender length" in page and "abc" in page and "PBM, measured rates" in page
    # the note on top, the bottom line before the details, the diagnostics last
    order = [page.index(s) for s in ("a note", "the bottom line", 'id="details"', "Provenance", "thermo counters")]
    assert order == sorted(order)
    assert "2000 times faster" in page


def test_side_results_requires_every_column(rng):
    side = _side("DEM", rng)
    with pytest.raises(ValueError, match="lacks columns"):
        SideResults("DEM", side.timeseries.drop(columns=["C_A"]), side.rtd, side.rsd_by_slice, DemSummary())


def test_the_report_says_how_the_dem_intervals_were_had():
    steady = {"holdup": {}, "batch_s": 40.0, "block_s": 5.0, "degrees_of_freedom": 6.6}
    line = interval_method(steady)
    assert "40-s batches" in line and "6.6 degrees of freedom" in line and "5-s blocks of entry time" in line
    assert interval_method({"holdup": {}}) == "" and interval_method({}) == ""
