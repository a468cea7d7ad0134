"""Does the hybrid predict what it was not built from? The validation campaign.

1. :data:`CHANGES` -- the ``validation`` preset (coarse particles, long enough for a pooled
   RTD) and one factor changed at a time: blender length x1.25 (more paddle stations at the
   same spacing), impeller 150 and 350 rpm, feed rate x2. :func:`run_campaign` runs each
   through the normal DEM stage (LIGGGHTS, post-processing, cache by input hash), so an
   interrupted campaign continues where it stopped; the shipped campaign results in
   :data:`REFERENCE_DIR` serve a fresh clone without LIGGGHTS (``pbmdem validate``,
   ``make validate``; ``--fresh`` / ``FRESH=1`` reruns the campaign).
2. :func:`predictions` -- for every changed run, PBMs built from the baseline DEM alone
   (length by rescaling the compartments, feed with unchanged velocities, rpm with
   velocities and rates scaled by the rpm ratio), from the table library (rpm interpolated
   between the other runs' tables, leave one out), and the run's own tables ("self": what a
   new DEM run gives the PBM). Each in both rate modes, judged by the agreement table of
   :mod:`workflows.agreement` against that run's DEM and its intervals.
3. :func:`judge` -- the verdict from the numbers. A quantity is predicted when the
   prediction's distance from the DEM is no larger than the hybrid's own error on the
   baseline (its PBM built from the baseline's tables against the baseline's DEM, relative,
   scaled to the new value) plus the half width of the new DEM's 95 % interval: the
   prediction is as good as the hybrid is where it was built. The run's self-built PBM
   (what a new DEM run would give the PBM) is reported beside it, not used as the yardstick:
   where it is poor, a lenient yardstick would pass anything. A change is predicted ("the
   hybrid predicts this") when every judged quantity of a rate mode is; else "this needs a
   new DEM run", with the failing quantities of the mode that came nearest.
"""

from __future__ import annotations

import datetime as _dt
import html
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from coupling.errors import ConfigError, OutputError, os_reason
from coupling.jsonable import json_ready
from coupling.tables import VelocityTable
from dem.run import can_resume, prepare_run
from pbm.studies import interpolate_tables, scale_blender, scale_speed
from workflows.agreement import MODES, agreement_rows, half_width, run_modes
from workflows.bench import write_json
from workflows.config import Config, config_without, load_preset, override
from workflows.dem_budget import budget_study, plot_budget
from workflows.pipeline import DemSide, Log, dem_stage, pbm_config_for, rtd_pulse, stderr_log, writable_directory
from workflows.report import fmt
from workflows.step_response import plot_step, run_step, step_comparison, step_config, step_html, summary_rows

REFERENCE_DIR = Path(__file__).resolve().parent / "reference" / "validation"
PRESET = "validation"


@dataclass(frozen=True)
class Change:
    """One run of the campaign: ``overrides`` (``dotted.path=value``) of the baseline."""

    name: str
    label: str
    overrides: tuple[str, ...] = ()


#: The baseline's blade stations sit 28.3 mm apart from x = 45 mm; x1.25 the length keeps
#: that spacing with 13 stations, the last 27.5 mm upstream of the weir (30 mm in the baseline).
CHANGES = (
    Change("baseline", "baseline (validation preset)"),
    Change("length_x1.25", "blender length x1.25",
           ("dem.geometry.length_m=0.4125", "dem.geometry.blade_stations=13", "dem.geometry.last_blade_x_m=0.385")),
    Change("rpm_150", "impeller 150 rpm", ("dem.operation.impeller_rpm=150",)),
    Change("rpm_350", "impeller 350 rpm", ("dem.operation.impeller_rpm=350",)),
    Change("feed_x2", "feed rate x2", ("dem.operation.feed_rate_total_per_s=147.4",)),
)


