"""Post-processing on synthetic dumps with a known flow: exact tables, outflow, C_A, RSD, RTD.

The synthetic blender (L = 0.33 m, D = 0.1 m, 4 x 2 compartments, dumps every 0.5 s to
30 s): at every dump after t = 0 one A particle (y = +0.02) and one B particle (y = -0.02)
appear at the inlet. A particles cross the blender in R_A = 4 s, B particles in R_B = 6 s
(x = L (age + 0.25) / R, never on a compartment edge); each is seen once past the weir
(x = L + 0.01) at age R and is gone at the next dump. vx = 0.1 (i + 1) m/s in slice i,
vy = +0.02 (A) or -0.03 (B) m/s. The hold-up is 4 t until 4 s, 18 at 5 s and 20 from 6 s.
"""

import dataclasses
import math

import numpy as np
import pandas as pd
import pytest

from coupling.errors import DumpFormatError
from dem import phases
from dem.config import DemConfig, TablesConfig
from dem.dumps import TruncatedDumpWarning, format_snapshot
from dem.post import postprocess
from dem.summary import DemSummary
from tests.known_dumps import COLUMNS, DUMP_S, END_S, STEADY, D, L, R, config, write_synthetic


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    cfg = config()
    directory = tmp_path_factory.mktemp("synthetic")
    write_synthetic(directory, cfg)
    return cfg, postprocess(str(directory / "dump.*.txt"), cfg, STEADY, provenance={"input_hash": "test"})


def test_velocity_table_exact(synthetic):
    _, res = synthetic
    table = res.table
    np.testing.assert_allclose(table.t, [0, 5, 10, 15, 20, 25])
    np.testing.assert_allclose(table.x_edges, np.linspace(0, L, 5))
    np.testing.assert_allclose(table.y_edges, [-D / 2, 0, D / 2])
    for k in range(6):
        for i in range(4):
            if table.n_samples[k, i].min() == 0:
                continue
            np.testing.assert_allclose(table.vx_pos[k, i], 0.1 * (i + 1), rtol=1e-9)
    np.testing.assert_allclose(table.vx_neg, 0.0)
    # steady windows (t >= 10 s): 2 A and 3 B per slice in every snapshot
    np.testing.assert_allclose(table.vy_pos[2:, :, 1], 0.02, rtol=1e-9)
    np.testing.assert_allclose(table.vy_pos[2:, :, 0], 0.0)
    np.testing.assert_allclose(table.vy_neg[2:, :, 0], 0.03, rtol=1e-9)
    np.testing.assert_allclose(table.count_A[2:, :, 1], 2.0)
    np.testing.assert_allclose(table.count_B[2:, :, 0], 3.0)
    np.testing.assert_allclose(table.count_A[2:, :, 0], 0.0)
    # 10 snapshots per window, 11 in the last (it holds the end time)
    np.testing.assert_array_equal(table.n_samples[2:5, :, 1], 20)
    np.testing.assert_array_equal(table.n_samples[5, :, 1], 22)
    np.testing.assert_array_equal(table.n_samples[2:5, :, 0], 30)
    assert table.attrs["input_hash"] == "test"
    assert table.attrs["snapshots_per_window"] == [10, 10, 10, 10, 10, 11]


