"""The validation campaign's numbers: PBMs built without a change predict the DEM run that
has it, and the campaign's rule judges each prediction (see :mod:`workflows.products.validate`)."""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field
from typing import Any

from coupling.errors import ConfigError
from coupling.tables import VelocityTable
from pbm.config import PbmConfig
from pbm.fill import fill_samples, fit_fill_law
from pbm.model import supported_modes
from pbm.studies import interpolate_tables, scale_blender, scale_speed
from workflows.analysis.agreement import MODES, AgreementRow, Judged, agreement_rows, run_modes
from workflows.config import Config, same_but_feed, same_but_speed
from workflows.pipeline.log import Log, stderr_log
from workflows.pipeline.results import pbm_config_for, rtd_pulse, run_operating_point
from workflows.pipeline.stages import DemSide
from workflows.prediction.calibration import Check

# --------------------------------------------------------------------------- predictions
#: Agreement rows that are diagnostics of the RTD's definition, not predictions to judge.
NOT_JUDGED = ("rtd_recovered_fraction",)


#: the sources that predict with flow that follows the fill (pbm.fill)
FILL_SOURCES = ("baseline + fill law", "library + fill law")


def feed_library(configs: dict[str, Config], baseline: str = "baseline") -> list[str]:
    """The runs that differ from the baseline only in the feed rate (and the duration), the
    baseline included: the runs a fill law is fitted from."""
    same = same_but_feed(configs[baseline])
    return [name for name, c in configs.items() if same_but_feed(c) == same]


@dataclass(frozen=True)
class Source:
    """What a PBM prediction is built from: a ``table``, and with ``rate_law`` = "fill" the
    law's exponents per rate mode (``exponents``; a mode missing: the law fitted to the
    table's own windows)."""

    table: VelocityTable
    rate_law: str = "table"
    exponents: dict[str, list[list[float]]] = field(default_factory=dict)

    def mode_updates(self) -> dict[str, dict[str, Any]]:
        """Per rate mode, the PbmConfig fields this source sets."""
        return {mode: {"rate_law": self.rate_law, "fill_exponents": self.exponents.get(mode)} for mode in MODES}


def library_law(sides: dict[str, DemSide], runs: list[str]) -> dict[str, list[list[float]]]:
    """Per rate mode, the fill law's exponents fitted to ``runs`` (their steady points; one
    run: its filling transient, :func:`pbm.fill.fit_fill_law`)."""
    out = {}
    for mode in MODES:
        tables = [sides[r].table for r in runs]
        if mode == "phases" or all(mode in supported_modes(t) for t in tables):
            out[mode] = fit_fill_law([fill_samples(t, mode) for t in tables]).beta.tolist()
    return out