def campaign_configs(base: Config | None = None) -> dict[str, Config]:
    """Each change's configuration, validated before any run starts."""
    base = base if base is not None else load_preset(PRESET)
    configs = {}
    for change in CHANGES:
        config = base
        for assignment in change.overrides:
            config = override(config, assignment)
        configs[change.name] = config.model_copy(update={"name": f"{base.name}-{change.name}"})
    return configs


def run_campaign(runs_root: str | Path = "runs/validation", fresh: bool = False, nprocs: int | None = None,
                 log: Log = stderr_log, reference_dir: Path = REFERENCE_DIR,
                 configs: dict[str, Config] | None = None, solver: bool = True) -> dict[str, DemSide]:
    """Every run of the campaign, in :data:`CHANGES` order: from the cache under
    ``runs_root``, the shipped results, else LIGGGHTS (an interrupted run continues from its
    newest restart file). ``fresh`` reruns every solver run; ``solver=False`` never starts
    LIGGGHTS (LookupError for a run that is neither cached nor shipped)."""
    configs = configs if configs is not None else campaign_configs()
    sides = {}
    for name, config in configs.items():
        resume = not fresh and can_resume(prepare_run(config.dem), runs_root)
        log(f"validation run {name}: {'resuming' if resume else 'starting or reusing'}")
        t0 = time.monotonic()
        sides[name] = dem_stage(config, runs_root=runs_root, np=nprocs, resume=resume, fresh=fresh, progress=False,
                                log=log, reference_dir=reference_dir, solver=solver)
        log(f"validation run {name}: {sides[name].source} ({time.monotonic() - t0:.0f} s)")
    return sides


# --------------------------------------------------------------------------- predictions
#: Agreement rows that are diagnostics of the RTD's definition, not predictions to judge.
NOT_JUDGED = ("rtd_recovered_fraction",)


def prediction_tables(sides: dict[str, DemSide], configs: dict[str, Config],
                      baseline: str = "baseline") -> dict[str, dict[str, VelocityTable | str]]:
    """For every run: its own table ("self"), the prediction from the baseline alone
    ("baseline": compartments rescaled to a new length, velocities and rates scaled by the
    rpm ratio, a new feed rate with the velocities unchanged), and from the table library
    ("library": interpolated in rpm between the other runs that differ only in rpm). A
    prediction that cannot be made is a string saying why."""
    base_cfg, base_table = configs[baseline], sides[baseline].table
    rpm_key = "dem.operation.impeller_rpm"
    out: dict[str, dict[str, VelocityTable | str]] = {}
    for name, config in configs.items():
        tables: dict[str, VelocityTable | str] = {"self": sides[name].table}
        if name != baseline:
            table = base_table
            length_factor = config.dem.geometry.length_m / base_cfg.dem.geometry.length_m
            if not math.isclose(length_factor, 1.0):
                table = scale_blender(table, length_factor=length_factor)
            speed = config.dem.operation.impeller_rpm / base_cfg.dem.operation.impeller_rpm
            if not math.isclose(speed, 1.0):
                table = scale_speed(table, speed)
            tables["baseline"] = table
        same_but_rpm = config_without(config, rpm_key)
        library = [(other.dem.operation.impeller_rpm, sides[o].table) for o, other in configs.items()
                   if o != name and config_without(other, rpm_key) == same_but_rpm]
        if len(library) >= 2:
            try:
                tables["library"] = interpolate_tables(library, config.dem.operation.impeller_rpm)
            except ConfigError as exc:
                tables["library"] = str(exc)
        out[name] = tables
    return out


@dataclass
class Prediction:
    """One PBM source's agreement rows against one run's DEM."""

    run: str
    source: str
    rows: list[dict[str, Any]] = field(default_factory=list)
    note: str = ""


