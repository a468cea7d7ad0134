"""The transport targets read off a comparison's summary: the phases mode is the target,
the other modes are information, a missing phases column fails."""

import json

import pytest

from workflows.analysis.targets import check


def row(key, dem, low, high, values):
    out = {"key": key, "quantity": key, "dem": dem, "dem_ci_low": low, "dem_ci_high": high}
    for mode, v in values.items():
        out[f"pbm_{mode}"] = v
        out[f"inside_{mode}"] = low <= v <= high
    return out


def summary(phases_variance: float, with_phases: bool = True):
    modes = lambda p, m: {"phases": p, "measured": m} if with_phases else {"measured": m}  # noqa: E731
    return {
        "agreement": [
            row("mean_residence_time_s", 21.2, 20.7, 21.7, modes(21.5, 22.0)),
            row("rtd_variance_s2", 261.0, 244.0, 277.0, modes(phases_variance, 200.0)),
            row("holdup", 1590.0, 1582.0, 1598.0, modes(1590.0, 1600.0)),
            row("holdup_slice_1", 200.0, 190.0, 210.0, modes(205.0, 230.0)),
        ],
        "dem_summary": {
            "pooled_rtd": {
                "horizon_s": 106.0,
                "entry_window_s": [55.0, 200.0],
                "n_entered": 12000,
                "recovered_fraction": {"value": 0.99},
            },
            "phase_fit": {"wall_time_s": 20.0},
        },
        "provenance": {"dem_wall_time_s": 1000.0, "dem_postprocess_time_s": 40.0},
    }


def verdicts(s):
    return {name: passed for name, _numbers, passed in check(s)}


def test_phases_mode_is_the_target_and_the_others_inform():
    good = verdicts(summary(258.0))
    assert good["phases: rtd_variance_s2 inside the DEM interval"] is True
    assert good["measured: rtd_variance_s2 inside the DEM interval"] is None  # information
    assert good["phases: every slice's hold-up within 10 % of the DEM"] is True
    assert good["phase fit <= 5 % of the DEM wall time"] is True
    bad = verdicts(summary(172.0))
    assert bad["phases: rtd_variance_s2 inside the DEM interval"] is False


def test_a_summary_without_the_phases_mode_fails():
    out = verdicts(summary(258.0, with_phases=False))
    assert out["phases: the PBM ran in this mode"] is False


def _noise(tau, vrr, low, high):
    return {"tau_s": tau, "vrr": vrr, "inside": low <= vrr <= high, "dem": {"value": vrr, "low": low, "high": high}}


def test_the_vrr_target_is_feeder_a_white_5_and_20_s_the_rest_informs():
    s = summary(258.0)
    a = [
        _noise(0.0, 40.0, 38.0, 42.0),
        _noise(1.0, 99.0, 1.0, 2.0),
        _noise(5.0, 4.5, 4.3, 4.7),
        _noise(20.0, 1.9, 1.8, 2.0),
    ]
    b = [_noise(0.0, 99.0, 38.0, 42.0)]
    s["vrr"] = {"pbm": {"phases": {"feeders": {"A": {"noise": a}, "B": {"noise": b}}}}}
    out = verdicts(s)
    assert out["phases: VRR of feeder A inside the DEM intervals"] is True  # tau 1 s is outside but not a target
    assert out["phases: VRR of feeder A inside the DEM intervals (information)"] is None
    assert out["phases: VRR of feeder B inside the DEM intervals (information)"] is None
    a[2] = _noise(5.0, 4.9, 4.3, 4.7)
    assert verdicts(s)["phases: VRR of feeder A inside the DEM intervals"] is False
    s["agreement"].append(row("rsd_outlet", 0.315, 0.306, 0.323, {"phases": 0.319, "measured": 0.2}))
    assert verdicts(s)["phases: rsd_outlet inside the DEM interval"] is None  # composition informs


OUT_OF_SAMPLE = (
    "phases: out of sample (refitted on the first half), the second half's mean and variance inside its intervals"
)


