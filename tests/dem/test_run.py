"""Running LIGGGHTS: the supervised solver process (any command, no solver needed) and
the real solver (marked ``liggghts``): smoke preset under ``mpirun -np 2``, post-processing
with the accounting checked against the solver's own counters, reuse without starting
LIGGGHTS or rebuilding the deck, loud failures, and an interrupted run resumed from its
restart file.

One smoke run is shared by the module (it is the expensive part: about 1.5 min on 2 free
cores); the resume test uses a 2 s variant on one rank.
"""

import os
import time
from pathlib import Path

import numpy as np
import pytest

from coupling.cache import load_entry
from coupling.errors import SolverNotFoundError, SolverRunError
from coupling.tables import read_table
from dem import deck
from dem.liggghts import run_solver
from dem.liggghts_log import ThermoParser
from dem.post import postprocess
from dem.run import prepare_run, read_status, run_dem, run_key, solver_command
from tests.known_dumps import variant
from workflows.cli.main import main
from workflows.config import load_preset

liggghts = pytest.mark.liggghts


@pytest.fixture(scope="module")
def smoke(smoke_runs_root):
    root = smoke_runs_root  # one real smoke run per session (conftest), reused here
    config = load_preset("smoke")
    assert config.dem.run.np == 2  # the preset runs under mpirun -np 2
    record = run_dem(prepare_run(config.dem), runs_root=root, progress=False)
    results = postprocess(
        record.dump_glob,
        config.dem,
        config.steady_state,
        massflow_dir=record.massflow_dir,
        solver_counters=record.solver_counters,
    )
    return config, root, record, results


@liggghts
def test_smoke_run_completes_under_mpi(smoke):
    config, root, record, _ = smoke
    assert record.state == "completed"
    assert record.command[:2] == ["mpirun", "--allow-run-as-root"] and "2" in record.command
    assert "3.8.0" in record.liggghts_version
    status = read_status(record.run_dir)
    assert status["state"] == "completed" and status["wall_time_s"] > 0 and status["finished"]
    assert (record.run_dir / "log.liggghts").stat().st_size > 0
    assert "Step" in (record.run_dir / "solver.out").read_text()
    # MPI splits the discharge files per rank
    assert list(record.run_dir.glob("discharge_A.txt.*"))


@liggghts
def test_smoke_accounting_and_crosscheck(smoke):
    _, _, record, results = smoke
    s = results.summary
    assert s.accounting["inserted"] > 0 and s.accounting["discharged"] > 0, (
        "smoke preset: particles must reach the outlet"
    )
    assert s.accounting["lost"] == 0, s.warnings
    assert s.accounting["accounting_mismatch"] == 0  # inserted = held + discharged
    assert s.accounting["massflow_unseen_in_dumps"] == 0
    assert s.accounting["discharge_crosscheck_diff"] == 0  # our exits vs the massflow files, same instant
    assert_thermo_counters_agree(s)


def assert_thermo_counters_agree(s):
    """Thermo counters (f_ins*[1], f_out*[2], atoms) against the dumps, when they were taken at
    the last dump's step; otherwise the results must say why they were not compared."""
    if s.accounting["solver_step"] != s.last_dump_step:
        assert any("not compared" in w for w in s.warnings)
        return
    assert s.accounting["solver_discharge_diff"] == 0  # vs the thermo counters f_outA[2] + f_outB[2]
    assert s.accounting["solver_inserted_diff"] == 0  # vs f_insA[1] + f_insB[1]
    assert s.accounting["solver_atoms"] == s.accounting["held"] + s.accounting["discharged_pending_deletion"]


@liggghts
def test_smoke_tables_have_data_in_every_window(smoke):
    config, _, _, results = smoke
    table = results.table
    assert table.n_windows == int(np.ceil(config.dem.operation.duration_s / config.dem.tables.window_s))
    assert (table.n_samples.sum(axis=(1, 2)) > 0).all()
    assert np.isfinite(results.timeseries["holdup_A"]).all()
    assert results.timeseries["outflow_A_per_s"].sum() > 0 and results.timeseries["outflow_B_per_s"].sum() > 0


