"""Design inversion against answers known in closed form: a chain of N equal tanks in series
(one transverse compartment, forward transfer only) has mean residence time L / v and,
for N = 1, |H(f)|^2 = 1 / (1 + (2 pi f / k)^2) with k = v / L; with velocities proportional
to the speed the library's interpolation is exact, so the feasible region is known too."""

import json
import math
import re

import numpy as np
import pytest
from scipy.optimize import brentq

from coupling.errors import ConfigError
from coupling.tables import make_table
from pbm.config import PbmConfig
from pbm.design import TableLibrary, design, design_spec, evaluate, evaluate_feed, feed_library, max_feed, speed_grid
from workflows.cli.main import main

L = 0.33
CONFIG = PbmConfig(feed_weights_a=[1.0], feed_weights_b=[1.0])


def tanks(n: int, v: float, windows: int = 3):
    return make_table(
        t=5.0 * np.arange(windows),
        x_edges=np.linspace(0, L, n + 1),
        y_edges=[-0.05, 0.05],
        vx_pos=v,
        vx_neg=0.0,
        vy_pos=0.0,
        vy_neg=0.0,
        window_s=5.0,
    )


def library(points) -> TableLibrary:
    return TableLibrary(tuple(points), CONFIG, 0.0, L)


def test_residence_time_bound_gives_the_length_of_l_over_v():
    v, target = 0.02, 20.0
    result = design(library([(250.0, tanks(5, v))]), design_spec(mrt_min_s=target))
    assert result.best.length_factor == pytest.approx(target * v / L, rel=1e-4)
    assert result.best.mean_residence_time_s == pytest.approx(target, rel=1e-4)
    assert result.best.margins["mrt_min_s"] >= 0  # the answer lies on the feasible side of the edge
    # 330 mm gives 16.5 s < 20 s: the library's own blender fails at its only speed
    assert result.rpm_ranges == []


def test_composition_bound_matches_the_single_tank_closed_form():
    v, band, sigma, tolerance, coverage = 0.02, 0.5, 0.1, 0.01, 3.0
    c = 0.5

    def excess(factor):  # outlet SD minus what fits in the tolerance, white noise on [0, band]
        k = v / (factor * L)
        vrr = band / (k / (2 * math.pi) * math.atan(2 * math.pi * band / k))
        return c * (1 - c) * sigma / math.sqrt(vrr) - tolerance / coverage

    expected = brentq(excess, 0.5, 2.0, xtol=1e-12)
    spec = design_spec(ca_tolerance=tolerance, coverage_sigmas=coverage, noise_sigma=sigma, noise_band_hz=band)
    result = design(library([(250.0, tanks(1, v))]), spec)
    # the VRR's quadrature (201 log-spaced frequencies) is good to ~1e-3
    assert result.best.length_factor == pytest.approx(expected, rel=2e-3)
    assert coverage * result.best.ca_sd == pytest.approx(tolerance, rel=1e-4)
    assert result.best.ca_rsd == pytest.approx(result.best.ca_sd / c)


def test_speed_library_gives_the_analytic_feasible_region():
    # v = c * rpm, linear in rpm: interpolating between 100 and 300 rpm is exact
    c = 0.02 / 200
    lib = library([(100.0, tanks(4, 100 * c)), (300.0, tanks(4, 300 * c))])
    result = design(lib, design_spec(mrt_min_s=20.0, mrt_max_s=30.0))
    for row in result.rows:
        assert row.length_factor_lo == pytest.approx(20.0 * c * row.rpm / L, rel=1e-4)
        assert row.length_factor_hi == pytest.approx(min(2.0, 30.0 * c * row.rpm / L), rel=1e-4)
    assert result.best.rpm == 100.0
    assert result.best.length_factor == pytest.approx(20.0 * c * 100 / L, rel=1e-4)
    # the library's own blender: L / (c rpm) in [20, 30] s <=> rpm in [L / (30 c), L / (20 c)]
    ((lo, hi),) = result.rpm_ranges
    assert lo == pytest.approx(L / (30 * c), rel=1e-4)
    assert hi == pytest.approx(L / (20 * c), rel=1e-4)
    assert all(min(evaluate(lib, result.spec, rpm, 1.0).margins.values()) >= 0 for rpm in (lo, hi))


