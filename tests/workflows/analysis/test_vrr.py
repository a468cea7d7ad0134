"""The DEM's transfer function from particle records (workflows.analysis.vrr) against exact ones:
a well-mixed tank (exponential RTD) and a 1-D chain of n equal tanks (Erlang RTD), whose
transfer functions are 1 / (1 + i 2 pi f T) and (k / (k + i 2 pi f))^n exactly."""

import math

import numpy as np
import pandas as pd
import pytest

from coupling.errors import ConfigError
from coupling.intervals import Interval
from coupling.jsonable import json_ready
from coupling.tables import make_table
from dem.summary import DemSummary, Estimate, PooledRtdSummary
from pbm.config import PbmConfig
from workflows.analysis.vrr import EnsembleCheck, VrrComparison, dem_transfer, vrr_comparison
from workflows.cli.main import main
from workflows.report.vrr import plot_vrr, vrr_html

WINDOW = (40.0, 200.0)
# Horizon 10 mean residence times: the conditional-on-recovery H differs from the
# untruncated exact one by < e^-10 for an exponential, far inside any interval here.
MEAN_S = 17.0
HORIZON = 10 * MEAN_S


def records(residence_a, residence_b, rng, window=WINDOW):
    """particle_records-like frame: entries uniform in the window, exit = entry + residence."""
    rows = []
    for code, tau in ((1, residence_a), (2, residence_b)):
        entry = rng.uniform(*window, size=tau.size)
        rows.append(
            pd.DataFrame(
                {"component": np.full(tau.size, code, dtype=np.int8), "entry_t_s": entry, "exit_t_s": entry + tau}
            )
        )
    return pd.concat(rows, ignore_index=True)


def spec(window=WINDOW, horizon=HORIZON, n_entered=1, mean=MEAN_S):
    return PooledRtdSummary(
        horizon, tuple(window), n_entered, mean_residence_time_s=Estimate(mean, mean, mean), bin_s=1.0
    )


def test_single_tank_exponential_rtd_recovered_within_interval(rng):
    n = 6000
    particles = records(rng.exponential(MEAN_S, n), rng.exponential(3.0, n), rng)
    # particles that must not count: entered before the window, or never left (NaN exit)
    extra = pd.DataFrame({"component": np.int8(1), "entry_t_s": [10.0, 100.0], "exit_t_s": [11.0, np.nan]})
    particles = pd.concat([particles, extra], ignore_index=True)
    freqs = np.array([0.0, 0.003, 0.01, 0.03])
    d = dem_transfer(particles, spec(), freqs, "A")
    exact = 1 / np.sqrt(1 + (2 * np.pi * freqs * MEAN_S) ** 2)
    assert d.n_entered == n + 1 and d.n_recovered == n
    assert d.H[0] == pytest.approx(1.0, abs=1e-12)  # conditional on recovery: all of it leaves
    assert np.all((d.abs_H.low <= exact) & (exact <= d.abs_H.high)), (d.abs_H, exact)
    np.testing.assert_allclose(d.vrr.estimate, 1 / d.abs_H.estimate**2)
    assert np.all(d.vrr.low <= 1 / exact**2) and np.all(1 / exact**2 <= d.vrr.high)
    assert d.floor == pytest.approx(1 / math.sqrt(n))
    assert d.resolved.all()
    # the component code and the feeder name select the same particles
    assert np.array_equal(dem_transfer(particles, spec(), freqs, 1, n_boot=50).H, d.H)


def test_sampling_floor_marks_high_frequencies_unresolved(rng):
    n = 2000
    particles = records(rng.exponential(MEAN_S, n), rng.exponential(MEAN_S, n), rng)
    d = dem_transfer(particles, spec(), [0.001, 2.0, 5.0], "B", n_boot=200)
    # at 2-5 Hz the exact |H| is ~0.004 < 1/sqrt(N) = 0.022: only noise is left
    assert d.resolved.tolist() == [True, False, False]
    assert np.all(d.abs_H.estimate[1:] < 3 * d.floor)


def test_interval_narrows_with_more_particles(rng):
    freqs = np.array([0.005, 0.02])
    widths = []
    for n in (500, 8000):
        particles = records(rng.exponential(MEAN_S, n), rng.exponential(MEAN_S, n), rng)
        d = dem_transfer(particles, spec(), freqs, "A", noise_taus_s=(0.0,), n_boot=500)
        widths.append((d.abs_H.high - d.abs_H.low, d.noise[0].high - d.noise[0].low))
    # 16 x the particles: ~4 x narrower; asked for at least 2 x
    assert np.all(widths[1][0] < 0.5 * widths[0][0])
    assert widths[1][1] < 0.5 * widths[0][1]