def test_velocity_means_are_ratios_of_sums(tmp_path):
    """3 particles at +1 m/s in one snapshot, 1 at -1 m/s in the next: vx_pos = 3/4, not 1/2."""
    # one 2-s window covered by the two dumps (a window longer than the dumps is refused)
    cfg = DemConfig(tables=TablesConfig(nx=4, ny=2, window_s=2.0, sample_interval_s=1.0, min_samples=1))
    dt = cfg.timestep_s
    rows1 = [(k, 1, 0.01, 0.01, 0, 1.0, 0, 0, 0.003) for k in (1, 2, 3)]
    rows2 = [(4, 1, 0.01, 0.01, 0, -1.0, 0, 0, 0.003)]
    for t, rows in ((1.0, rows1), (2.0, rows2)):
        step = int(round(t / dt))
        (tmp_path / f"dump.{step}.txt").write_bytes(format_snapshot(step, COLUMNS, np.array(rows)))
    res = postprocess(str(tmp_path / "dump.*.txt"), cfg)
    assert res.table.vx_pos[0, 0, 1] == pytest.approx(0.75)
    assert res.table.vx_neg[0, 0, 1] == pytest.approx(0.25)
    assert res.table.count_A[0, 0, 1] == pytest.approx(2.0)
    assert res.table.n_samples[0, 0, 1] == 4


def test_outflow_and_composition(synthetic):
    _, res = synthetic
    ts = res.timeseries
    np.testing.assert_allclose(ts["t_s"], np.arange(1, 31))
    out_a = np.where(ts["t_s"] >= 5, 2.0, 0.0)
    out_b = np.where(ts["t_s"] >= 7, 2.0, 0.0)
    np.testing.assert_allclose(ts["outflow_A_per_s"], out_a)
    np.testing.assert_allclose(ts["outflow_B_per_s"], out_b)
    np.testing.assert_allclose(ts["inflow_per_s"], 4.0)
    c_a = ts["C_A"].to_numpy()
    assert np.isnan(c_a[:4]).all()
    np.testing.assert_allclose(c_a[4:6], 1.0)
    np.testing.assert_allclose(c_a[6:], 0.5)


def test_holdup_and_steady_state(synthetic):
    _, res = synthetic
    ts = res.timeseries
    np.testing.assert_allclose(ts["holdup_A"][ts["t_s"] >= 5], 8)
    np.testing.assert_allclose(ts["holdup_B"][ts["t_s"] >= 7], 12)
    assert len(res.holdup) == 61
    s = res.summary
    assert s.steady_state_time_s == pytest.approx(10.0)
    assert s.steady_outflow_per_s == pytest.approx(4.0)
    assert s.steady_C_A == pytest.approx(0.5)


def test_rsd_and_floor(synthetic):
    _, res = synthetic
    floor = math.sqrt(0.1) / 0.4  # p = 0.4; 2 A (fraction 1) and 3 B (fraction 0) per slice
    np.testing.assert_allclose(res.timeseries["rsd_outlet"][res.timeseries["t_s"] >= 7], math.sqrt(2))
    np.testing.assert_allclose(res.timeseries["rsd_outlet_floor"][res.timeseries["t_s"] >= 7], floor)
    np.testing.assert_allclose(res.rsd_by_slice, math.sqrt(2))
    np.testing.assert_allclose(res.rsd_by_slice_floor, floor)
    assert res.summary.final_rsd_blender == pytest.approx(math.sqrt(8 * 0.25 / 7) / 0.5)
    assert res.summary.final_rsd_blender_floor == pytest.approx(floor)


def test_per_dump_counts_are_kept_and_the_outlets_read_off_them(synthetic):
    """Every compartment's particles at every dump are kept (what the steady quantities
    come from); the outlet's, at which the PBM's composition is sampled, are the same
    counts as the compartment sequences give, which stand in for them in older files."""
    from dem.post import DemResults

    cfg, res = synthetic
    assert res.snapshot_counts.shape == (len(res.holdup), 2, cfg.tables.nx, cfg.tables.ny)
    np.testing.assert_array_equal(
        res.snapshot_counts.sum(axis=(1, 2, 3)), res.holdup[["holdup_A", "holdup_B"]].sum(axis=1)
    )
    after = res.holdup["t_s"].to_numpy() > res.summary.steady_time
    outlet = res.steady_outlet_counts()  # (dumps, A and B, NY): 2 A on +y (column 1), 3 B on -y
    np.testing.assert_array_equal(outlet, [[[0, 2], [3, 0]]] * int(after.sum()))
    np.testing.assert_array_equal(res.sequences.counts()[after][:, -1], outlet.sum(axis=1))
    np.testing.assert_array_equal(
        res.sequences.counts((1,)) + res.sequences.counts((2,)), res.snapshot_counts.sum(axis=1)
    )
    entry = res.to_cache_entry({"input_hash": "test"})
    np.testing.assert_array_equal(DemResults.from_cache_entry(entry).snapshot_counts, res.snapshot_counts)
    older = dataclasses.replace(entry, arrays={k: v for k, v in entry.arrays.items() if k != "snapshot_counts"})
    np.testing.assert_array_equal(DemResults.from_cache_entry(older).steady_outlet_counts(), outlet)