def test_unreachable_spec_says_so():
    result = design(library([(250.0, tanks(3, 0.02))]), design_spec(mrt_min_s=500.0))
    assert result.best is None and result.rpm_ranges == []
    assert any("meets the spec" in note for note in result.notes)


def test_specs_outside_the_library_are_refused():
    lib = library([(100.0, tanks(2, 0.01)), (300.0, tanks(2, 0.03))])
    with pytest.raises(ConfigError, match=r"400 rpm leave the table library, which covers 100\.\.300 rpm"):
        speed_grid(lib, design_spec(mrt_min_s=10.0, rpm_max=400.0))
    with pytest.raises(ConfigError, match="rescaling is not trusted"):
        design_spec(mrt_min_s=10.0, length_factor_max=3.0)
    with pytest.raises(ConfigError, match="at least one criterion"):
        design_spec(noise_sigma=0.1)
    with pytest.raises(ConfigError, match="noise_sigma > 0"):
        design_spec(ca_tolerance=0.01)
    with pytest.raises(ConfigError, match="mrt_min_s"):
        design_spec(mrt_min_s=30.0, mrt_max_s=20.0)


def test_speed_grid_holds_every_run_and_points_between():
    lib = library([(150.0, tanks(2, 0.01)), (250.0, tanks(2, 0.02)), (350.0, tanks(2, 0.03))])
    grid = speed_grid(lib, design_spec(mrt_min_s=10.0, rpm_min=200.0))
    assert grid[0] == 200.0 and grid[-1] == 350.0
    assert {250.0, 350.0} <= set(grid.tolist())
    assert np.all(np.diff(grid) > 0)


def test_cli_on_the_shipped_library(tmp_path, capsys):
    # a residence-time spec needs no frequency response: quick on the campaign's three speeds
    code = main(["design", "--mrt-min", "22", "--mrt-max", "40", "--out", str(tmp_path)])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "150 rpm" in out.err and "350 rpm" in out.err  # the library found: the campaign's speed runs
    assert re.search(r"smallest blender: \d+\.\d mm", out.out)
    # the campaign's feed runs are a feed library: the largest feed the 330-mm blender takes
    assert "feed library: 36.85 /s" in out.err
    assert re.search(r"largest feed meeting the spec .*: \d+\.\d particles/s", out.out)
    assert (tmp_path / "design.json").is_file() and (tmp_path / "feasible.png").stat().st_size > 10_000
    # the figure is drawn from the record design.json holds: the file alone redraws it
    from workflows.report.design import plot_feasible

    again = plot_feasible(json.loads((tmp_path / "design.json").read_text()), tmp_path / "again.png")
    assert again.stat().st_size > 10_000