@liggghts
def test_second_request_reuses_without_liggghts(smoke, monkeypatch):
    config, root, record, _ = smoke
    status_mtime = (record.run_dir / "status.json").stat().st_mtime_ns
    out_mtime = (record.run_dir / "solver.out").stat().st_mtime_ns
    inputs = prepare_run(config.dem)
    assert inputs.key == record.key == run_key(inputs.files, inputs.liggghts_version)
    assert inputs.liggghts_version == record.liggghts_version

    def asked_again(*args, **kwargs):
        raise AssertionError("run_dem asked for what prepare_run computed")

    # the deck and the version are computed once, by prepare_run
    with monkeypatch.context() as patch:
        patch.setattr("dem.run.liggghts_version", asked_again)
        patch.setattr("dem.deck.build_deck", asked_again)
        again = run_dem(inputs, runs_root=root, progress=False)
    assert again.reused and again.key == record.key
    # even with no solver installed at all, the completed run of the same deck is found
    gone = prepare_run(variant(config, run={"liggghts": "no-such-liggghts-binary"}).dem)
    assert gone.key is None and gone.liggghts_version is None and gone.deck_hash == inputs.deck_hash
    again = run_dem(gone, runs_root=root, progress=False)
    assert again.reused and again.run_dir == record.run_dir
    assert (record.run_dir / "status.json").stat().st_mtime_ns == status_mtime
    assert (record.run_dir / "solver.out").stat().st_mtime_ns == out_mtime


@liggghts
def test_cli_run_writes_cache_then_reuses_it(smoke, tmp_path, capsys):
    _, root, record, _ = smoke
    cache_dir = tmp_path / "cache"
    argv = ["dem", "run", "--preset", "smoke", "--runs-dir", str(root), "--cache-dir", str(cache_dir), "--no-progress"]
    assert main(argv) == 0
    out = capsys.readouterr()
    (cache_file,) = cache_dir.glob("dem-*.h5")
    assert str(cache_file) in out.out
    entry = load_entry(cache_file)
    provenance = entry.provenance
    assert provenance["run_key"] == record.key and provenance["deck_hash"] == read_status(record.run_dir)["deck_hash"]
    assert provenance["liggghts_version"] == record.liggghts_version and "config_toml" in provenance
    assert entry.table.attrs["input_hash"] == entry.key
    mtime = cache_file.stat().st_mtime_ns
    assert main(argv) == 0
    assert "reused from the cache" in capsys.readouterr().err
    assert cache_file.stat().st_mtime_ns == mtime
    # a corrupt cache file is rebuilt from the (completed) run, not trusted
    cache_file.write_bytes(b"garbage")
    assert main(argv) == 0
    assert "not usable, rebuilding" in capsys.readouterr().err
    load_entry(cache_file, key=entry.key)


@liggghts
def test_cli_post_from_dumps(smoke, tmp_path, capsys):
    _, _, record, results = smoke
    out = tmp_path / "tables.h5"
    assert main(["dem", "post", "--preset", "smoke", "--dumps", record.dump_glob, "--out-file", str(out)]) == 0
    table = read_table(out)
    np.testing.assert_allclose(table.vx_pos, results.table.vx_pos)
    assert load_entry(out).summary["discharge_crosscheck_diff"] == 0  # discharge files found beside dumps/


@liggghts
def test_error_line_raises_with_log_tail(tmp_path):
    # a real LIGGGHTS error: it prints its banner, then rejects the command line
    config = variant(load_preset("smoke"), run={"liggghts": "liggghts -echo bogus", "np": 1})
    inputs = prepare_run(config.dem)
    with pytest.raises(SolverRunError, match="Illegal echo command") as info:
        run_dem(inputs, runs_root=tmp_path, progress=False)
    assert info.value.run_dir is not None and "ERROR" in info.value.log_tail
    assert read_status(info.value.run_dir)["state"] == "crashed"
    # a crashed run is never served as a result: a new request starts it again (and fails again)
    with pytest.raises(SolverRunError):
        run_dem(inputs, runs_root=tmp_path, progress=False)


def test_missing_solver_or_launcher(tmp_path):
    config = variant(load_preset("smoke"), run={"liggghts": "no-such-liggghts-binary"})
    inputs = prepare_run(config.dem)  # no solver is not an error until a run must start
    assert inputs.key is None and inputs.files == deck.build_deck(config.dem)
    with pytest.raises(SolverNotFoundError, match="no-such-liggghts-binary.*apt-get install liggghts openmpi-bin"):
        run_dem(inputs, runs_root=tmp_path, progress=False)
    assert not any(tmp_path.iterdir())
    config = variant(load_preset("smoke"), run={"launcher": "no-such-mpirun -np {np}", "np": 2})
    with pytest.raises(SolverNotFoundError, match="no-such-mpirun.*make setup"):
        solver_command(config.dem.run)