def chain_table(n_tanks, k_per_s, length_m=0.3):
    """n tanks in series (NY = 1), forward rate k in both rate modes; nothing moves back."""
    dx = length_m / n_tanks
    zero = np.zeros((1, n_tanks, 1))
    return make_table(
        t=5.0 * np.arange(12),
        x_edges=np.linspace(0, length_m, n_tanks + 1),
        y_edges=np.array([-0.05, 0.05]),
        vx_pos=k_per_s * dx,
        vx_neg=0.0,
        vy_pos=0.0,
        vy_neg=0.0,
        rate_x_pos=zero + k_per_s,
        rate_x_neg=zero,
        rate_y_pos=zero,
        rate_y_neg=zero,
    )


def half_widths(value, interval: Interval):
    """Distance of ``value`` from the interval's estimate, in half widths on its side."""
    est, low, high = (np.asarray(v, dtype=float) for v in interval)
    value = np.asarray(value, dtype=float)
    return np.abs(value - est) / np.where(value > est, high - est, est - low)


def test_pbm_and_dem_agree_on_the_pbm_own_erlang_rtd(rng, tmp_path):
    n_tanks, n = 5, 6000
    k = n_tanks / MEAN_S  # Erlang(5, k): mean 17 s, the PBM chain's exact RTD
    table = chain_table(n_tanks, k)
    assert table.has_rates
    particles = records(rng.gamma(n_tanks, 1 / k, n), rng.gamma(n_tanks, 1 / k, n), rng)
    c = vrr_comparison(table, PbmConfig(), 10.0, DemSummary(pooled_rtd=spec(n_entered=2 * n)), particles)
    assert isinstance(c, VrrComparison)
    freqs = np.asarray(c.frequency_hz)
    assert freqs.size == 25 and freqs[0] == pytest.approx(0.1 / MEAN_S) and freqs[-1] == pytest.approx(1.0)
    exact = np.abs((k / (k + 2j * np.pi * freqs)) ** n_tanks)
    assert set(c.pbm) == {"velocity", "measured"}
    for mode, m in c.pbm.items():
        for f in ("A", "B"):
            pbm, dem = m.feeders[f], c.dem[f]
            np.testing.assert_allclose(pbm.abs_H, exact, rtol=1e-9)
            assert pbm.mean_residence_time_s == pytest.approx(MEAN_S)
            # A 95 % interval misses the truth now and then, and here one sample per feeder
            # decides every point at once (this seed's B sample sits ~1 half width low
            # throughout), so judge the distance in half widths, not the verdicts.
            resolved = np.asarray(dem.resolved)
            vrr = Interval(*(np.asarray(v)[resolved] for v in dem.vrr))
            assert np.all(half_widths(np.asarray(pbm.vrr)[resolved], vrr) < 1.5), (mode, f)
            for row in pbm.noise:
                assert half_widths(row.vrr, row.dem) < 1.5, (mode, f, row)
                assert abs(row.ratio_to_dem - 1) < 0.03
            inside = [v for v in pbm.inside if v is not None]
            assert len(inside) == resolved.sum() >= 10
        assert m.inside_fraction >= 0.5
        # the worst ratio comes from near the floor, where the interval spans a factor ~2;
        # a miss (outside the interval) is a few %, where the interval is narrow
        assert 0.5 < m.worst.ratio_pbm_to_dem < 2.0
        outside = m.worst_outside
        assert outside is None or abs(outside.ratio_pbm_to_dem - 1) < 0.1
    for f in ("A", "B"):
        d = c.dem[f]
        resolved = np.asarray(d.resolved)
        # the Erlang |H| falls as f^-5: the floor is reached inside the sweep, and then stays
        assert resolved[0] and not resolved[-1] and not np.any(np.diff(resolved.astype(int)) > 0)
        assert d.floor == pytest.approx(1 / math.sqrt(n))
        for iv, uncorrected in zip(d.noise, d.noise_uncorrected):
            # the floor's bias of the noise VRR is below its interval's width
            assert abs(uncorrected - iv.estimate) < iv.high - iv.low
    out = plot_vrr(c, tmp_path / "vrr.png")
    assert out.stat().st_size > 10_000
    # the comparison report's section: every mode's count of resolved points, every noise row
    section = vrr_html(c, out.name)
    for mode, m in c.pbm.items():
        assert f"<td>{mode}</td><td>{m.n_inside}/{m.n_judged} resolved points</td>" in section
    assert section.count("<tr><td>A, ") == len(c.noise_taus_s) and "vrr.png" in section
    # the time-domain ensemble agrees with the transfer functions it is reported beside
    for mode, m in c.pbm.items():
        (row,) = m.ensemble_check
        assert isinstance(row, EnsembleCheck)
        assert abs(row.relative_difference) < 0.05 and f"<tr><td>{mode}</td><td>{row.sigma:g}</td>" in section
    assert_record_matches(c)


