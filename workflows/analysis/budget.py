"""How little DEM does a trustworthy PBM need? (``python -m workflows.analysis.budget``)

A PBM built from only the first T seconds of a DEM run predicts the full run's
quantities; the budget is the smallest T whose predictions all agree with the PBM built
from the whole run by the same rule, to within the DEM's own sampling uncertainty.

* :func:`table_from_first` -- the velocity table a PBM would have had if the DEM had
  stopped at T: measured windows before T, the steady mean seen so far after it (the
  measured rates refitted by maximum likelihood on the pooled particle moves).
* :func:`budget_study` -- for each T, each PBM rate mode on that table against the same
  modes on the whole run's table built by the same rule, each quantity of the agreement table judged against the half
  width of the full run's DEM 95 % interval (:func:`judge`); the smallest T per mode
  (:func:`smallest_budget`).
* :func:`main` -- the CLI: reads a DEM results file (default: the shipped reduced run),
  writes ``dem_budget.json`` and ``dem_budget.png``, prints a short table.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from coupling.blas import single_threaded_blas
from coupling.errors import ConfigError
from coupling.phases import PhaseTransport
from coupling.tables import RATE_NAMES, VELOCITY_NAMES, VelocityTable
from dem import phases
from dem.post import DemResults, sequence_diameters
from dem.rates import RATE_KEYS, fit_rates
from pbm.model import fill_missing_velocities
from workflows.analysis.agreement import MODES, AgreementRow, Judged, agreement_rows, run_modes
from workflows.config import Config
from workflows.pipeline.results import pbm_config_for, rtd_pulse

DEFAULT_T = (30.0, 45.0, 60.0, 90.0, 120.0, 180.0, 260.0)
#: agreement rows that are not judged: the recovered fraction's DEM interval is ~0.1 %
#: wide around a value the PBM approaches only through its RTD tail; it says nothing about
#: whether the tables converged that the mean and variance do not already say
SKIPPED = ("rtd_recovered_fraction",)

Log = Callable[[str], None]


# ----------------------------------------------------------------------------- the table
def table_from_first(results: DemResults, t_use_s: float, steady_time_s: float) -> VelocityTable:
    """The velocity table of ``results`` as a PBM would have it had the DEM stopped at
    T = ``t_use_s`` [s], for a PBM that still runs the full duration.

    Rule (why: a DEM stopped at T has measured the filling and the steady flow up to T, so
    the PBM uses the transient as measured and, for the whole steady period, the steady
    flow seen so far; applied at T = the run's end, the same rule gives the whole run's
    steady table, so the PBMs at different T differ only in how much DEM they saw):

    * windows that start before the steady state are kept as measured;
    * every window from the steady state on holds the steady mean of the complete windows
      in [``steady_time_s``, T): velocities as particle-weighted means sum(N v) / sum(N),
      N = count_A + count_B (a window that held more particles says more about the flow
      they saw), taken after the missing velocities of the windows before T are filled
      by the PBM's own rule (:func:`pbm.model.fill_missing_velocities`; nothing leaks
      from after T); the plain mean where those windows held no particle at all; counts
      as plain means; ``n_samples`` summed (that much data stands behind the mean);
    * the measured rates of those windows are refitted by maximum likelihood
      (:func:`dem.rates.fit_rates`) on the transition counts summed over the same steady
      windows, not averaged: a mean of per-window fits weighs a compartment's poorly
      observed windows like its well observed ones and carries each fit's bias, whereas
      the pooled counts are exactly the evidence a DEM stopped at T holds. Compartments
      with fewer than ``table.min_samples`` pooled observations stay NaN (the PBM fills
      them, as it fills every unmeasured rate).

    T beyond the table's end counts as its end. Raises ValueError when [steady_time_s, T)
    holds no complete window (then there is no steady flow to hold), for a non-finite T
    or steady time, and when the table has rates but ``results`` has no transition counts
    for its windows.
    """
    table = results.table
    if not (math.isfinite(t_use_s) and t_use_s > 0):
        raise ValueError(f"T = {t_use_s!r}: expected a finite time > 0 s")
    if not math.isfinite(steady_time_s):
        raise ValueError(
            f"T = {t_use_s:g} s: the steady-state time is {steady_time_s!r}; "
            "without a steady state there is no steady flow to hold"
        )
    tol = 1e-9 * table.window_s
    ends = table.t + table.window_s
    known = ends <= t_use_s + tol
    after_steady = table.t >= steady_time_s - tol
    steady = known & after_steady
    if not steady.any():
        after = ends[after_steady]
        first = f"the first one ends at {after[0]:g} s" if after.size else "the table has none after it"
        raise ValueError(
            f"T = {t_use_s:g} s: no complete {table.window_s:g}-s window lies in "
            f"[steady time {steady_time_s:g} s, T); {first}"
        )
    attrs = {
        "budget_t_use_s": float(min(t_use_s, table.t_end)),
        "budget_steady_time_s": float(steady_time_s),
        "budget_rule": "windows from the steady state on hold the steady mean of the windows in "
        "[steady time, T) (workflows.analysis.budget.table_from_first)",
    }
    table = _hold_steady_mean(results, known=known, steady=steady, hold=after_steady, attrs=attrs)
    return table.replace(phases=refit_phases(results, t_use_s, steady_time_s))


def _hold_steady_mean(
    results: DemResults, known: np.ndarray, steady: np.ndarray, hold: np.ndarray, attrs: dict[str, Any]
) -> VelocityTable:
    """The table with the ``hold`` windows set to the steady mean of the ``steady``
    windows (the rule of :func:`table_from_first`), missing velocities filled from the
    ``known`` windows only. Masks are (K,) bool; ``steady`` lies within ``known``."""
    table = results.table
    early = table.replace(
        t=table.t[known],
        n_samples=table.n_samples[known],
        **{
            name: getattr(table, name)[known]
            for name in (*VELOCITY_NAMES, "count_A", "count_B", *(RATE_NAMES if table.has_rates else ()))
        },
    )
    filled, _ = fill_missing_velocities(early)
    window = steady[known]  # the steady windows, indexed within the known ones
    n = filled.count_A[window] + filled.count_B[window]
    total = n.sum(axis=0)
    held: dict[str, np.ndarray] = {}
    for name in VELOCITY_NAMES:
        v = getattr(filled, name)[window]
        weighted = (n * v).sum(axis=0) / np.where(total > 0, total, 1.0)
        held[name] = np.where(total > 0, weighted, v.mean(axis=0))
    for name in ("count_A", "count_B"):
        held[name] = getattr(table, name)[steady].mean(axis=0)
    held["n_samples"] = table.n_samples[steady].sum(axis=0)

    attrs = {**table.attrs, **attrs, "budget_steady_windows": int(steady.sum())}
    if table.has_rates:
        fit = refit_rates(results, steady)
        held.update({f"rate_{key}": getattr(fit, key) for key in RATE_KEYS})
        attrs.update(
            {
                "budget_rates_converged": bool(fit.converged),
                "budget_rates_iterations": int(fit.iterations),
                "budget_rates_capped": int(fit.capped),
            }
        )

    fields = {}
    for name, value in held.items():
        full = getattr(table, name).copy()
        full[hold] = value
        fields[name] = full
    return table.replace(**fields, attrs=attrs)


def refit_phases(results: DemResults, t_use_s: float, steady_time_s: float) -> PhaseTransport | None:
    """The phase model a run stopped at ``t_use_s`` would carry: refitted
    (:func:`dem.phases.table_with_phases`) on the compartment sequences up to then; None
    when the table has none, or the particles that entered in [steady time, T) are too few
    to fit one (the budget's PBM then runs without the phases mode)."""
    if not results.table.has_phases or results.sequences is None:
        return None
    seen = results.sequences.snapshot_t
    if t_use_s >= seen[-1] and steady_time_s == results.summary.steady_time:
        # the same sequences and steady time as the post-processing's own fit, which is
        # deterministic: its model, without fitting it again
        return results.table.phases
    try:
        short = results.sequences.until(t_use_s)
        refit, _fits = phases.table_with_phases(
            results.table,
            short,
            steady_time_s,
            phases.moving_phases(results.table.phases),
            diameters=sequence_diameters(short, results.particles),
        )
    except (ValueError, FloatingPointError, np.linalg.LinAlgError):
        return None
    return refit.phases


def refit_rates(results: DemResults, windows: np.ndarray):
    """:func:`dem.rates.fit_rates` on the transition counts summed over ``windows`` (a (K,)
    bool mask), at the table's dump interval and observation threshold."""
    table = results.table
    transitions = np.asarray(results.transitions)
    s = table.nx * table.ny
    if transitions.shape != (table.n_windows, s + 1, s + 1):
        raise ValueError(
            f"the table carries measured rates but the transition counts have shape "
            f"{transitions.shape}, not (K, S+1, S+1) = ({table.n_windows}, {s + 1}, {s + 1})"
        )
    interval = table.attrs.get("rates_interval_s")
    if interval is None:
        raise ValueError(
            "the table carries measured rates but no 'rates_interval_s' attribute (the dump "
            "interval they were fitted at)"
        )
    # the rate fits are a hot loop of small matrices: one BLAS thread (coupling.blas)
    with single_threaded_blas():
        return fit_rates(
            transitions[windows].sum(axis=0), table.nx, table.ny, float(interval), min_observations=table.min_samples
        )


# ----------------------------------------------------------------------------- judging
def judge(rows_t: list[AgreementRow], reference_rows: list[AgreementRow], mode: str) -> list[Judged]:
    """One judged quantity per row (every agreement row but :data:`SKIPPED`): the T-PBM's
    value against the reference PBM's (the whole run's), with the half width of the
    reference rows' DEM interval as the tolerance (:meth:`AgreementRow.half_width`)."""
    reference = {row.key: row for row in reference_rows if row.key not in SKIPPED}
    return [
        Judged(
            row.key, row.quantity, row.value(mode), reference[row.key].value(mode), reference[row.key].half_width(mode)
        )
        for row in rows_t
        if row.key in reference
    ]


@dataclass(frozen=True)
class Verdict:
    """One rate mode's verdict on :func:`judge`'s rows. ``all_inside_without_slices``
    leaves the per-slice hold-ups out: their DEM half widths are ~0.5 % of a slice's
    hold-up, tighter than anything else judged."""

    rows: tuple[Judged, ...]

    @property
    def all_inside(self) -> bool:
        return all(row.ok for row in self.rows)

    @property
    def all_inside_without_slices(self) -> bool:
        return all(row.ok for row in self.rows if not row.key.startswith("holdup_slice_"))

    @property
    def n_inside(self) -> int:
        return sum(row.ok for row in self.rows)

    @property
    def worst(self) -> Judged | None:
        return max(self.rows, key=lambda r: r.deviation if math.isfinite(r.deviation) else math.inf, default=None)

    def record(self) -> dict[str, Any]:
        worst = self.worst
        return {
            "all_inside": self.all_inside,
            "all_inside_without_slices": self.all_inside_without_slices,
            "n_inside": self.n_inside,
            "n_rows": len(self.rows),
            "worst": None if worst is None else worst.key,
            "worst_deviation": None if worst is None else worst.deviation,
            "rows": [
                {
                    "key": r.key,
                    "quantity": r.quantity,
                    "pbm_T": r.value,
                    "pbm_whole": r.reference,
                    "half_width": r.tolerance,
                    "deviation": r.deviation,
                    "inside": r.ok,
                }
                for r in self.rows
            ],
        }


def verdict(judged: list[Judged]) -> Verdict:
    return Verdict(tuple(judged))


@dataclass(frozen=True)
class WholeRow:
    """The whole-run PBM's value of one quantity in one mode, with the DEM's interval (for
    the RTD overlap: the mode's noise band) and the half width every T is judged by."""

    key: str
    quantity: str
    pbm_whole: float
    dem: float
    dem_ci_low: float
    dem_ci_high: float
    half_width: float

    def record(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class Budget:
    """One DEM budget T: its steady-state time, what its table was built from, the error
    that kept it from being judged (None when judged) and per mode its :class:`Verdict`."""

    t_s: float
    fraction: float
    steady_time_s: float | None = None
    error: str | None = None
    table: dict[str, Any] | None = None
    modes: dict[str, Verdict] = field(default_factory=dict)

    def record(self) -> dict[str, Any]:
        out = {
            "t_s": self.t_s,
            "fraction": self.fraction,
            "steady_time_s": self.steady_time_s,
            "error": self.error,
            "modes": {mode: v.record() for mode, v in self.modes.items()},
        }
        if self.table is not None:
            out["table"] = self.table
        return out


@dataclass(frozen=True)
class BudgetStudy:
    """:func:`budget_study`'s answer (see there); ``smallest_T`` and
    ``smallest_T_without_slices``: per mode (T [s], fraction of the run), None when no T
    qualifies."""

    t_end_s: float
    steady_state_time_s: float
    whole: dict[str, list[WholeRow]]
    holding: dict[str, Verdict]
    budgets: list[Budget]
    smallest_T: dict[str, tuple[float | None, float | None]]
    smallest_T_without_slices: dict[str, tuple[float | None, float | None]]
    reference: str | None = None
    elapsed_s: float | None = None

    def record(self) -> dict[str, Any]:
        def smallest(values: dict[str, tuple[float | None, float | None]]) -> dict[str, Any]:
            return {mode: {"t_s": t, "fraction": f} for mode, (t, f) in values.items()}

        out = {
            "t_end_s": self.t_end_s,
            "steady_state_time_s": self.steady_state_time_s,
            "skipped": list(SKIPPED),
            "yardstick": YARDSTICK,
            "whole": {mode: [r.record() for r in rows] for mode, rows in self.whole.items()},
            "holding": {mode: v.record() for mode, v in self.holding.items()},
            "budgets": [b.record() for b in self.budgets],
            "smallest_T": smallest(self.smallest_T),
            "smallest_T_without_slices": smallest(self.smallest_T_without_slices),
        }
        if self.reference is not None:
            out["reference"], out["elapsed_s"] = self.reference, self.elapsed_s
        return out


YARDSTICK = (
    "|pbm_T - pbm_whole| <= half width of the whole run's DEM 95 % interval (RTD overlap: 1 - noise low of the mode)"
)


def smallest_budget(all_inside: dict[float, bool]) -> float | None:
    """The smallest T such that T and every larger T studied are all inside; None when
    the largest T studied is not."""
    best = None
    for t in sorted(all_inside, reverse=True):
        if not all_inside[t]:
            break
        best = t
    return best


# ----------------------------------------------------------------------------- the study
def budget_study(
    results: DemResults, config: Config, t_values: Sequence[float], log: Log = lambda message: None
) -> BudgetStudy:
    """For each T in ``t_values``: each PBM rate mode on :func:`table_from_first`, judged
    quantity by quantity (every agreement row but :data:`SKIPPED`) against the same mode
    on the whole run's table built by the same rule (T = the run's end).

    The yardstick: a quantity of the T-PBM is inside when |pbm_T - pbm_whole| <= half the
    width of the whole run's DEM 95 % interval (for the RTD overlap, the noise-band width
    1 - noise low). Why not the literal "inside the DEM interval": on the quantities on
    which the PBM itself is biased (the hold-up profile, the outlet RSD, ...) even the
    whole-run PBM lies outside, so no T could ever pass; the question is whether the
    tables have converged -- whether more DEM would change the PBM's predictions -- and
    the DEM's own sampling uncertainty is the scale below which a change does not matter.
    Both sides of the comparison are built by one rule, so they differ in nothing but how
    much DEM they saw.

    The steady-state time for T is the one the first T seconds of the DEM show
    (``config.steady_state`` on the DEM's hold-up up to T): the rule is causal, so it is
    the full run's once T passes it, and a T before it has no budget. A T that fails
    (no steady state yet, no complete steady window) is reported with its ``error`` and
    counts as not inside.

    ``holding``: the whole-run steady table's PBM judged the same way against the PBM on
    the per-window table (every 5-s window as measured): how much holding one steady flow
    for the fluctuating windows moves the PBM by itself, whatever the DEM budget.

    Returns ``t_end_s``, ``steady_state_time_s``, ``skipped``, ``yardstick``, ``whole``
    (per mode: the whole-run PBM's rows with the DEM interval and half width),
    ``holding`` (per mode: :func:`verdict`), ``budgets`` (per T: ``t_s``, ``fraction`` of
    the full duration, ``steady_time_s``, ``error``, ``table`` (what the steady period
    was built from) and per mode :func:`verdict`), ``smallest_T`` and
    ``smallest_T_without_slices`` (per mode: ``t_s`` and ``fraction``, None when no T
    qualifies). Raises ValueError when the run never reaches the steady state.
    """
    table, summary = results.table, results.summary
    pbm_config = pbm_config_for(config, table, rtd_pulse(summary))
    t_end = table.t_end
    steady_full = summary.steady_time
    if steady_full is None:
        raise ConfigError("the DEM run never reaches the steady state: there is no steady flow to budget")

    def rows_of(t: VelocityTable) -> list[AgreementRow]:
        return agreement_rows(
            summary,
            results.particles,
            run_modes(t, pbm_config, config.steady_state, summary),
            results.steady_outlet_counts(),
        )

    log("PBM on the whole run's steady table")
    whole_rows = rows_of(table_from_first(results, t_end, steady_full))
    log("PBM on the per-window table")
    window_rows = rows_of(table)
    modes = [mode for mode in MODES if math.isfinite(whole_rows[0].value(mode))]
    whole = {mode: whole_run_rows(whole_rows, mode) for mode in modes}
    holding = {mode: verdict(judge(whole_rows, window_rows, mode)) for mode in modes}
    budgets = [
        judge_budget(results, config, t_use, whole_rows, modes, rows_of, log)
        for t_use in sorted(float(t) for t in t_values)
    ]
    smallest, without_slices = {}, {}
    for mode in modes:
        for out, flag in ((smallest, "all_inside"), (without_slices, "all_inside_without_slices")):
            t_best = smallest_budget({b.t_s: mode in b.modes and getattr(b.modes[mode], flag) for b in budgets})
            out[mode] = (t_best, None if t_best is None else min(t_best / t_end, 1.0))
    return BudgetStudy(t_end, steady_full, whole, holding, budgets, smallest, without_slices)


def whole_run_rows(whole_rows: list[AgreementRow], mode: str) -> list[WholeRow]:
    """The whole-run PBM's rows of ``mode`` (all but :data:`SKIPPED`) with the DEM interval
    and the yardstick's half width; the RTD overlap's lower bound is the mode's noise low."""
    return [
        WholeRow(
            row.key,
            row.quantity,
            row.value(mode),
            row.dem,
            row.pbm[mode].noise_low if row.pbm[mode].noise_low is not None else row.dem_ci_low,
            row.dem_ci_high,
            row.half_width(mode),
        )
        for row in whole_rows
        if row.key not in SKIPPED
    ]


def judge_budget(
    results: DemResults,
    config: Config,
    t_use: float,
    whole_rows: list[AgreementRow],
    modes: list[str],
    rows_of: Callable[[VelocityTable], list[AgreementRow]],
    log: Log,
) -> Budget:
    """One DEM budget of :func:`budget_study`: the steady-state time the first ``t_use``
    seconds [s] show, the table built from them and every mode's :func:`verdict` against
    the whole run's rows; a budget with no steady state or no complete steady window
    carries its ``error`` instead."""
    table = results.table
    t_end = table.t_end
    entry = Budget(t_use, min(t_use / t_end, 1.0))
    times = results.timeseries["t_s"].to_numpy(float)
    holdup = (results.timeseries["holdup_A"] + results.timeseries["holdup_B"]).to_numpy(float)
    seen = times <= t_use + 1e-9
    steady_time = config.steady_state.time(times[seen], holdup[seen])
    if steady_time is None:
        entry.error = f"T = {t_use:g} s: the DEM's first {t_use:g} s never reach the steady state"
        log(entry.error)
        return entry
    entry.steady_time_s = steady_time
    try:
        table_t = table_from_first(results, t_use, steady_time)
    except ValueError as exc:
        entry.error = str(exc)
        log(entry.error)
        return entry
    entry.table = {
        key.removeprefix("budget_"): value
        for key, value in table_t.attrs.items()
        if key.startswith("budget_") and key != "budget_rule"
    }
    if t_use >= t_end - 1e-9 * table.window_s:  # the whole run: its PBM is the reference itself
        rows_t = whole_rows
    else:
        log(f"PBM on the first {t_use:g} s")
        rows_t = rows_of(table_t)
    entry.modes = {mode: verdict(judge(rows_t, whole_rows, mode)) for mode in modes}
    return entry