def test_rtd(synthetic):
    _, res = synthetic
    s = res.summary
    assert s.rtd_tag_time_s == pytest.approx(10.0)
    assert s.rtd_tagged == 4  # entries at 10.5 and 11.0 s, one A and one B each
    assert s.rtd_recovered_fraction == 1.0 and s.rtd_recovered_ok
    assert s.mean_residence_time_s == pytest.approx(5.0)
    assert s.rtd_variance_s2 == pytest.approx(1.0, rel=1e-4)  # dump times are whole timesteps
    e = dict(zip(res.rtd["t_s"], res.rtd["E_per_s"]))
    assert e[4.5] == pytest.approx(0.5) and e[6.5] == pytest.approx(0.5)
    assert np.sum(res.rtd["E_per_s"]) * 1.0 == pytest.approx(1.0)


def test_accounting_closes(synthetic):
    s = synthetic[1].summary
    assert s.accounting["inserted"] == 120
    assert s.accounting["held"] == 20  # A entered after 26 s, B after 24 s
    assert s.accounting["discharged"] == 100
    assert s.accounting["lost"] == 0 and s.accounting["accounting_mismatch"] == 0
    assert s.accounting["exits_seen_past_weir"] == 100
    assert s.warnings == ()


def test_exits_never_seen_past_weir_use_disappearance(tmp_path):
    """Deleted by the outlet face between dumps: counted at the first dump without them."""
    cfg = config()
    write_synthetic(tmp_path, cfg, vanish_unseen=True)
    res = postprocess(str(tmp_path / "dump.*.txt"), cfg, STEADY)
    s = res.summary
    assert s.accounting["exits_seen_past_weir"] == 0
    assert s.accounting["exits_from_vanishing"] == s.accounting["discharged"] == 100
    assert s.accounting["lost"] == 0 and s.accounting["accounting_mismatch"] == 0
    assert s.mean_residence_time_s == pytest.approx(5.0)


def test_massflow_file_gives_exit_times_and_crosscheck(tmp_path):
    cfg = config()
    truth = write_synthetic(tmp_path, cfg, vanish_unseen=True, lose_id=33)
    # the solver's per-particle file: deleted 0.2 s before the dump that misses them
    lines = ["# ID time  diameter x y z u v w  (ex ey ez, color)"]
    for pid, (_ptype, _entry, exit_s) in sorted(truth.items()):
        if pid != 33 and np.isfinite(exit_s):
            lines.append(f"{pid}  {exit_s - 0.2:.4g}  0.003 0.331 0 0 0.1 0 0")
    half = len(lines) // 2
    (tmp_path / "discharge_A.txt.0").write_text("\n".join(lines[:half]) + "\n")
    (tmp_path / "discharge_A.txt.1").write_text("\n".join(lines[:1] + lines[half:]) + "\n")
    res = postprocess(
        str(tmp_path / "dump.*.txt"), cfg, STEADY, massflow_dir=tmp_path, solver_counters={"discharged": len(lines) - 1}
    )
    s = res.summary
    assert s.accounting["massflow_discharged"] == len(lines) - 1
    assert s.accounting["exits_from_massflow"] == len(lines) - 1
    assert s.accounting["discharge_crosscheck_diff"] == 0 and s.accounting["solver_discharge_diff"] == 0
    assert (
        s.accounting["lost"] == 1 and s.accounting["accounting_mismatch"] == 1
    )  # particle 33 left through a wall at 10 s
    assert any("accounting" in w for w in s.warnings)
    # exit times come from the file (0.2 s before the dump that misses them): 3.8 and 5.8 s
    assert s.mean_residence_time_s == pytest.approx(4.8, rel=1e-4)


