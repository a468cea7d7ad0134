"""The validation campaign's numbers: PBMs built without a change predict the DEM run that
has it, and the campaign's rule judges each prediction (see :mod:`workflows.products.validate`)."""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from coupling.errors import ConfigError
from coupling.tables import VelocityTable
from pbm.studies import interpolate_tables, scale_blender, scale_speed
from workflows.analysis.agreement import MODES, agreement_rows, half_width, run_modes
from workflows.config import Config, config_without
from workflows.pipeline.stages import DemSide, Log, pbm_config_for, rtd_pulse, stderr_log


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
