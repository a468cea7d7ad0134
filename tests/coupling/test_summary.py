"""The shared summary contract: the fields both sides report, and the PBM's record."""

import math
from dataclasses import fields

import numpy as np

from coupling.summary import SHARED_FIELDS, ProcessSummary
from dem.summary import RECORD_SCALARS, DemSummary
from pbm import PbmConfig, simulate, synthetic_table
from pbm.summary import RECORD_KEYS, PbmSummary


def _shared_of(cls) -> set[str]:
    return {f.name for f in fields(cls)} & set(SHARED_FIELDS)


def test_both_sides_carry_every_shared_field():
    assert _shared_of(DemSummary) == _shared_of(PbmSummary) == set(SHARED_FIELDS)
    assert set(SHARED_FIELDS) <= set(RECORD_SCALARS) and set(SHARED_FIELDS) <= set(RECORD_KEYS)
    assert len(SHARED_FIELDS) == 9


def test_steady_time_reads_either_sides_never_steady():
    assert DemSummary(steady_state_time_s=math.nan).steady_time is None
    assert ProcessSummary(steady_state_time_s=None).steady_time is None
    assert DemSummary(steady_state_time_s=12.5).steady_time == 12.5


def test_pbm_record_is_the_old_dict():
    table = synthetic_table(nx=4, ny=3, n_windows=8)
    result = simulate(table, PbmConfig(duration_s=40.0))
    s, rec = result.summary, result.summary.record()
    expected = {
        "mean_residence_time_s": s.mean_residence_time_s,
        "rtd_variance_s2": s.rtd_variance_s2,
        "rtd_recovered_fraction": s.rtd_recovered_fraction,
        "steady_outflow_per_s": s.steady_outflow_per_s,
        "steady_C_A": s.steady_C_A,
        "final_rsd_outlet": float(result.rsd_outlet[-1]),
        "final_rsd_blender": float(result.rsd_blender[-1]),
        "final_rsd_by_slice": [float(v) for v in result.rsd_by_slice_final],
        "holdup_final": float(result.counts[-1].sum(axis=(1, 2)).sum()),
        "holdup_final_A": float(result.holdup_A[-1]),
        "holdup_final_B": float(result.holdup_B[-1]),
        "steady_state_time_s": s.steady_state_time_s,
        "rtd_pulse_s": float(result.rtd_pulse_s),
        "rtd_pulse_rule": s.rtd_pulse_rule,
        "filled_compartment_windows": s.filled_compartment_windows,
        "nx": 4,
        "ny": 3,
        "duration_s": 40.0,
        "method": PbmConfig().method,
        "rate_law": "table",
        "fill_law_form": None,
        "fill_exponents": None,
        "wall_time_s": s.wall_time_s,
    }
    assert list(rec) == list(expected)  # the order summary.json has always had
    np.testing.assert_equal(rec, expected)  # NaN equal to NaN, values exact
    assert [type(v) for v in rec.values()] == [type(v) for v in expected.values()]
    assert isinstance(rec["final_rsd_by_slice"], list)


def test_pbm_record_gives_nested_lists_back():
    base = simulate(synthetic_table(nx=2, ny=1, n_windows=2), PbmConfig(duration_s=5.0)).summary
    fill = PbmSummary(**{**{f.name: getattr(base, f.name) for f in fields(base)}, "fill_exponents": ((1.5, 0.0),) * 2})
    assert fill.record()["fill_exponents"] == [[1.5, 0.0], [1.5, 0.0]]


def test_dem_record_round_trips_in_order():
    record = {name: i for i, name in enumerate(RECORD_SCALARS)}
    record.update({"inserted": 10, "steady": {}, "pooled_rtd": None, "warnings": ["w"], "wall_time_s": 3.0})
    back = DemSummary.from_record(record).record()
    assert back == record
    assert list(back)[: len(RECORD_SCALARS)] == list(RECORD_SCALARS)