@liggghts
def test_interrupt_then_resume(tmp_path):
    """Ctrl-C after the first restart file: the solver group is terminated, the run marked
    interrupted; --resume continues from the restart and the result is complete and sound."""
    # 1-s velocity windows: 2 s of dumps cannot cover a 5-s window (refused by the post-processing)
    config = variant(
        load_preset("smoke"),
        operation={"duration_s": 2.0},
        numerics={"restart_interval_s": 0.5},
        run={"np": 1},
        tables={"window_s": 1.0},
    )
    seen = {}

    def interrupt_after_restart(line):
        # LIGGGHTS writes a step's restart before that step's thermo row: a thermo row at a
        # step >= the restart's means the restart file is complete
        tokens = line.split()
        if "sent" in seen or len(tokens) != 9 or not tokens[0].isdigit():
            return
        run_dir = next(tmp_path.iterdir())
        steps = [int(p.name.split(".")[1]) for p in run_dir.glob("restart/restart.*.bin")]
        if steps and int(tokens[0]) >= min(steps):
            seen["sent"] = int(tokens[0])
            # what Ctrl-C does in the main thread (a real SIGINT may be ignored when the tests
            # run in a background job, so raise it directly)
            raise KeyboardInterrupt

    inputs = prepare_run(config.dem)
    with pytest.raises(KeyboardInterrupt):
        run_dem(inputs, runs_root=tmp_path, progress=False, on_line=interrupt_after_restart)
    run_dir = next(tmp_path.iterdir())
    status = read_status(run_dir)
    assert status["state"] == "interrupted"
    assert not _solver_alive(status.get("solver_pid"))
    # neither a bad argument nor a plain rerun may cost the interrupted run's outputs
    kept = sorted(p.name for p in run_dir.rglob("*") if p.is_file())
    with pytest.raises(SolverRunError, match="number of MPI ranks must be >= 1"):
        run_dem(inputs, runs_root=tmp_path, np=0, progress=False)
    with pytest.raises(SolverRunError, match="--resume .*--fresh"):
        run_dem(inputs, runs_root=tmp_path, progress=False)
    assert sorted(p.name for p in run_dir.rglob("*") if p.is_file()) == kept
    record = run_dem(inputs, runs_root=tmp_path, resume=True, progress=False)
    assert record.state == "completed" and record.resumed_from.startswith("restart/")
    results = postprocess(
        record.dump_glob,
        config.dem,
        config.steady_state,
        massflow_dir=record.massflow_dir,
        solver_counters=record.solver_counters,
    )
    s = results.summary
    assert s.t_end_s == pytest.approx(2.0, abs=1e-3)
    assert s.accounting["lost"] == 0 and s.accounting["accounting_mismatch"] == 0
    assert_thermo_counters_agree(s)
    assert s.accounting["discharge_crosscheck_diff"] == 0
    steps = sorted(int(p.name.split(".")[1]) for p in run_dir.glob("dumps/dump.*.txt"))
    assert len(set(np.diff(steps))) == 1  # no gap, no duplicate across the restart


@liggghts
def test_sigterm_is_handled_like_ctrl_c(tmp_path):
    """A scheduler's or `timeout`'s SIGTERM: every rank ends within 2 s, the run is marked
    interrupted, and --resume finishes it."""
    import signal
    import subprocess
    import sys

    config = variant(load_preset("smoke"), operation={"duration_s": 3.0}, numerics={"restart_interval_s": 0.5})
    (tmp_path / "config.toml").write_text(__import__("workflows.config", fromlist=["dump_toml"]).dump_toml(config))
    script = (
        "import sys; from dem.run import prepare_run, run_dem; from workflows.config import load_config; "
        "run_dem(prepare_run(load_config(sys.argv[1]).dem), runs_root=sys.argv[2], progress=False)"
    )
    log = tmp_path / "child.err"
    with (
        open(log, "w") as err,
        subprocess.Popen(
            [sys.executable, "-c", script, str(tmp_path / "config.toml"), str(tmp_path / "runs")],
            cwd=Path(__file__).resolve().parents[2],
            stderr=err,
        ) as child,
    ):
        deadline = time.monotonic() + 300
        run_dir = None
        while time.monotonic() < deadline and child.poll() is None:
            time.sleep(0.5)
            runs = [p for p in (tmp_path / "runs").glob("*") if p.is_dir()]
            if runs and (runs[0] / "restart").is_dir():
                from dem.run import _restart_files  # the rule --resume applies: complete restart files only

                if _restart_files(runs[0]):
                    run_dir = runs[0]
                    break
        assert run_dir is not None, log.read_text() or "no restart file in time"
        solver_pid = read_status(run_dir)["solver_pid"]
        child.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        while _solver_alive(solver_pid) and time.monotonic() - sent < 10:
            time.sleep(0.05)
        # handled, the solver is gone in milliseconds; 5 s leaves a loaded machine its
        # scheduling delays and still tells it from an unhandled signal (the solver running
        # on to its end) and from the 10-s grace before SIGKILL
        assert time.monotonic() - sent <= 5.0, "the solver outlived SIGTERM by more than 5 s"
        child.wait(timeout=30)
    assert read_status(run_dir)["state"] == "interrupted"
    record = run_dem(prepare_run(config.dem), runs_root=tmp_path / "runs", resume=True, progress=False)
    assert record.state == "completed" and record.resumed_from.startswith("restart/")