def test_cli_bad_library_is_one_line(tmp_path, capsys):
    code = main(["design", "--mrt-min", "20", "--library", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "nowhere" in err


def steady_tanks(feed: float, n: int = 5, a: float = 0.05, beta: float = 1.0, windows: int = 6):
    """Tanks in series at steady state under the flow law r = a N^beta: each holds
    N = (feed / a)^(1 / (1 + beta)) and passes feed particles/s on."""
    held = (feed / a) ** (1.0 / (1.0 + beta))
    rate = a * held**beta
    zeros = np.zeros((windows, n, 1))
    return make_table(
        t=5.0 * np.arange(windows),
        x_edges=np.linspace(0, L, n + 1),
        y_edges=[-0.05, 0.05],
        vx_pos=rate * L / n,
        vx_neg=0.0,
        vy_pos=0.0,
        vy_neg=0.0,
        count_A=held / 2 + zeros,
        count_B=held / 2 + zeros,
        n_samples=100 + zeros.astype(int),
        rate_x_pos=rate + zeros,
        rate_x_neg=zeros,
        rate_y_pos=zeros,
        rate_y_neg=zeros,
        window_s=5.0,
    )


def test_largest_feed_follows_the_flow_law():
    """Tanks whose rates follow r = a N^beta: the library's law is fitted exactly, and the
    largest feed with a mean residence time >= T is where n N(F) / F = T."""
    n, a, beta = 5, 0.05, 1.0
    config = CONFIG.model_copy(update={"rates": "measured", "feed_rate_a_per_s": 50.0, "feed_rate_b_per_s": 50.0})
    feeds = feed_library([(f, steady_tanks(f, n, a, beta)) for f in (50.0, 100.0, 200.0)], config, 250.0, L)
    np.testing.assert_allclose(np.array(feeds.exponents)[:, 0], beta, atol=1e-9)
    mrt = {f: n * (f / a) ** (1 / (1 + beta)) / f for f in (50.0, 100.0, 200.0)}
    for f, expected in mrt.items():  # at the runs themselves: their own steady state
        assert evaluate_feed(feeds, design_spec(mrt_min_s=1.0), f).mean_residence_time_s == pytest.approx(
            expected, rel=1e-6
        )
    result = max_feed(feeds, design_spec(mrt_min_s=mrt[100.0]))
    assert result.best.feed_per_s == pytest.approx(100.0, rel=1e-4)
    assert result.best.margins["mrt_min_s"] >= 0
    # met up to the library's top: said, and nothing beyond it is claimed
    top = max_feed(feeds, design_spec(mrt_min_s=0.1 * mrt[200.0]))
    assert top.best.feed_per_s == 200.0 and "outside the runs" in top.notes[0]
    # a residence-time window met only in the middle: the lower feeds that fail are named
    window = max_feed(feeds, design_spec(mrt_min_s=mrt[100.0], mrt_max_s=0.999 * mrt[50.0]))
    assert window.best.feed_per_s == pytest.approx(100.0, rel=1e-4)
    assert window.notes == ["not met at the lower feeds scanned: 50 /s"]
    none = max_feed(feeds, design_spec(mrt_min_s=2 * mrt[50.0]))
    assert none.best is None and "no feed" in none.notes[0]
    with pytest.raises(ConfigError, match="distinct feed rates"):
        feed_library([(50.0, steady_tanks(50.0))], config, 250.0, L)


def test_forked_speeds_and_the_residence_only_edge_change_nothing(monkeypatch):
    # v grows with rpm: from 125 rpm on, the composition sets the shortest length and the
    # residence time the longest, both inside the lengths searched
    c = 0.02 / 200
    lib = library([(100.0, tanks(4, 100 * c)), (200.0, tanks(4, 200 * c))])
    spec = design_spec(ca_tolerance=0.015, noise_sigma=0.1, mrt_max_s=30.0)
    monkeypatch.setattr("pbm.design.free_cores", lambda limit=None: 2)
    forked = design(lib, spec)
    monkeypatch.setattr("pbm.design.free_cores", lambda limit=None: 1)
    serial = design(lib, spec)
    # every margin judged on every point, the composition included
    monkeypatch.setattr("pbm.design._RESIDENCE", ())
    full = design(lib, spec)
    for result in (forked, serial):
        assert result.to_dict() == full.to_dict()
    assert all(0.5 < r.length_factor_lo < r.length_factor_hi < 2.0 for r in full.rows[1:])
    assert full.rpm_ranges  # the ranges' search took the rows' evaluations at 1 x as known


def test_speed_ranges_ignore_known_evaluations_of_other_criteria():
    from pbm.design import Evaluation, speed_ranges

    lib = library([(250.0, tanks(3, 0.02))])
    spec = design_spec(mrt_min_s=10.0, ca_tolerance=0.03, noise_sigma=0.1)
    wrong = Evaluation(250.0, 1.0, 99.0, None, None, None, {"mrt_min_s": 89.0})  # no composition judged
    assert speed_ranges(lib, spec, [250.0], known=[wrong]) == speed_ranges(lib, spec, [250.0])


def test_a_command_line_imports_no_figure_library_or_integrator_before_it_runs():
    import subprocess
    import sys

    # the parser imports no configuration (pydantic, pbm, scipy), so that the design's figure
    # process forks before them; and reading the library, the search and the largest feed
    # import no figure library, integrator, compiled kernel or frame library
    probe = (
        "import sys, workflows.cli.main as m; m.build_parser(['design']); "
        "print(sorted(k for k in ('matplotlib', 'scipy', 'pydantic', 'workflows.config', 'pbm') if k in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
    probe = (
        "import sys, workflows.products.design as d, pbm.design as p; runs = d.library_runs(); "
        "spec = p.design_spec(ca_tolerance=0.04, noise_sigma=0.1, noise_tau_s=5, mrt_max_s=25); "
        "p.design(d.load_library(runs, 'measured'), spec); "
        "p.max_feed(d.load_feed_library(runs, 'measured'), spec); "
        "print(sorted(k for k in ('matplotlib', 'scipy.integrate', 'pbm.ensemble', 'numba', 'pandas', 'meshio') "
        "if k in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_a_point_whose_residence_time_fails_gets_no_frequency_response(monkeypatch):
    """The composition is judged only where the residence time is met: the points where it
    fails get no frequency response, and the answers -- the blender's and the largest
    feed's -- are those judging every margin at every point gives."""
    import pbm.design

    c = 0.02 / 200
    lib = library([(100.0, tanks(4, 100 * c)), (200.0, tanks(4, 200 * c))])
    spec = design_spec(ca_tolerance=0.015, noise_sigma=0.1, mrt_max_s=30.0)
    monkeypatch.setattr("pbm.design.free_cores", lambda limit=None: 1)
    responses = []
    respond = pbm.design.system_response
    monkeypatch.setattr("pbm.design.system_response", lambda *a, **k: responses.append(a[0]) or respond(*a, **k))
    feeds = feed_library([(f, steady_tanks(f, beta=1.0)) for f in (10.0, 20.0, 40.0)], PbmConfig(), 250.0, 0.33)
    feed_spec = design_spec(ca_tolerance=0.05, noise_sigma=0.1, mrt_max_s=4.0)
    quick, quick_feed = design(lib, spec), max_feed(feeds, feed_spec)
    spared = [e for r in quick.rows for e in r.scanned if e.vrr is None]
    spared_feeds = [e for e in quick_feed.scanned if e.vrr is None]
    assert spared and all(e.margins["mrt_max_s"] < 0 and not e.feasible for e in spared)
    assert spared_feeds and all(e.margins["mrt_max_s"] < 0 for e in spared_feeds)
    n_quick = len(responses)
    monkeypatch.setattr("pbm.design._RESIDENCE", ())
    full, full_feed = design(lib, spec), max_feed(feeds, feed_spec)
    assert len(responses) - n_quick > n_quick  # judged whole everywhere: more responses
    assert [(r.length_factor_lo, r.length_factor_hi) for r in quick.rows] == [
        (r.length_factor_lo, r.length_factor_hi) for r in full.rows
    ]
    assert quick.best == full.best and quick.rpm_ranges == full.rpm_ranges
    assert quick_feed.best == full_feed.best


def test_a_design_that_fails_after_its_search_leaves_no_figure(tmp_path, monkeypatch):
    """The figure is drawn beside the feed library's search, to a file of its own: when the
    search fails, neither file is written and nothing of the drawing is left behind."""
    from coupling.forked import Prepared
    from workflows.products.design import run_design
    from workflows.report import DESIGN_FIGURES

    def broken(*_a, **_k):
        raise ConfigError("the feed library's search broke")

    monkeypatch.setattr("workflows.products.design.max_feed", broken)
    spec = design_spec(mrt_min_s=22.0, mrt_max_s=40.0)
    with Prepared(DESIGN_FIGURES) as figures, pytest.raises(ConfigError, match="broke"):
        run_design(spec, tmp_path / "out", figures=figures)
    assert list((tmp_path / "out").iterdir()) == []