def assert_record_matches(c: VrrComparison) -> None:
    """``record()`` is the nested dict vrr.json and summary.json hold: every key, and the
    typed result's numbers under them."""
    r = c.record()
    assert list(r) == ["frequency_hz", "steady_time_s", "noise", "interval", "resolved_factor", "dem", "pbm", "note"]
    assert r["frequency_hz"] is c.frequency_hz and r["note"] == c.note
    assert r["noise"]["taus_s"] == list(c.noise_taus_s) and r["noise"]["f_max_hz"] == c.noise_f_max_hz
    assert set(r["interval"]) == {"block_s", "n_boot", "level", "seed", "method"}
    for f, d in c.dem.items():
        rd = r["dem"][f]
        assert list(rd) == [
            "n_entered",
            "n_recovered",
            "n_blocks",
            "recovered_fraction",
            "mean_residence_time_s",
            "floor_abs_H",
            "resolved",
            "abs_H",
            "vrr",
            "noise",
        ]
        assert rd["floor_abs_H"] == d.floor and rd["recovered_fraction"] == d.n_recovered / d.n_entered
        assert rd["vrr"]["value"] is d.vrr.estimate and rd["abs_H"]["high"] is d.abs_H.high
        assert [list(row) for row in rd["noise"]] == [["tau_s", "value", "low", "high", "uncorrected"]] * len(d.noise)
    for mode, m in c.pbm.items():
        rm = r["pbm"][mode]
        assert list(rm) == [
            "feeders",
            "windows_averaged",
            "n_judged",
            "n_inside",
            "inside_fraction",
            "worst",
            "worst_outside",
            "ensemble_check",
        ]
        assert rm["n_judged"] == sum(int(np.sum(c.dem[f].resolved)) for f in c.dem)
        assert rm["n_inside"] == sum(v is True for fv in m.feeders.values() for v in fv.inside)
        assert rm["worst"] == {
            "ratio_pbm_to_dem": m.worst.ratio_pbm_to_dem,
            "feeder": m.worst.feeder,
            "frequency_hz": m.worst.frequency_hz,
        }
        assert isinstance(rm["windows_averaged"], list) and len(rm["windows_averaged"]) == 2
        for f, fv in m.feeders.items():
            rf = rm["feeders"][f]
            assert list(rf) == ["mean_residence_time_s", "abs_H", "vrr", "inside", "noise"]
            assert rf["vrr"] is fv.vrr and rf["inside"] == list(fv.inside)
            for row, n in zip(rf["noise"], fv.noise):
                assert row == {
                    "tau_s": n.tau_s,
                    "vrr": n.vrr,
                    "dem": {"value": n.dem.estimate, "low": n.dem.low, "high": n.dem.high},
                    "inside": n.inside,
                    "ratio_to_dem": n.ratio_to_dem,
                }
        (row,) = rm["ensemble_check"]
        assert list(row) == [
            "sigma",
            "members",
            "from_s",
            "sd_time_domain",
            "sd_frequency_domain",
            "relative_difference",
            "ensemble_s",
        ]
    json_ready(r)  # nothing but JSON-able values (numpy arrays, floats, None) below the keys


def test_velocity_only_table_gives_one_mode(rng):
    table = make_table(
        t=[0.0, 5.0],
        x_edges=np.linspace(0, 0.3, 3),
        y_edges=np.array([-0.05, 0.05]),
        vx_pos=0.3 / 2 * 0.2,
        vx_neg=0.0,
        vy_pos=0.0,
        vy_neg=0.0,
    )
    particles = records(rng.gamma(2, 5.0, 1000), rng.gamma(2, 5.0, 1000), rng)
    c = vrr_comparison(
        table,
        PbmConfig(),
        0.0,
        DemSummary(pooled_rtd=spec(n_entered=2000, mean=10.0)),
        particles,
        frequencies=[0.01, 0.05],
        noise_taus_s=(0.0,),
        n_boot=100,
    )
    assert list(c.pbm) == ["velocity"] and list(c.record()["pbm"]) == ["velocity"]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"component": "C"}, "component must be one of"),
        ({"component": 3}, "component must be one of"),
        ({"pooled_spec": None}, "pooled RTD"),
        ({"pooled_spec": spec(window=(190.0, 194.0))}, "at least two blocks"),
        ({"frequencies": [-1.0]}, "frequencies must be"),
    ],
)
def test_bad_inputs_raise_config_error_naming_the_value(rng, kwargs, match):
    particles = records(rng.exponential(5.0, 200), rng.exponential(5.0, 200), rng)
    args = {"particles": particles, "pooled_spec": spec(), "frequencies": [0.01], "component": "A", **kwargs}
    with pytest.raises(ConfigError, match=match):
        dem_transfer(**args)


def test_cli_bad_path_one_line_exit_2(tmp_path, capsys):
    missing = tmp_path / "nope.h5"
    assert main(["study", "vrr", "--reference", str(missing), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0] and "Traceback" not in err[0]