def test_rtd_recovery_flag(tmp_path):
    cfg = config()
    write_synthetic(tmp_path, cfg, end_s=16.0)  # B tagged at 11.5-12 s leave at 17.5-18 s
    res = postprocess(str(tmp_path / "dump.*.txt"), cfg, rtd_tag_time_s=11.0)
    s = res.summary
    assert s.rtd_recovered_fraction == pytest.approx(0.5)
    assert not s.rtd_recovered_ok
    assert any("95" in w for w in s.warnings)


def test_no_snapshot_is_an_error(tmp_path):
    (tmp_path / "dump.0.txt").write_bytes(b"")
    with pytest.warns(TruncatedDumpWarning), pytest.raises(DumpFormatError, match="no complete snapshot"):
        postprocess(str(tmp_path / "dump.*.txt"), config())


def test_massflow_parts_of_a_resumed_run(tmp_path):
    """Records set aside before a resume (``.upto<step>``) and the resumed run's records are
    merged; an ID in both keeps the resumed run's record."""
    cfg = config()
    truth = write_synthetic(tmp_path, cfg, vanish_unseen=True)
    header = "# ID time  diameter x y z u v w  (ex ey ez, color)"
    rows = {
        pid: f"{pid}  {exit_s - 0.2:.4g}  0.003 0.331 0 0 0.1 0 0"
        for pid, (_, _, exit_s) in truth.items()
        if np.isfinite(exit_s)
    }
    early = [r for pid, r in rows.items() if truth[pid][2] <= 15.0]
    late = [r for pid, r in rows.items() if truth[pid][2] >= 14.0]  # 14-15 s listed in both parts
    (tmp_path / "discharge_A.txt.upto300000").write_text("\n".join([header, *early]) + "\n")
    (tmp_path / "discharge_A.txt").write_text("\n".join([header, *late]) + "\n")
    s = postprocess(str(tmp_path / "dump.*.txt"), cfg, STEADY, massflow_dir=tmp_path).summary
    assert s.accounting["massflow_duplicate_ids"] == len(early) + len(late) - len(rows) > 0
    assert s.accounting["massflow_discharged"] == len(rows)
    assert s.accounting["discharge_crosscheck_diff"] == 0 and s.accounting["lost"] == 0


def test_absurd_particle_id_is_refused_not_allocated(tmp_path):
    """An id of 9e12 (a corrupted digit) would make the per-id arrays 65 TiB."""
    cfg = config()
    step = int(round(1.0 / cfg.timestep_s))
    rows = [(1, 1, 0.01, 0.01, 0, 0.1, 0, 0, 0.003), (9e12, 2, 0.02, -0.01, 0, 0.1, 0, 0, 0.003)]
    (tmp_path / f"dump.{step}.txt").write_bytes(format_snapshot(step, COLUMNS, np.array(rows)))
    with pytest.raises(DumpFormatError, match=r"atom 2 \(column 'id'\): particle id 9000000000000 is implausible"):
        postprocess(str(tmp_path / "dump.*.txt"), cfg, STEADY)