def _solver_alive(pid):
    if not pid:
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    # a zombie is dead for our purpose
    try:
        with open(f"/proc/{pid}/stat") as handle:
            return handle.read().split()[2] != "Z"
    except OSError:
        return False


# ----------------------------------------------------------------------------- no solver needed
def test_thermo_counters_are_the_decks_named_columns():
    parser = ThermoParser(deck.THERMO_DISCHARGED, deck.THERMO_INSERTED, deck.THERMO_COLUMNS)
    # LIGGGHTS 3.8.0 prints the header without the v_/f_ prefixes
    assert not parser.feed("Step simtime Atoms insA insB outA outB ts[1] ts[2]")
    assert parser.feed("  8482 0.5 120 70 64 5 3 0.25 0.011")
    assert parser.counters() == {"discharged": 8.0, "inserted": 134.0, "atoms": 120, "step": 8482}


def test_solver_output_errors_and_exit_status(tmp_path):
    seen = []
    result = run_solver(
        ["sh", "-c", "echo Step Atoms; echo 'ERROR: Illegal fix'; exit 3"], tmp_path, "out.txt", on_line=seen.append
    )
    assert result.returncode == 3 and result.error_lines == ["ERROR: Illegal fix"]
    assert result.failure == "LIGGGHTS reported an error: ERROR: Illegal fix"
    assert result.output == "Step Atoms\nERROR: Illegal fix\n" == "".join(seen)
    assert result.output_file == tmp_path / "out.txt" and result.wall_s >= 0 and result.cpu_s >= 0
    again = run_solver(["sh", "-c", "exit 2"], tmp_path, "out.txt", append=True)
    assert again.failure == "LIGGGHTS exited with status 2" and again.output == result.output


def test_solver_hanging_after_an_error_is_stopped(tmp_path):
    t0 = time.monotonic()
    result = run_solver(
        ["sh", "-c", "echo 'ERROR on proc 1: boom'; exec sleep 60"], tmp_path, "out.txt", error_grace_s=1.0
    )
    assert time.monotonic() - t0 < 30 and result.returncode != 0 and result.error_lines


def test_timeout_and_interrupt_stop_every_process_of_the_session(tmp_path):
    with pytest.raises(SolverRunError, match="longer than the 1 s allowed"):
        run_solver(["sh", "-c", "sleep 60 & echo $! > child.pid; wait"], tmp_path, "out.txt", timeout_s=1.0)
    assert not _solver_alive((tmp_path / "child.pid").read_text())

    def interrupt(line):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_solver(
            ["sh", "-c", "sleep 60 & echo $! > child.pid; echo started; wait"], tmp_path, "out.txt", on_line=interrupt
        )
    assert not _solver_alive((tmp_path / "child.pid").read_text())


# ----------------------------------------------------------------------------- issue 22: killed runs
def _dead_pid() -> int:
    import subprocess

    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


THERMO_HEADER = "Step simtime Atoms insA insB outA outB ts[1] ts[2]\n"