def predictions(sides: dict[str, DemSide], configs: dict[str, Config], log: Log = stderr_log) -> list[Prediction]:
    """Every source of :func:`prediction_tables` for every run, in both rate modes, as the
    agreement table against that run's DEM (same entry window, horizon and steady rule)."""
    out = []
    for name, tables in prediction_tables(sides, configs).items():
        config, dem = configs[name], sides[name].results
        for source, table in tables.items():
            if isinstance(table, str):
                out.append(Prediction(name, source, note=table))
                continue
            log(f"PBM of {name} from {source}")
            modes = run_modes(table, pbm_config_for(config, table, rtd_pulse(dem.summary)), config.steady_state, dem.summary)
            out.append(Prediction(name, source, agreement_rows(dem.summary, dem.particles, modes)))
    return out


def judge(predicted: list[dict[str, Any]], own: list[dict[str, Any]],
          calibration: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The verdict on one prediction (module docstring, 3.): per rate mode and quantity,
    ``error`` = |prediction - DEM| and ``tolerance`` = the hybrid's own error on the
    ``calibration`` run (its self-built PBM against its DEM, default ``own``), relative to
    that DEM value and scaled to this one (absolute for the RTD overlap, whose ideal is 1),
    plus the half width of this DEM's interval; ``ok`` = error <= tolerance. The run's own
    self-built PBM (``own``) is reported beside it as ``self``. The mode predicts the change
    when every judged quantity is ok. Quantities missing anywhere are left out and listed."""
    own_rows = {row["key"]: row for row in own}
    cal_rows = {row["key"]: row for row in (calibration if calibration is not None else own)}
    verdict: dict[str, Any] = {}
    for mode in MODES:
        rows, missing = [], []
        for row in predicted:
            key = row["key"]
            if key in NOT_JUDGED:
                continue
            cal = cal_rows.get(key, {})
            dem, pred, self_value = row.get("dem"), row.get(f"pbm_{mode}"), own_rows.get(key, {}).get(f"pbm_{mode}")
            cal_dem, cal_pbm = cal.get("dem"), cal.get(f"pbm_{mode}")
            half = half_width(row, mode)
            values = (dem, pred, self_value, cal_dem, cal_pbm, half)
            if any(v is None or not np.isfinite(v) for v in values) or (key != "rtd_overlap" and cal_dem == 0):
                missing.append(key)
                continue
            model_error = (abs(cal_pbm - cal_dem) if key == "rtd_overlap"
                           else abs(cal_pbm - cal_dem) / abs(cal_dem) * abs(dem))
            error, tolerance = abs(pred - dem), model_error + half
            rows.append({"key": key, "quantity": row["quantity"], "dem": dem, "dem_ci_low": row["dem_ci_low"],
                         "dem_ci_high": row["dem_ci_high"], "predicted": pred, "self": self_value, "error": error,
                         "model_error": model_error, "tolerance": tolerance, "ok": error <= tolerance})
        failing = [r["key"] for r in rows if not r["ok"]]
        verdict[mode] = {"rows": rows, "missing": missing, "failing": failing,
                         "predicts": bool(rows) and not failing}
    return verdict


def verdict_text(verdict: dict[str, Any]) -> str:
    """The plain verdict of a change from :func:`judge`'s numbers; when no rate mode
    predicts it, the failures of the mode that came nearest."""
    good = [mode for mode in MODES if verdict.get(mode, {}).get("predicts")]
    if good:
        return f"the hybrid predicts this ({' and '.join(good)} rates)"
    judged = [mode for mode in MODES if verdict.get(mode, {}).get("rows")]
    if not judged:
        return "this needs a new DEM run (no quantity could be judged)"
    best = min(judged, key=lambda mode: len(verdict[mode]["failing"]))
    failing = verdict[best]["failing"]
    slices = [key for key in failing if key.startswith("holdup_slice_")]
    named = [key for key in failing if key not in slices]
    named += [f"hold-up of {len(slices)} axial slice{'s' if len(slices) > 1 else ''}"] if slices else []
    return (f"this needs a new DEM run (nearest: {best} rates, {len(failing)} of {len(verdict[best]['rows'])} "
            f"quantities outside tolerance: {', '.join(named)})")


# --------------------------------------------------------------------------- the report
#: The DEM budgets studied on the baseline, as fractions of its duration.
BUDGET_FRACTIONS = (0.25, 0.3, 0.45, 0.6, 0.75, 1.0)
SOURCE_COLOURS = {"self": "#636363", "baseline": "#e6550d", "library": "#31a354"}
MODE_MARKERS = {"velocity": "o", "measured": "s"}
PARITY = (("mean_residence_time_s", "mean residence time [s]"), ("rtd_variance_s2", "RTD variance [s²]"),
          ("little_mean_residence_time_s", "hold-up / outflow [s]"), ("holdup", "steady hold-up [particles]"),
          ("outflow_per_s", "steady outflow [1/s]"), ("C_A", "steady C_A [-]"),
          ("rsd_outlet", "outlet RSD [-]"), ("lacey_outlet", "outlet Lacey index [-]"))


def verdicts(preds: list[Prediction], baseline: str = "baseline") -> list[dict[str, Any]]:
    """:func:`judge` for every prediction that is not a run's own PBM, calibrated on the
    baseline's self-built PBM (the accuracy the hybrid shows on the run it is built from)."""
    own = {p.run: p.rows for p in preds if p.source == "self"}
    calibration = own.get(baseline)
    out = []
    for p in preds:
        if p.source == "self":
            continue
        if not p.rows:
            out.append({"run": p.run, "source": p.source, "verdict": f"not predicted: {p.note}", "judged": None})
            continue
        judged = judge(p.rows, own[p.run], calibration)
        out.append({"run": p.run, "source": p.source, "verdict": verdict_text(judged), "judged": judged})
    return out


def plot_parity(preds: list[Prediction], path: Path) -> None:
    """Predicted against DEM, one panel per quantity, the DEM's 95 % interval as error bars."""
    fig = Figure(figsize=(13, 6.5), layout="constrained")
    axes = fig.subplots(2, 4).ravel()
    for ax, (key, label) in zip(axes, PARITY):
        lo_all, hi_all = [], []
        for p in preds:
            row = next((r for r in p.rows if r["key"] == key), None)
            if row is None or row.get("dem") is None or not np.isfinite(row["dem"]):
                continue
            for mode in MODES:
                value = row.get(f"pbm_{mode}")
                if value is None or not np.isfinite(value):
                    continue
                err = [[max(row["dem"] - row["dem_ci_low"], 0)], [max(row["dem_ci_high"] - row["dem"], 0)]]
                ax.errorbar([row["dem"]], [value], xerr=err, fmt=MODE_MARKERS[mode], ms=5,
                            color=SOURCE_COLOURS[p.source], mfc="none" if mode == "velocity" else None, lw=0.8)
                lo_all += [row["dem_ci_low"], value]
                hi_all += [row["dem_ci_high"], value]
        if lo_all:  # one range for both axes: the diagonal is the 45-degree line of a perfect prediction
            lo, hi = min(lo_all), max(hi_all)
            pad = 0.05 * (hi - lo or abs(hi) or 1)
            ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="k", lw=0.6, ls="--")
            ax.set_xlim(lo - pad, hi + pad)
            ax.set_ylim(lo - pad, hi + pad)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("DEM", fontsize=8)
        ax.set_ylabel("PBM", fontsize=8)
        ax.tick_params(labelsize=7)
    handles = [axes[0].plot([], [], "o", color=c, label=s)[0] for s, c in SOURCE_COLOURS.items()]
    handles += [axes[0].plot([], [], m, color="k", mfc="none" if mode == "velocity" else None, label=f"{mode} rates")[0]
                for mode, m in MODE_MARKERS.items()]
    fig.legend(handles=handles, loc="outside lower center", ncol=5, fontsize=8)
    fig.savefig(path, dpi=110)