def test_sparse_ids_within_the_bound_are_accepted(tmp_path):
    """Dumps from late in a long run: few particles, ids near a million."""
    cfg = config()
    step = int(round(5.0 / cfg.timestep_s))  # the end of the first 5-s window: the window is covered
    rows = [(999_000 + k, 1, 0.01 * k, 0.01, 0, 0.1, 0, 0, 0.003) for k in (1, 2, 3)]
    (tmp_path / f"dump.{step}.txt").write_bytes(format_snapshot(step, COLUMNS, np.array(rows)))
    res = postprocess(str(tmp_path / "dump.*.txt"), cfg, STEADY)
    assert res.summary.accounting["inserted"] == 3


def test_snapshot_time_beyond_any_run_is_refused(tmp_path):
    cfg = config()
    step = int(round(1e6 / cfg.timestep_s))  # 10**6 s: 10**6 one-second sampling intervals
    rows = [(1, 1, 0.01, 0.01, 0, 0.1, 0, 0, 0.003)]
    (tmp_path / f"dump.{step}.txt").write_bytes(format_snapshot(step, COLUMNS, np.array(rows)))
    with pytest.raises(DumpFormatError, match="beyond 100000 sampling intervals"):
        postprocess(str(tmp_path / "dump.*.txt"), cfg, STEADY)


def test_particle_moves_between_dumps_are_counted_exactly(synthetic):
    """Each A particle (j = 1) is seen twice in each axial slice and once past the weir, so
    its moves are: stay, forward, stay, forward, stay, forward, stay, out; B (j = 0, 6 s)
    the same with three sightings per slice. Nothing else appears."""
    cfg, res = synthetic
    counts = res.transitions.sum(axis=0)
    n_states = 4 * 2 + 1
    assert res.transitions.shape[1:] == (n_states, n_states)
    out = n_states - 1
    records = res.particles
    entry = {ptype: records.loc[records["component"] == ptype, "entry_t_s"].to_numpy() for ptype in (1, 2)}
    n_a, n_b = ((entry[ptype] + R[ptype] <= END_S + 1e-3).sum() for ptype in (1, 2))
    for i in range(4):
        a, b = i * 2 + 1, i * 2
        a_next, b_next = (out, out) if i == 3 else (a + 2, b + 2)
        # the move out of slice i is seen at age (i + 1) R / 4, if the run lasts that long
        for state, nxt, ptype in ((a, a_next, 1), (b, b_next, 2)):
            made = int((entry[ptype] + (i + 1) * R[ptype] / 4 <= END_S + 1e-3).sum())
            assert counts[state, nxt] == made
        assert counts[a, a] >= n_a and counts[b, b] >= 2 * n_b
    allowed = np.zeros_like(counts, bool)
    for c in range(8):
        allowed[c, c] = True
        allowed[c, c + 2 if c < 6 else out] = True
    assert counts[~allowed].sum() == 0
    assert res.table.has_rates and res.table.rate_x_pos.shape == (res.table.n_windows, 4, 2)


def test_moves_out_of_the_blender_between_dumps_come_from_the_discharges(tmp_path):
    """Particles deleted before any dump sees them past the weir leave from the last slice
    all the same: the same counts as when they are seen past the weir."""
    cfg = config()
    write_synthetic(tmp_path / "seen", cfg)
    write_synthetic(tmp_path / "unseen", cfg, vanish_unseen=True)
    seen = postprocess(str(tmp_path / "seen" / "dump.*.txt"), cfg, STEADY)
    unseen = postprocess(str(tmp_path / "unseen" / "dump.*.txt"), cfg, STEADY)
    assert np.array_equal(seen.transitions.sum(axis=0)[:, -1], unseen.transitions.sum(axis=0)[:, -1])
    assert unseen.transitions.sum(axis=0)[7, -1] > 0