def _killed_run(root, inputs, solver_out_rows, log_rows, restart_step=2000):
    """A run directory as SIGKILL (or a lost node) leaves it: status "running" with a pid
    that no longer exists, dumps, a restart file; solver.out with ``solver_out_rows`` thermo
    rows (it lost the rest when its reader died) and log.liggghts with ``log_rows``."""
    import json

    run_dir = Path(root) / inputs.key
    (run_dir / "dumps").mkdir(parents=True)
    (run_dir / "restart").mkdir()
    (run_dir / "dumps" / "dump.1000.txt").write_text("x")
    (run_dir / "restart" / f"restart.{restart_step}.bin").write_bytes(b"\0" * 64)
    row = lambda step: f"{step} 0.1 10 5 5 0 0 0.2 0.01\n"
    (run_dir / "solver.out").write_text(THERMO_HEADER + "".join(row(s) for s in solver_out_rows))
    (run_dir / "log.liggghts").write_text(THERMO_HEADER + "".join(row(s) for s in log_rows))
    status = {"state": "running", "key": inputs.key, "pid": _dead_pid(), "solver_pid": _dead_pid(), "started": "x"}
    (run_dir / "status.json").write_text(json.dumps(status))
    return run_dir


def test_stale_running_status_is_diagnosed_and_resumable(tmp_path):
    """kill -9 / SIGHUP of `dem run`: the status stays "running". A plain rerun names what
    happened and points to --resume (not "already running", not a loop); the restart at
    step 2000 is complete by log.liggghts (step 2500) although solver.out stopped at 1500."""
    from dem.run import _restart_files, can_resume

    inputs = prepare_run(load_preset("smoke").dem)
    run_dir = _killed_run(tmp_path, inputs, solver_out_rows=[500, 1000, 1500], log_rows=[500, 1000, 1500, 2000, 2500])
    assert [p.name for p in _restart_files(run_dir)] == ["restart.2000.bin"]
    with pytest.raises(
        SolverRunError,
        match=r"stopped \(crashed: killed without a trace \(its processes \(pid \d+, "
        r"solver pid \d+\) no longer exist.*continue it with --resume",
    ):
        run_dem(inputs, runs_root=tmp_path, progress=False)
    status = read_status(run_dir)
    assert status["state"] == "crashed" and "killed without a trace" in status["error"]
    assert can_resume(inputs, tmp_path)
    assert (run_dir / "dumps" / "dump.1000.txt").exists()  # nothing discarded


def test_restart_newer_than_every_log_is_not_trusted(tmp_path):
    from dem.run import _restart_files, last_thermo_step

    inputs = prepare_run(load_preset("smoke").dem)
    run_dir = _killed_run(tmp_path, inputs, solver_out_rows=[500], log_rows=[500, 1000], restart_step=2000)
    assert last_thermo_step(run_dir) == 1000 and _restart_files(run_dir) == []


def test_a_live_or_recycled_pid_is_told_apart(tmp_path):
    """A pid alive with the recorded start time is the run's; the same pid with another start
    time (reused after a reboot) is not; a run on another host is not judged from here."""
    import socket

    from dem.run import _liveness, _process_identity, diagnose_stale_status

    me = _process_identity(os.getppid())
    assert _liveness({**me, "solver_pid": None})[0] == "alive"
    assert _liveness({**me, "pid_start_ticks": me["pid_start_ticks"] + 1})[0] == "dead"
    other = {"state": "running", "pid": 1, "host": socket.gethostname() + "-elsewhere"}
    assert _liveness(other)[0] == "unknown"
    assert diagnose_stale_status(tmp_path, other)["state"] == "running"  # not rewritten without --resume
    assert diagnose_stale_status(tmp_path, other, resume=True)["state"] == "crashed"


def test_unusable_tmpdir_is_named_not_taken_for_a_missing_solver(tmp_path, monkeypatch):
    from dem.liggghts import check_tmpdir, liggghts_version

    afile = tmp_path / "afile"
    afile.write_text("")
    for value, message in (
        (str(afile), "is not a directory"),
        (str(afile / "sub"), r"is not a directory \(.*afile is a file\)"),
    ):
        monkeypatch.setenv("TMPDIR", value)
        with pytest.raises(SolverRunError, match=f"TMPDIR={value} {message}.*set TMPDIR to a writable directory"):
            liggghts_version()
    check_tmpdir({"TMPDIR": str(tmp_path / "new" / "dir")})  # created by Open MPI: fine
    check_tmpdir({})


@pytest.mark.parametrize(
    ("holdup", "throughput", "message"),
    [
        (float("nan"), 1e6, r"particles_held \(the hold-up, --holdup\) must be a finite number"),
        (float("inf"), 1e6, r"particles_held \(the hold-up, --holdup\) must be a finite number"),
        (1000.0, float("nan"), r"particle_steps_per_core_s \(the throughput, --throughput\) must be a finite number"),
        (1000.0, float("inf"), r"particle_steps_per_core_s \(the throughput, --throughput\) must be a finite number"),
        (1000.0, -1.0, r"throughput\) must be .* in \(0, 1e\+15\], got -1"),
    ],
)
def test_cluster_estimate_refuses_non_finite_inputs(holdup, throughput, message):
    from coupling.errors import ConfigError
    from dem.cluster import estimate_cost

    with pytest.raises(ConfigError, match=message):
        estimate_cost(load_preset("smoke").dem, holdup, throughput, 8)