def prediction_tables(
    sides: dict[str, DemSide], configs: dict[str, Config], baseline: str = "baseline"
) -> dict[str, dict[str, Source | str]]:
    """For every run: its own table ("self"), the prediction from the baseline alone
    ("baseline": compartments rescaled to a new length, velocities and rates scaled by the
    rpm ratio, a new feed rate with the velocities unchanged), and from the table library
    ("library": interpolated in rpm between the other runs that differ only in rpm). A run
    of the feed library also gets two predictions with flow that follows the fill
    (:mod:`pbm.fill`): "baseline + fill law", the baseline's steady rates under the law of
    its own windows (its filling transient: one DEM run); and "library + fill law", the
    steady rates of the nearest other run in feed (one with a phase model if any) under
    the law of the other runs' steady points (leave one out). A prediction that cannot be
    made is a string saying why. Speeds, lengths and feed rates are each run's operating
    point's (:func:`workflows.pipeline.results.run_operating_point`)."""
    base_table = sides[baseline].table
    point = {name: run_operating_point(side.table, configs[name]) for name, side in sides.items()}
    feed_runs = [r for r in feed_library(configs, baseline) if r in sides]
    feed = {r: point[r].feed_rate_total_per_s for r in feed_runs}
    out: dict[str, dict[str, Source | str]] = {}
    for name, config in configs.items():
        if name not in sides:  # a run the campaign does not have (yet)
            continue
        tables: dict[str, Source | str] = {"self": Source(sides[name].table)}
        if name != baseline:
            table = base_table
            length_factor = point[name].length_m / point[baseline].length_m
            if not math.isclose(length_factor, 1.0):
                table = scale_blender(table, length_factor=length_factor)
            speed = point[name].impeller_rpm / point[baseline].impeller_rpm
            if not math.isclose(speed, 1.0):
                table = scale_speed(table, speed)
            tables["baseline"] = Source(table)
        same = same_but_speed(config)
        library = [
            (point[o].impeller_rpm, sides[o].table)
            for o, other in configs.items()
            if o != name and o in sides and same_but_speed(other) == same
        ]
        if len(library) >= 2:
            try:
                tables["library"] = Source(interpolate_tables(library, point[name].impeller_rpm))
            except ConfigError as exc:
                tables["library"] = str(exc)
        if name in feed_runs and name != baseline:
            tables[FILL_SOURCES[0]] = Source(base_table, "fill")
            others = [r for r in feed_runs if r != name]
            if len(others) >= 2:
                with_phases = [r for r in others if sides[r].table.phases is not None] or others
                nearest = min(with_phases, key=lambda r: abs(math.log(feed[r] / feed[name])))
                tables[FILL_SOURCES[1]] = Source(sides[nearest].table, "fill", library_law(sides, others))
            else:
                tables[FILL_SOURCES[1]] = f"the feed library holds {len(others)} other run(s); a law needs two"
        out[name] = tables
    return out


@dataclass
class Prediction:
    """One PBM source's agreement rows against one run's DEM."""

    run: str
    source: str
    rows: list[AgreementRow] = field(default_factory=list)
    note: str = ""


def predictions(sides: dict[str, DemSide], configs: dict[str, Config], log: Log = stderr_log) -> list[Prediction]:
    """Every source of :func:`prediction_tables` for every run, in both rate modes, as the
    agreement table against that run's DEM (same entry window, horizon and steady rule)."""
    out = []
    for name, tables in prediction_tables(sides, configs).items():
        config, dem = configs[name], sides[name].results
        for source, built in tables.items():
            if isinstance(built, str):
                out.append(Prediction(name, source, note=built))
                continue
            log(f"PBM of {name} from {source}")
            table = built.table
            modes = run_modes(
                table,
                prediction_config(config, table, dem.summary),
                config.steady_state,
                dem.summary,
                built.mode_updates(),
            )
            out.append(
                Prediction(name, source, agreement_rows(dem.summary, dem.particles, modes, dem.steady_outlet_counts()))
            )
    return out


def prediction_config(config: Config, table: VelocityTable, dem_summary) -> PbmConfig:
    """The PBM configuration that predicts the run of ``config`` from ``table``: the run's
    feed and RTD pulse, and its duration when the run is longer than the table (a slower
    feed): the table's last window then holds on."""
    pbm = pbm_config_for(config, table, rtd_pulse(dem_summary))
    if table.t_end < config.dem.operation.duration_s:
        pbm = pbm.model_copy(update={"duration_s": config.dem.operation.duration_s})
    return pbm


@dataclass(frozen=True)
class PredictedQuantity:
    """One quantity of one prediction judged by the campaign's rule: ``judged.value`` the
    prediction, ``judged.reference`` the DEM, ``judged.tolerance`` = ``model_error`` + the
    half width of the DEM's interval; ``self_value`` the run's own self-built PBM, reported
    beside it."""

    judged: Judged
    dem_ci_low: float
    dem_ci_high: float
    self_value: float
    model_error: float

    @property
    def key(self) -> str:
        return self.judged.key

    @property
    def ok(self) -> bool:
        return self.judged.ok

    def record(self) -> dict[str, Any]:
        j = self.judged
        return {
            "key": j.key,
            "quantity": j.quantity,
            "dem": j.reference,
            "dem_ci_low": self.dem_ci_low,
            "dem_ci_high": self.dem_ci_high,
            "predicted": j.value,
            "self": self.self_value,
            "error": j.error,
            "model_error": self.model_error,
            "tolerance": j.tolerance,
            "ok": j.ok,
        }