def test_particle_records_match_the_synthetic_truth(tmp_path):
    cfg = config()
    truth = write_synthetic(tmp_path, cfg)
    records = postprocess(str(tmp_path / "dump.*.txt"), cfg, STEADY).particles.set_index("id")
    assert len(records) == len(truth)
    for pid, (ptype, entry, exit_s) in truth.items():
        row = records.loc[pid]
        assert row["component"] == ptype
        assert row["entry_t_s"] == pytest.approx(entry, abs=1e-4)
        assert row["entry_y_m"] == pytest.approx(0.02 if ptype == 1 else -0.02)
        assert row["diameter_m"] == pytest.approx(0.006)  # the dumps' radius 0.003
        if math.isnan(exit_s):
            assert math.isnan(row["exit_t_s"]) and row["exit_cell"] == -1
        else:
            assert row["exit_t_s"] == pytest.approx(exit_s, abs=1e-4)
            assert row["exit_cell"] == (7 if ptype == 1 else 6)


def test_pooled_rtd_and_steady_intervals(tmp_path):
    """80 s of the synthetic flow: hold-up 20, outflow 4 /s, so Little's law gives 5 s and
    the horizon is 25 s; every particle entering in (10, 55] s is a tracer, half A (4 s),
    half B (6 s): mean 5 s, variance 1 s^2, all recovered."""
    cfg = config()
    write_synthetic(tmp_path, cfg, end_s=80.0)
    s = postprocess(str(tmp_path / "dump.*.txt"), cfg, STEADY).summary
    steady = s.steady
    assert steady["holdup"]["value"] == pytest.approx(20.0)
    assert steady["holdup"]["low"] <= 20.0 <= steady["holdup"]["high"]
    assert steady["outflow_per_s"]["value"] == pytest.approx(4.0, rel=0.02)
    assert steady["little_mean_residence_time_s"]["value"] == pytest.approx(5.0, rel=0.02)
    assert steady["C_A"]["low"] < 0.5 < steady["C_A"]["high"]
    assert sum(steady["holdup_by_slice"]["value"]) == pytest.approx(20.0)
    pooled = s.pooled_rtd
    assert pooled.horizon_s == 25.0
    assert pooled.entry_window_s == pytest.approx([s.steady_state_time_s, 55.0])
    assert pooled.recovered_fraction.value == 1.0
    assert pooled.mean_residence_time_s.value == pytest.approx(5.0)
    assert pooled.rtd_variance_s2.value == pytest.approx(1.0)
    assert abs(pooled.n_entered - 2 * (55.0 - s.steady_state_time_s) / DUMP_S) <= 2  # dumps on the edges


def test_a_run_too_short_for_the_horizon_says_so(synthetic):
    _, res = synthetic
    assert res.summary.pooled_rtd.n_entered == 0
    assert "no pooled RTD" in res.summary.pooled_rtd.note


def _assert_same(a, b, where="results"):
    """Equal to the last bit (NaN equal to NaN), through dataclasses, dicts, lists and frames."""
    import dataclasses

    import pandas as pd

    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            _assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, pd.DataFrame):
        pd.testing.assert_frame_equal(a, b, check_exact=True, obj=where)
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a.keys() - {"wall_time_s"}:  # how long a fit took is no result
            _assert_same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, (list, tuple)) and not (a and isinstance(a[0], (int, float))):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{where}[{i}]")
    elif a is None or isinstance(a, (str, bool)):
        assert a == b, where
    else:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=where)


def test_postprocessing_read_in_parts_gives_the_one_pass_results(tmp_path):
    """Dumps fed to a Postprocessor in three parts, the results taken after each: every taking
    equals postprocess of the dumps up to then in one pass, and taking leaves it as
    it was."""
    from dem.dumps import dump_paths
    from dem.post import Postprocessor

    cfg = config()
    write_synthetic(tmp_path, cfg)
    files = dump_paths(str(tmp_path / "dump.*.txt"))
    post = Postprocessor(cfg)
    for part in np.array_split(np.arange(len(files)), 3):
        post.add([files[i] for i in part])
        upto = files[: part[-1] + 1]
        streamed = post.results(STEADY, provenance={"input_hash": "test"})
        once = postprocess(upto, cfg, STEADY, provenance={"input_hash": "test"})
        _assert_same(streamed, once)
    assert streamed.summary.t_end_s == pytest.approx(END_S)
    with pytest.raises(DumpFormatError, match="does not follow the step"):
        post.add(files[-1:])