def plot_profiles(preds: list[Prediction], runs: list[str], path: Path) -> None:
    """The steady hold-up per axial slice of every run: DEM with its interval, each source's PBM."""
    fig = Figure(figsize=(3.2 * len(runs), 3.8), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(runs), sharey=True))
    for ax, run in zip(axes, runs):
        mine = [p for p in preds if p.run == run and p.rows]
        if mine:
            rows = sorted((r for r in mine[0].rows if r["key"].startswith("holdup_slice_")),
                          key=lambda r: int(r["key"].rsplit("_", 1)[1]))
            if rows:
                slices = np.arange(1, len(rows) + 1)
                ax.fill_between(slices, [r["dem_ci_low"] for r in rows], [r["dem_ci_high"] for r in rows],
                                color="#b2182b", alpha=0.25)
                ax.plot(slices, [r["dem"] for r in rows], color="#b2182b", lw=2)
            for p in mine:
                prow = sorted((r for r in p.rows if r["key"].startswith("holdup_slice_")),
                              key=lambda r: int(r["key"].rsplit("_", 1)[1]))
                for mode in MODES:
                    ax.plot(np.arange(1, len(prow) + 1), [r[f"pbm_{mode}"] for r in prow],
                            color=SOURCE_COLOURS[p.source], ls="--" if mode == "velocity" else "-", lw=1)
        ax.set_title(run, fontsize=9)
        ax.set_xlabel("axial slice (inlet → outlet)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("particles", fontsize=8)
    handles = [axes[0].plot([], [], color="#b2182b", lw=2, label="DEM (band: 95 %)")[0]]
    handles += [axes[0].plot([], [], color=c, label=f"PBM from {s}")[0] for s, c in SOURCE_COLOURS.items()]
    handles += [axes[0].plot([], [], color="k", ls=ls, lw=1, label=f"{mode} rates")[0]
                for mode, ls in (("velocity", "--"), ("measured", "-"))]
    fig.legend(handles=handles, loc="outside lower center", ncol=6, fontsize=8)
    fig.savefig(path, dpi=110)


def _campaign_rows(sides: dict[str, DemSide]) -> list[dict[str, Any]]:
    rows = []
    labels = {c.name: c.label for c in CHANGES}
    for name, side in sides.items():
        summary = side.results.summary
        pooled, steady = summary.get("pooled_rtd") or {}, summary.get("steady") or {}
        rows.append({"run": name, "change": labels.get(name, name), "source": side.source, "key": side.key,
                     "dem_wall_time_s": side.provenance.get("wall_time_s"),
                     "holdup": (steady.get("holdup") or {}).get("value"),
                     "mean_residence_time_s": (pooled.get("mean_residence_time_s") or {}).get("value"),
                     "tracers": pooled.get("n_entered"),
                     "recovered": (pooled.get("recovered_fraction") or {}).get("value")})
    return rows


def campaign_span_s(sides: dict[str, DemSide]) -> float | None:
    """Elapsed time of the campaign's solver runs [s]: from the first run's start to the
    last one's end, each start taken as its end minus its recorded wall time (so a resumed
    run counts from its first attempt). None when a run lacks the timestamps."""
    starts, ends = [], []
    for side in sides.values():
        finished, wall = side.provenance.get("run_finished"), side.provenance.get("wall_time_s")
        if not finished or wall is None:
            return None
        end = _dt.datetime.fromisoformat(str(finished)).timestamp()
        starts.append(end - float(wall))
        ends.append(end)
    return max(ends) - min(starts) if ends else None


def render_report(campaign: list[dict[str, Any]], judged: list[dict[str, Any]], figures: dict[str, str],
                  budget: dict[str, Any] | None = None, span_s: float | None = None,
                  step_section: str | None = None) -> str:
    """The validation page: the campaign, a verdict per change, the numbers behind each."""
    total = sum(r["dem_wall_time_s"] or 0 for r in campaign)
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>Validation campaign</title>",
             "<style>body{font-family:sans-serif;max-width:1300px;margin:auto}table{border-collapse:collapse;"
             "font-size:13px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}"
             "td:first-child,th:first-child{text-align:left}.no{background:#fdd}.yes{background:#dfd}</style>",
             "</head><body><h1>Does the hybrid predict what it was not built from?</h1>",
             "<p>Each run below is a real LIGGGHTS run of the <code>validation</code> preset with one factor "
             "changed. Each is predicted by PBMs built without it: from the baseline DEM alone (length by "
             "rescaled compartments, rpm by velocities scaled with the speed, feed with unchanged velocities), "
             "and from the table library (rpm interpolated between the other runs). A quantity is predicted "
             "when |prediction − DEM| ≤ the hybrid's relative error on the baseline (its PBM against its DEM) "
             "× the new DEM value + half the new DEM's 95 % interval: as good as the hybrid is where it was "
             "built. The self-built PBM (the run's own tables) is shown for reference.</p>",
             "<h2>Campaign</h2><table><tr><th>run</th><th>change</th><th>DEM from</th><th>DEM wall time [s]</th>"
             "<th>steady hold-up</th><th>mean residence time [s]</th><th>tracers</th><th>recovered</th></tr>"]
    for r in campaign:
        parts.append(f"<tr><td>{html.escape(r['run'])}</td><td>{html.escape(r['change'])}</td>"
                     f"<td>{html.escape(r['source'])}</td><td>{fmt(r['dem_wall_time_s'])}</td>"
                     f"<td>{fmt(r['holdup'])}</td><td>{fmt(r['mean_residence_time_s'])}</td>"
                     f"<td>{fmt(r['tracers'])}</td><td>{fmt(r['recovered'])}</td></tr>")
    span = "" if span_s is None else (f"; elapsed from the first run's start to the last one's end: "
                                      f"{span_s / 3600:.2f} h (runs that overlap count once)")
    parts.append(f"</table><p>Sum of the runs' DEM wall times: {total / 3600:.2f} h{span}.</p>")
    parts.append("<h2>Verdicts</h2><table><tr><th>run</th><th>predicted from</th><th>velocity rates</th>"
                 "<th>measured rates</th><th>verdict</th></tr>")
    for v in judged:
        cells = []
        for mode in MODES:
            j = (v["judged"] or {}).get(mode)
            cells.append("<td>–</td>" if j is None else
                         f"<td class='{'yes' if j['predicts'] else 'no'}'>{len(j['rows']) - len(j['failing'])}"
                         f"/{len(j['rows'])} ok</td>")
        parts.append(f"<tr><td>{html.escape(v['run'])}</td><td>{html.escape(v['source'])}</td>{''.join(cells)}"
                     f"<td>{html.escape(v['verdict'])}</td></tr>")
    parts.append("</table>")
    for name in ("parity", "profiles"):
        if name in figures:
            parts.append(f"<p><img src='{figures[name]}' style='max-width:100%'></p>")
    if budget is not None:
        parts.append("<h2>How little DEM does the PBM need?</h2><p>PBMs built from the baseline's first T "
                     "seconds (the transient as measured, the steady flow seen by T held for the rest), each "
                     "quantity against the same PBM built from the whole run, judged by the half width of the "
                     "DEM's 95 % interval.</p><table><tr><th>rate mode</th><th>smallest T [s]</th>"
                     "<th>fraction of the run</th><th>without the slice hold-ups [s]</th></tr>")
        for mode, best in budget["smallest_T"].items():
            other = budget["smallest_T_without_slices"].get(mode, {})
            parts.append(f"<tr><td>{mode}</td><td>{fmt(best['t_s'])}</td><td>{fmt(best['fraction'], 2)}</td>"
                         f"<td>{fmt(other.get('t_s'))}</td></tr>")
        parts.append("</table>")
        if "budget" in figures:
            parts.append(f"<p><img src='{figures['budget']}' style='max-width:100%'></p>")
    if step_section:
        parts.append(step_section)
    parts.append("<h2>The numbers behind each verdict</h2>")
    for v in judged:
        if not v["judged"]:
            continue
        parts.append(f"<h3>{html.escape(v['run'])}, predicted from {html.escape(v['source'])}</h3>"
                     "<table><tr><th>quantity</th><th>DEM</th><th>95 % interval</th>"
                     + "".join(f"<th>{m}: predicted</th><th>{m}: self-built</th><th>{m}: ok</th>" for m in MODES)
                     + "</tr>")
        by_mode = {m: {r["key"]: r for r in v["judged"][m]["rows"]} for m in MODES}
        keys = list(dict.fromkeys(k for m in MODES for k in by_mode[m]))
        for key in keys:
            first = next(by_mode[m][key] for m in MODES if key in by_mode[m])
            cells = ""
            for m in MODES:
                r = by_mode[m].get(key)
                cells += ("<td>–</td><td>–</td><td>–</td>" if r is None else
                          f"<td>{fmt(r['predicted'])}</td><td>{fmt(r['self'])}</td>"
                          f"<td class='{'yes' if r['ok'] else 'no'}'>{fmt(r['ok'])}</td>")
            parts.append(f"<tr><td>{html.escape(first['quantity'])}</td><td>{fmt(first['dem'])}</td>"
                         f"<td>{fmt(first['dem_ci_low'])} – {fmt(first['dem_ci_high'])}</td>{cells}</tr>")
        parts.append("</table>")
    parts.append("</body></html>")
    return "\n".join(parts)


