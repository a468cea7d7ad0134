"""Stop a DEM run once the PBM it feeds has converged (``pbmdem dem run --stop-when-converged``).

The criterion is the DEM budget's (:mod:`workflows.analysis.budget`) asked while the run goes:
every :data:`CHECK_EVERY_S` seconds of simulated time T, the dumps written so far are
post-processed (each dump read once over all checks, :class:`RunDirectoryCheck`), and the
PBMs built from their first T and T - dT seconds
(:func:`workflows.analysis.budget.table_from_first`, every rate mode the table carries) are
compared quantity by quantity on the agreement table. The run has converged when no
quantity moved by more than half the width of the DEM's 95 % interval at T: more DEM would
not change the PBM by more than the DEM itself can resolve. A quantity the DEM cannot yet
judge (no steady state, no pooled RTD yet) has not converged, so the earliest stop is one
check after the pooled RTD first exists.

The check runs on a thread beside the solver, one at a time (a check still running when
the next is due is skipped, not queued); the dumps of a check are those written before the
thermo line that started it, so every file it reads is complete. When a check says
converged, the next solver line stops the run (:class:`dem.run.StopRun`): it is kept,
marked ``stopped`` (never taken for a complete run), and ``--resume`` continues it.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from coupling.errors import DumpFormatError
from dem import deck
from dem.dumps import dump_paths
from dem.liggghts_log import ThermoParser
from dem.post import DemResults, Postprocessor
from dem.run import StopRun
from workflows.analysis.agreement import MODES, AgreementRow, agreement_rows, run_modes
from workflows.analysis.budget import Verdict, judge, table_from_first, verdict
from workflows.config import Config
from workflows.pipeline.results import pbm_config_for, rtd_pulse

#: Simulated seconds between checks (and the dT of the comparison).
CHECK_EVERY_S = 20.0


@dataclass(frozen=True)
class Convergence:
    """One convergence check at T: ``converged``, ``why`` not (None when it did) and per
    rate mode the :class:`~workflows.analysis.budget.Verdict` of the PBM from the first
    T - dT seconds against the PBM from the first T."""

    converged: bool
    t_s: float
    why: str | None = None
    modes: dict[str, Verdict] = field(default_factory=dict)


def converged(results: DemResults, config: Config, t_s: float, step_s: float = CHECK_EVERY_S) -> Convergence:
    """Whether the PBMs from the first ``t_s`` and ``t_s - step_s`` seconds of ``results``
    agree on every judged quantity to within half the DEM's 95 % interval at ``t_s``, in
    every rate mode."""
    summary = results.summary
    steady = summary.steady_time
    if steady is None:
        return Convergence(False, t_s, f"no steady state in the first {t_s:g} s")
    if not summary.has_pooled_rtd:
        # without it the agreement table has no RTD rows: judging the rest would pass a
        # PBM whose residence times nobody has checked
        return Convergence(
            False, t_s, f"no pooled RTD in the first {t_s:g} s yet (its entry window ends a horizon before T)"
        )
    if t_s - step_s < steady + results.table.window_s:
        return Convergence(
            False, t_s, f"no complete steady window before {t_s - step_s:g} s (steady from {steady:g} s)"
        )
    pbm_config = pbm_config_for(config, results.table, rtd_pulse(summary))

    def rows(t: float) -> list[AgreementRow]:
        table = table_from_first(results, t, steady)
        return agreement_rows(
            summary,
            results.particles,
            run_modes(table, pbm_config, config.steady_state, summary),
            results.steady_outlet_counts(),
        )

    now, before = rows(t_s), rows(t_s - step_s)
    # the yardstick is the DEM at T: the reference rows of judge() carry the half widths
    modes = {m: verdict(judge(before, now, m)) for m in MODES if math.isfinite(now[0].value(m))}
    if modes and all(v.all_inside for v in modes.values()):
        return Convergence(True, t_s, None, modes)
    worst = {m: v.worst.key for m, v in modes.items() if not v.all_inside and v.worst is not None}
    return Convergence(
        False, t_s, "moved by more than the DEM resolves: " + ", ".join(f"{m}: {k}" for m, k in worst.items()), modes
    )


@dataclass(frozen=True)
class CheckCost:
    """What one :class:`RunDirectoryCheck` cost: the dumps it read and the seconds spent
    reading them, finishing the results and judging the PBMs."""

    t_s: float
    dumps_read: int
    read_s: float
    results_s: float
    criterion_s: float

    @property
    def total_s(self) -> float:
        return self.read_s + self.results_s + self.criterion_s


class RunDirectoryCheck:
    """:func:`converged` on the dumps of ``run_dir`` up to T (and its discharge files), as
    ``check(T)``: the dumps are read once, by a :class:`dem.post.Postprocessor` kept
    between calls, so a check costs the dumps (and rate windows) written since the one
    before (the results equal a post-processing of every dump up to T in one pass). Calls
    must come with increasing T; they do from :class:`ConvergenceWatch`, one at a time.
    ``costs`` keeps what each check cost."""

    def __init__(self, run_dir: Path, config: Config, step_s: float = CHECK_EVERY_S) -> None:
        self.run_dir, self.config, self.step_s = Path(run_dir), config, float(step_s)
        self.post = Postprocessor(config.dem)
        self.costs: list[CheckCost] = []

    def __call__(self, t_s: float) -> Convergence:
        last = round(t_s / self.config.dem.timestep_s)
        read = self.post.last_step
        t0 = time.perf_counter()
        n_read = self.post.add([p for p in _dumps(self.run_dir) if read < deck.dump_step(p) <= last])
        t1 = time.perf_counter()
        if self.post.last_step < 0:
            return Convergence(False, t_s, f"no dump written up to {t_s:g} s in {self.run_dir}")
        results = self.post.results(self.config.steady_state, massflow_dir=self.run_dir)
        t2 = time.perf_counter()
        answer = converged(results, self.config, t_s, self.step_s)
        self.costs.append(CheckCost(t_s, n_read, t1 - t0, t2 - t1, time.perf_counter() - t2))
        return answer


def _dumps(run_dir: Path) -> list[Path]:
    try:
        return dump_paths(str(run_dir / deck.DUMP_GLOB))
    except DumpFormatError:  # none written yet
        return []


class ConvergenceWatch:
    """The ``on_line`` callback of :func:`dem.run.run_dem` that stops the run once
    ``check(T)`` (default :class:`RunDirectoryCheck`) says converged. ``history`` keeps
    every check's answer; ``log`` is told each one."""

    def __init__(
        self,
        config: Config,
        run_dir: Path,
        every_s: float = CHECK_EVERY_S,
        check: Callable[[float], Convergence] | None = None,
        log: Callable[[str], None] = lambda message: None,
    ) -> None:
        if not (math.isfinite(every_s) and every_s > 0):
            raise ValueError(f"the check interval must be > 0 s, got {every_s}")
        self.dt = float(config.dem.timestep_s)
        self.every_s = float(every_s)
        self.check = check or RunDirectoryCheck(Path(run_dir), config, self.every_s)
        self.log = log
        self.parser = ThermoParser(deck.THERMO_DISCHARGED, deck.THERMO_INSERTED, deck.THERMO_COLUMNS)
        self.next_s = 2 * self.every_s  # the first comparison needs T - dT > 0
        self.history: list[Convergence] = []
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._failed = False

    @property
    def converged_at(self) -> float | None:
        with self._lock:
            return next((h.t_s for h in self.history if h.converged), None)

    def postprocessor(self) -> Postprocessor | None:
        """The dumps the checks have read, for the run's own post-processing to finish
        (it then reads only the dumps written after the last check, and its results are
        the one-pass results all the same); None when the checks were not
        :class:`RunDirectoryCheck` or one of them failed part-way. Waits for a running check."""
        if self._thread is not None:
            self._thread.join()
        if self._failed or not isinstance(self.check, RunDirectoryCheck):
            return None
        return self.check.post

    def _run(self, t_s: float) -> None:
        try:
            answer = self.check(t_s)
        except Exception as exc:  # a failed check is a check that did not converge, said so
            self._failed = True
            answer = Convergence(False, t_s, f"check failed: {exc}")
        with self._lock:
            self.history.append(answer)
        verdict = "converged" if answer.converged else f"not yet ({answer.why})"
        costs = self.check.costs if isinstance(self.check, RunDirectoryCheck) else []
        if costs and costs[-1].t_s == t_s:
            verdict += f"; {costs[-1].dumps_read} new dumps, {costs[-1].total_s:.0f} s"
        self.log(f"convergence check at {t_s:g} s: {verdict}")

    def __call__(self, line: str) -> None:
        t_stop = self.converged_at
        if t_stop is not None:
            raise StopRun(f"the PBM converged at T = {t_stop:g} s (checks every {self.every_s:g} s)")
        if not self.parser.feed(line) or self.parser.step is None:
            return
        t = self.parser.step * self.dt
        # strictly after T: the dump written at T is closed before a later thermo line
        if t > self.next_s + 0.5 * self.dt:
            due = self.next_s
            self.next_s = (math.floor(t / self.every_s) + 1) * self.every_s
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, args=(due,), daemon=True)
                self._thread.start()