def test_refit_phases_rewrites_a_results_file_from_its_sequences(synthetic, tmp_path, capsys):
    """`pbmdem dem refit-phases`: the phase model fitted again to the file's own sequences
    (no dumps), the file rewritten whole, everything else as it was."""
    from coupling.cache import load_entry, save_entry
    from dem.post import DemResults
    from workflows.cli.main import main

    _, res = synthetic
    path = tmp_path / "dem-test.h5"
    stripped = dataclasses.replace(res, table=res.table.replace(phases=None))
    save_entry(path, stripped.to_cache_entry({"key": "test"}))
    assert not DemResults.from_cache_entry(load_entry(path)).table.has_phases
    assert main(["dem", "refit-phases", str(path)]) == 0
    # K as the grid's choice makes it on these sequences (their flow is deterministic, and
    # the held-out half does gain from more phases)
    k, _gain = phases.choose_phases(res.sequences, res.summary.steady_time)
    assert f"phase model K = {k} " in capsys.readouterr().out
    back = DemResults.from_cache_entry(load_entry(path))
    assert back.table.has_phases and back.table.phases.n_phases == k
    assert back.summary.record()["phase_fit"]["moving_phases"] == k
    assert back.summary.record()["phase_fit"]["observed_grid"] == [back.table.nx, 1]
    np.testing.assert_array_equal(back.snapshot_counts, res.snapshot_counts)
    pd.testing.assert_frame_equal(back.particles, res.particles)