def validation_report(out_dir: str | Path = "results/validation", runs_root: str | Path = "runs/validation",
                      fresh: bool = False, nprocs: int | None = None, log: Log = stderr_log,
                      reference_dir: Path = REFERENCE_DIR, solver: bool = True) -> Path:
    """``make validate``: the campaign (:func:`run_campaign`), every prediction and verdict,
    ``summary.json``, the figures and ``report.html`` in ``out_dir``. Returns the page."""
    out_dir = writable_directory(out_dir, "validation output directory")
    configs = campaign_configs()
    sides = run_campaign(runs_root, fresh=fresh, nprocs=nprocs, log=log, reference_dir=reference_dir,
                         configs=configs, solver=solver)
    preds = predictions(sides, configs, log=log)
    judged = verdicts(preds)
    campaign = _campaign_rows(sides)
    span_s = campaign_span_s(sides)
    base = sides["baseline"].results
    budget_t = [round(f * base.table.t_end / base.table.window_s) * base.table.window_s for f in BUDGET_FRACTIONS]
    log("how little DEM: PBMs from the baseline's first T seconds")
    try:
        budget = budget_study(base, configs["baseline"], budget_t, log=log)
    except ValueError as exc:  # a baseline that never reaches the steady state has no budget
        log(f"no DEM budget: {exc}")
        budget = None
    log("the dynamic check: the feed-step run")
    try:
        step_side = run_step(runs_root, fresh=fresh, nprocs=nprocs, log=log, solver=solver)
        step = step_comparison(step_side, sides["baseline"], step_config())
    except LookupError as exc:  # neither shipped nor cached, and the solver may not run
        log(f"no dynamic check: {exc}")
        step = None
    try:
        figures = {"parity": "parity.png", "profiles": "profiles.png", "budget": "budget.png"}
        if step is not None:
            figures["step"] = "step.png"
            plot_step(step, out_dir / figures["step"])
        plot_parity(preds, out_dir / figures["parity"])
        plot_profiles(preds, list(sides), out_dir / figures["profiles"])
        if budget is not None:
            plot_budget(budget, out_dir / figures["budget"])
        else:
            figures.pop("budget")
        write_json(out_dir / "summary.json", json_ready({
            "campaign": campaign, "campaign_elapsed_s": span_s, "verdicts": judged, "dem_budget": budget,
            "step_response": None if step is None else summary_rows(step),
            "predictions": [{"run": p.run, "source": p.source, "note": p.note, "agreement": p.rows} for p in preds]}))
        page = out_dir / "report.html"
        page.write_text(render_report(campaign, judged, figures, budget, span_s,
                                      None if step is None else step_html(step, figures.get("step"))))
    except OSError as exc:
        raise OutputError(f"cannot write the validation report in {out_dir}: {os_reason(exc)}") from exc
    return page