@liggghts
@pytest.mark.parametrize("sig", ["SIGKILL", "SIGHUP"])
def test_killed_by_any_signal_then_rerun_and_resume(tmp_path, sig):
    """`dem run` killed by SIGKILL (nothing can be handled: the status stays "running") or
    SIGHUP (handled like SIGTERM: interrupted) after a complete restart file: a plain rerun
    says how it ended and points to --resume, and --resume finishes the run."""
    import signal
    import subprocess
    import sys

    config = variant(
        load_preset("smoke"), operation={"duration_s": 2.0}, numerics={"restart_interval_s": 0.5}, run={"np": 1}
    )
    (tmp_path / "config.toml").write_text(__import__("workflows.config", fromlist=["dump_toml"]).dump_toml(config))
    script = (
        "import sys; from dem.run import prepare_run, run_dem; from workflows.config import load_config; "
        "run_dem(prepare_run(load_config(sys.argv[1]).dem), runs_root=sys.argv[2], progress=False)"
    )
    with (
        open(tmp_path / "child.err", "w") as err,
        subprocess.Popen(
            [sys.executable, "-c", script, str(tmp_path / "config.toml"), str(tmp_path / "runs")],
            cwd=Path(__file__).resolve().parents[2],
            stderr=err,
        ) as child,
    ):
        from dem.run import _restart_files

        deadline, run_dir = time.monotonic() + 300, None
        while time.monotonic() < deadline and child.poll() is None and run_dir is None:
            time.sleep(0.2)
            runs = [p for p in (tmp_path / "runs").glob("*") if p.is_dir()]
            if runs and _restart_files(runs[0]):
                run_dir = runs[0]
        assert run_dir is not None, (tmp_path / "child.err").read_text() or "no restart file in time"
        solver_pid = read_status(run_dir)["solver_pid"]
        child.send_signal(getattr(signal, sig))
        child.wait(timeout=60)
    # the solver ends too: by our handler (SIGHUP) or on its broken output pipe (SIGKILL)
    sent = time.monotonic()
    while _solver_alive(solver_pid) and time.monotonic() - sent < 30:
        time.sleep(0.1)
    assert not _solver_alive(solver_pid)
    assert read_status(run_dir)["state"] == ("running" if sig == "SIGKILL" else "interrupted")
    inputs = prepare_run(config.dem)
    expected = "crashed: killed without a trace" if sig == "SIGKILL" else "interrupted"
    with pytest.raises(SolverRunError, match=rf"stopped \({expected}.*--resume"):
        run_dem(inputs, runs_root=tmp_path / "runs", progress=False)
    record = run_dem(inputs, runs_root=tmp_path / "runs", resume=True, progress=False)
    assert record.state == "completed" and record.resumed_from.startswith("restart/")


def test_restart_rewritten_by_a_killed_resume_is_not_vouched_for_by_an_older_log(tmp_path):
    """Attempt 1 reached step 5000; the resumed attempt rewrote restart.4500 and was killed
    while writing it: attempt 1's log (older than the file) does not make it complete."""
    from dem.run import _restart_files

    inputs = prepare_run(load_preset("smoke").dem)
    run_dir = _killed_run(tmp_path, inputs, solver_out_rows=[], log_rows=[4000, 4500, 5000], restart_step=4000)
    os.replace(run_dir / "log.liggghts", run_dir / "log.liggghts.attempt1")
    old = time.time() - 100
    os.utime(run_dir / "log.liggghts.attempt1", (old, old))
    os.utime(run_dir / "restart" / "restart.4000.bin", (old - 10, old - 10))
    (run_dir / "restart" / "restart.4500.bin").write_bytes(b"\0" * 10)  # the truncated rewrite
    (run_dir / "solver.out").write_text(
        THERMO_HEADER + "4000 0.1 10 5 5 0 0 0.2 0.01\n5000 0.1 10 5 5 0 0 0.2 0.01\n"
        "\n# --- resumed from restart/restart.4000.bin at x ---\n"
    )
    assert [p.name for p in _restart_files(run_dir)] == ["restart.4000.bin"]