@dataclass(frozen=True)
class ModePrediction:
    """One rate mode's verdict on a prediction: it predicts the change when every judged
    quantity is ok; ``missing``: quantities that could not be judged (left out)."""

    rows: tuple[PredictedQuantity, ...]
    missing: tuple[str, ...] = ()

    @property
    def failing(self) -> list[str]:
        return [r.key for r in self.rows if not r.ok]

    @property
    def predicts(self) -> bool:
        return bool(self.rows) and not self.failing

    def record(self) -> dict[str, Any]:
        return {
            "rows": [r.record() for r in self.rows],
            "missing": list(self.missing),
            "failing": self.failing,
            "predicts": self.predicts,
        }


def judge(
    predicted: list[AgreementRow], own: list[AgreementRow], calibration: list[AgreementRow] | None = None
) -> dict[str, ModePrediction]:
    """The verdict on one prediction (module docstring, 3.): per rate mode and quantity,
    the error |prediction - DEM| against the tolerance = the hybrid's own error on the
    ``calibration`` run (its self-built PBM against its DEM, default ``own``), relative to
    that DEM value and scaled to this one (absolute for the RTD overlap, whose ideal is 1),
    plus the half width of this DEM's interval (:class:`~workflows.analysis.agreement.Judged`).
    The run's own self-built PBM (``own``) is reported beside it (NaN where it lacks the
    mode). Quantities missing from the prediction or the calibration are left out and listed."""
    own_rows = {row.key: row for row in own}
    cal_rows = {row.key: row for row in (calibration if calibration is not None else own)}
    verdict: dict[str, ModePrediction] = {}
    for mode in MODES:
        rows, missing = [], []
        for row in predicted:
            key = row.key
            if key in NOT_JUDGED:
                continue
            cal, mine = cal_rows.get(key), own_rows.get(key)
            dem, pred = row.dem, row.value(mode)
            self_value = math.nan if mine is None else mine.value(mode)
            cal_dem, cal_pbm = (math.nan, math.nan) if cal is None else (cal.dem, cal.value(mode))
            half = row.half_width(mode)
            # the self-built PBM is only reported: a run whose own results lack a rate mode
            # (results made before its phase model) is still judged in it
            values = (dem, pred, cal_dem, cal_pbm, half)
            if not all(math.isfinite(v) for v in values) or (key != "rtd_overlap" and cal_dem == 0):
                missing.append(key)
                continue
            model_error = (
                abs(cal_pbm - cal_dem) if key == "rtd_overlap" else abs(cal_pbm - cal_dem) / abs(cal_dem) * abs(dem)
            )
            judged = Judged(key, row.quantity, pred, dem, model_error + half)
            rows.append(PredictedQuantity(judged, row.dem_ci_low, row.dem_ci_high, self_value, model_error))
        verdict[mode] = ModePrediction(tuple(rows), tuple(missing))
    return verdict


@dataclass(frozen=True)
class PredictionVerdict:
    """The campaign's verdict on one prediction (one run, one source): its text and, when it
    could be judged, each rate mode's :class:`ModePrediction`."""

    run: str
    source: str
    verdict: str
    judged: dict[str, ModePrediction] | None

    def record(self) -> dict[str, Any]:
        return {
            "run": self.run,
            "source": self.source,
            "verdict": self.verdict,
            "judged": None if self.judged is None else {m: v.record() for m, v in self.judged.items()},
        }