def test_the_out_of_sample_target_needs_both_moments_inside_and_fails_without_the_check():
    s = summary(258.0)
    assert verdicts(s)[OUT_OF_SAMPLE] is False  # no memory check in the summary
    held = {
        "dem_mean_s": {"value": 20.7, "low": 20.2, "high": 21.1},
        "dem_variance_s2": {"value": 250.0, "low": 218.0, "high": 288.0},
        "pbm_mean_s": 21.07,
        "pbm_variance_s2": 258.0,
        "mean_inside": True,
        "variance_inside": True,
    }
    s["memory"] = {"out_of_sample": held}
    assert verdicts(s)[OUT_OF_SAMPLE] is True
    s["memory"] = {"out_of_sample": {**held, "pbm_mean_s": 21.3, "mean_inside": False}}
    assert verdicts(s)[OUT_OF_SAMPLE] is False
    assert verdicts(summary(258.0, with_phases=False)).get(OUT_OF_SAMPLE) is None  # no phases mode, no line


@pytest.mark.parametrize(
    ("text", "what"),
    [
        # the reproducers
        ("[1,2]", "the summary is [1, 2]; a JSON object is valid"),
        ("NaN", "the summary is NaN; a JSON object is valid"),
        ('{"agreement": 5}', "'agreement' is 5; a list of rows (objects) is valid"),
        ('{"agreement": [1, "x"]}', "agreement[0] is 1; an object is valid"),
        ('{"agreement": [{"quantity": null}]}', "agreement[0].quantity is null; a text is valid"),
        # variants
        ("", "not a readable summary (Expecting value"),
        ('{"agreement": [{"quantity": "holdup"}]}', "agreement[0].key is null; a text is valid"),
        ('{"agreement": [{"key": 3}]}', "agreement[0].key is 3; a text is valid"),
        ('{"agreement": [{"key": "holdup", "dem": "1590"}]}', 'agreement[0].dem is "1590"; a number or null is valid'),
        (
            '{"agreement": [{"key": "holdup", "pbm_phases": true}]}',
            "agreement[0].pbm_phases is true; a number or null is valid",
        ),
        (
            '{"agreement": [{"key": "holdup", "inside_phases": 1}]}',
            "agreement[0].inside_phases is 1; true, false or null",
        ),
        ('{"dem_summary": [1]}', "'dem_summary' is [1]; an object is valid"),
        ('{"provenance": "x"}', "'provenance' is \"x\"; an object is valid"),
        ("null", "the summary is null; a JSON object is valid"),
        (
            '{"agreement": [{"key": "holdup", "pbm_phases": 1}]}',
            "not a summary of pbmdem compare (missing 'quantity')",
        ),
        (
            '{"agreement": [{"key": "x", "pbm_phases": 1}], "vrr": {"pbm": {"phases": {"feeders": {"A": '
            '{"noise": [{"tau_s": 0}]}}}}}}',
            "not a summary of pbmdem compare (missing 'vrr')",
        ),
        (
            '{"agreement": [{"key": "holdup_slice_0", "quantity": "q", "dem": 0, "pbm_phases": 1}]}',
            "not a summary of pbmdem compare (ZeroDivisionError: division by zero)",
        ),
    ],
)
def test_a_malformed_summary_is_one_line_naming_the_file(tmp_path, capsys, text, what):
    from workflows.cli.main import main

    path = tmp_path / "summary.json"
    path.write_text(text)
    assert main(["targets", str(path)]) == 2
    captured = capsys.readouterr()
    assert captured.err.startswith(f"pbmdem: error: {path}: ") and captured.err.count("\n") == 1
    assert what in captured.err
    assert captured.out == ""  # nothing printed for a file that cannot be judged
    assert path.read_text() == text


def test_a_well_formed_summary_still_reads(tmp_path, capsys):
    from workflows.cli.main import main

    path = tmp_path / "summary.json"
    path.write_text(json.dumps(summary(258.0)))
    assert main(["targets", str(path)]) in (0, 1)
    assert "phases: rtd_variance_s2 inside the DEM interval" in capsys.readouterr().out
