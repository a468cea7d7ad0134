"""Stop a DEM run once the PBM it feeds has converged (``pbmdem dem run --stop-when-converged``).

The criterion is the DEM budget's (:mod:`workflows.analysis.budget`) asked while the run goes:
every :data:`CHECK_EVERY_S` seconds of simulated time T, the dumps written so far are
post-processed, and the PBMs built from their first T and T - dT seconds
(:func:`workflows.analysis.budget.table_from_first`, both rate modes the table carries) are
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
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from dem import deck
from dem.dumps import dump_paths
from dem.liggghts_log import ThermoParser
from dem.post import DemResults, postprocess
from dem.run import StopRun
from workflows.analysis.agreement import MODES, AgreementRow, agreement_rows, run_modes
from workflows.analysis.budget import Verdict, judge, table_from_first, verdict
from workflows.config import Config
from workflows.pipeline.stages import pbm_config_for, rtd_pulse

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
        return agreement_rows(summary, results.particles, run_modes(table, pbm_config, config.steady_state, summary))

    now, before = rows(t_s), rows(t_s - step_s)
    # the yardstick is the DEM at T: the reference rows of judge() carry the half widths
    modes = {m: verdict(judge(before, now, m)) for m in MODES if math.isfinite(now[0].value(m))}
    if modes and all(v.all_inside for v in modes.values()):
        return Convergence(True, t_s, None, modes)
    worst = {m: v.worst.key for m, v in modes.items() if not v.all_inside and v.worst is not None}
    return Convergence(
        False, t_s, "moved by more than the DEM resolves: " + ", ".join(f"{m}: {k}" for m, k in worst.items()), modes
    )


def check_run_directory(run_dir: Path, config: Config, t_s: float, step_s: float = CHECK_EVERY_S) -> Convergence:
    """:func:`converged` on the dumps of ``run_dir`` up to ``t_s`` (and its discharge files)."""
    last = round(t_s / config.dem.timestep_s)
    files = [p for p in dump_paths(str(run_dir / deck.DUMP_GLOB)) if int(p.name.split(".")[1]) <= last]
    results = postprocess(files, config.dem, config.steady_state, massflow_dir=run_dir)
    return converged(results, config, t_s, step_s)


class ConvergenceWatch:
    """The ``on_line`` callback of :func:`dem.run.run_dem` that stops the run once
    ``check(T)`` (default :func:`check_run_directory`) says converged. ``history`` keeps
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
        self.check = check or (lambda t: check_run_directory(Path(run_dir), config, t, self.every_s))
        self.log = log
        self.parser = ThermoParser(deck.THERMO_DISCHARGED, deck.THERMO_INSERTED, deck.THERMO_COLUMNS)
        self.next_s = 2 * self.every_s  # the first comparison needs T - dT > 0
        self.history: list[Convergence] = []
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    @property
    def converged_at(self) -> float | None:
        with self._lock:
            return next((h.t_s for h in self.history if h.converged), None)

    def _run(self, t_s: float) -> None:
        try:
            answer = self.check(t_s)
        except Exception as exc:  # a failed check is a check that did not converge, said so
            answer = Convergence(False, t_s, f"check failed: {exc}")
        with self._lock:
            self.history.append(answer)
        self.log(f"convergence check at {t_s:g} s: " + ("converged" if answer.converged else f"not yet ({answer.why})"))

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