def verdicts(preds: list[Prediction], baseline: str = "baseline") -> list[PredictionVerdict]:
    """:func:`judge` for every prediction that is not a run's own PBM, calibrated on the
    baseline's self-built PBM (the accuracy the hybrid shows on the run it is built from)."""
    own = {p.run: p.rows for p in preds if p.source == "self"}
    calibration = own.get(baseline)
    out = []
    for p in preds:
        if p.source == "self":
            continue
        if not p.rows:
            out.append(PredictionVerdict(p.run, p.source, f"not predicted: {p.note}", None))
            continue
        judged = judge(p.rows, own[p.run], calibration)
        out.append(PredictionVerdict(p.run, p.source, verdict_text(judged), judged))
    return out


@dataclass(frozen=True)
class LawVerdict:
    """A campaign run predicted by the library's law fitted without it
    (:mod:`workflows.prediction.calibration`): how many quantities hold the DEM's value in
    their prediction interval, how many predictions lie in the DEM's interval widened by
    the seed scatter, of ``n``; the verdict and its text."""

    run: str
    file: str
    covered: int
    inside_widened: int
    n: int
    predicts: bool
    verdict: str

    def record(self) -> dict[str, Any]:
        return {
            "run": self.run,
            "file": self.file,
            "covered": self.covered,
            "inside_widened": self.inside_widened,
            "n": self.n,
            "predicts": self.predicts,
            "verdict": self.verdict,
        }


def law_verdicts(sides: dict[str, DemSide], check: Check) -> list[LawVerdict]:
    """:class:`LawVerdict` of every campaign run that is a run of the library (the same DEM
    inputs: the same results file name)."""
    out = []
    library = set(check.runs())
    for name, side in sides.items():
        file = side.cache_file.name
        if file not in library:
            continue
        rows = check.of_run(file)
        predicts, text = check.verdict(file)
        out.append(
            LawVerdict(
                name,
                file,
                sum(r.covered for r in rows),
                sum(r.inside_widened for r in rows),
                len(rows),
                predicts,
                text,
            )
        )
    return out


def campaign_span_s(sides: dict[str, DemSide]) -> float | None:
    """Elapsed time of the campaign's solver runs [s]: the time during which at least one
    of them ran (runs side by side count once; days between runs made in different
    sessions do not count), each run taken as its recorded wall time up to its end. None
    when a run lacks the timestamps."""
    spans = []
    for side in sides.values():
        finished, wall = side.provenance.get("run_finished"), side.provenance.get("wall_time_s")
        if not finished or wall is None:
            return None
        end = _dt.datetime.fromisoformat(str(finished)).timestamp()
        spans.append((end - float(wall), end))
    total, reach = 0.0, -math.inf
    for start, end in sorted(spans):
        if end > reach:
            total += end - max(start, reach)
            reach = end
    return total if spans else None


def verdict_text(verdict: dict[str, ModePrediction]) -> str:
    """The plain verdict of a change from :func:`judge`'s numbers; when no rate mode
    predicts it, the failures of the mode that came nearest."""
    good = [mode for mode in MODES if mode in verdict and verdict[mode].predicts]
    if good:
        return f"the hybrid predicts this ({' and '.join(good)} rates)"
    judged = [mode for mode in MODES if mode in verdict and verdict[mode].rows]
    if not judged:
        return "this needs a new DEM run (no quantity could be judged)"
    best = min(judged, key=lambda mode: len(verdict[mode].failing))
    failing = verdict[best].failing
    slices = [key for key in failing if key.startswith("holdup_slice_")]
    named = [key for key in failing if key not in slices]
    named += [f"hold-up of {len(slices)} axial slice{'s' if len(slices) > 1 else ''}"] if slices else []
    return (
        f"this needs a new DEM run (nearest: {best} rates, {len(failing)} of {len(verdict[best].rows)} "
        f"quantities outside tolerance: {', '.join(named)})"
    )