def test_a_refit_that_cannot_fit_leaves_the_file_as_it_was(synthetic, tmp_path, capsys):
    from coupling.cache import save_entry
    from workflows.cli.main import main

    _, res = synthetic
    unsteady = dataclasses.replace(res, summary=dataclasses.replace(res.summary, steady_state_time_s=None))
    path = save_entry(tmp_path / "dem-test.h5", unsteady.to_cache_entry({"key": "test"}))
    before = path.read_bytes()
    assert main(["dem", "refit-phases", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "steady state" in err[0], err
    assert path.read_bytes() == before


def test_recompute_steady_rewrites_a_results_file_from_its_sequences(tmp_path, capsys):
    """`pbmdem dem recompute-steady` on a file made before the per-dump counts were kept
    and with its steady quantities gone: the counts read off the sequences give back the
    post-processing's steady quantities and pooled RTD exactly, batches and all."""
    from coupling.cache import load_entry, save_entry
    from dem.post import DemResults
    from workflows.cli.main import main

    cfg = config()
    write_synthetic(tmp_path, cfg, end_s=80.0)
    res = postprocess(str(tmp_path / "dump.*.txt"), cfg, STEADY)
    assert res.summary.steady["batch_s"] == 10.0  # two residence times of 5 s, in 5-s blocks
    record = res.summary.record()
    record["steady"], record["pooled_rtd"] = {}, {}
    older = dataclasses.replace(res, snapshot_counts=None, summary=DemSummary.from_record(record))
    path = save_entry(tmp_path / "dem-test.h5", older.to_cache_entry({"key": "test"}))
    assert main(["dem", "recompute-steady", str(path)]) == 0
    assert "steady hold-up 20 [" in capsys.readouterr().out
    back = DemResults.from_cache_entry(load_entry(path))
    _assert_same(back.summary.steady, res.summary.steady)
    _assert_same(back.summary.pooled_rtd, res.summary.pooled_rtd)
    assert back.snapshot_counts is None
    pd.testing.assert_frame_equal(back.particles, res.particles)


def test_recompute_steady_without_counts_or_sequences_leaves_the_file_as_it_was(synthetic, tmp_path, capsys):
    from coupling.cache import save_entry
    from workflows.cli.main import main

    _, res = synthetic
    bare = dataclasses.replace(res, snapshot_counts=None, sequences=None)
    path = save_entry(tmp_path / "dem-test.h5", bare.to_cache_entry({"key": "test"}))
    before = path.read_bytes()
    assert main(["dem", "recompute-steady", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "neither compartment counts nor" in err[0], err
    assert path.read_bytes() == before


def test_results_with_an_earlier_versions_intervals_are_brought_up_to_date_on_reading(tmp_path):
    """Steady quantities without recorded batches (an earlier version's 5-s bootstrap) are
    computed again when the results are read, from the counts or the sequences; with
    neither they stay, and the results warn that their intervals are too narrow."""
    from dem.post import DemResults

    cfg = config()
    write_synthetic(tmp_path, cfg, end_s=80.0)
    res = postprocess(str(tmp_path / "dump.*.txt"), cfg, STEADY)
    record = res.summary.record()
    old = {k: v for k, v in record["steady"].items() if k not in ("batch_s", "degrees_of_freedom")}
    old["holdup"] = {"value": 20.0, "low": 19.99, "high": 20.01}
    record["steady"] = old
    older = dataclasses.replace(res, snapshot_counts=None, summary=DemSummary.from_record(record))
    read = DemResults.from_cache_entry(older.to_cache_entry({"key": "test"}))
    _assert_same(read.summary.steady, res.summary.steady)
    assert not any("earlier version" in w for w in read.summary.warnings)
    bare = dataclasses.replace(older, sequences=None)
    kept = DemResults.from_cache_entry(bare.to_cache_entry({"key": "test"}))
    assert kept.summary.steady["holdup"]["low"] == 19.99
    assert any("earlier version's, over 5-s blocks" in w for w in kept.summary.warnings)
    # a pooled RTD whose intervals were not expanded for their blocks (no block count
    # recorded) is computed again too, with current steady quantities beside it
    record = res.summary.record()
    plain = {k: v for k, v in record["pooled_rtd"].items() if k != "n_blocks"}
    plain["mean_residence_time_s"] = {**plain["mean_residence_time_s"], "low": 0.0}
    record["pooled_rtd"] = plain
    unexpanded = dataclasses.replace(res, summary=DemSummary.from_record(record))
    again = DemResults.from_cache_entry(unexpanded.to_cache_entry({"key": "test"}))
    _assert_same(again.summary.pooled_rtd, res.summary.pooled_rtd)
    assert again.summary.pooled_rtd.n_blocks == res.summary.pooled_rtd.n_blocks >= 2


def test_a_refit_of_sequences_that_jump_far_says_it_will_be_slow():
    """Every particle's second run five slices on (the issue's pathological refit, 6 times a
    clean one): a note before the fit; the shipped run's own moves give none."""
    from pathlib import Path

    from coupling.cache import load_entry
    from dem.post import DemResults, far_move_share, slow_refit_note

    shipped = Path(__file__).resolve().parents[2] / "workflows/reference/validation/dem-dccc770e3c39f48c.h5"
    results = DemResults.from_cache_entry(load_entry(shipped))
    seq = results.sequences
    assert slow_refit_note(results) is None and far_move_share(seq) < 1e-3
    second = seq.run_offsets[:-1] + 1
    second = second[second < seq.run_offsets[1:]]
    second = second[seq.run_state[second] < seq.n_cells]
    state = seq.run_state.copy()
    i, j = np.divmod(state[second].astype(np.int64), seq.ny)
    state[second] = (np.minimum(i + 5, seq.nx - 1) * seq.ny + j).astype(state.dtype)
    jumping = dataclasses.replace(results, sequences=dataclasses.replace(seq, run_state=state))
    note = slow_refit_note(jumping)
    assert note is not None and "\n" not in note and far_move_share(jumping.sequences) > 1e-2
