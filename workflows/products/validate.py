"""Does the hybrid predict what it was not built from? The validation campaign.

1. The campaign file ``workflows/presets/campaigns/validation.toml``
   (:func:`workflows.products.campaign.load_campaign`) -- the ``validation`` preset (coarse
   particles, long enough for a pooled RTD) and one factor changed at a time: blender length
   x1.25 (more paddle stations at the same spacing), impeller 150 and 350 rpm, feed rate
   x0.5, x1.5 and x2. :func:`run_campaign` runs each
   through the normal DEM stage (LIGGGHTS, post-processing, cache by input hash), so an
   interrupted campaign continues where it stopped; the shipped campaign results in
   :data:`VALIDATION_DIR` serve a fresh clone without LIGGGHTS (``pbmdem validate``,
   ``make validate``; ``--fresh`` / ``FRESH=1`` reruns the campaign).
2. :func:`predictions` -- for every changed run, PBMs built from the baseline DEM alone
   (length by rescaling the compartments, feed with unchanged velocities, rpm with
   velocities and rates scaled by the rpm ratio), from the table library (rpm interpolated
   between the other runs' tables, leave one out), and the run's own tables ("self": what a
   new DEM run gives the PBM). Each in both rate modes, judged by the agreement table of
   :mod:`workflows.analysis.agreement` against that run's DEM and its intervals.
3. :func:`judge` -- the verdict from the numbers. A quantity is predicted when the
   prediction's distance from the DEM is no larger than the hybrid's own error on the
   baseline (its PBM built from the baseline's tables against the baseline's DEM, relative,
   scaled to the new value) plus the half width of the new DEM's 95 % interval: the
   prediction is as good as the hybrid is where it was built. The run's self-built PBM
   (what a new DEM run would give the PBM) is reported beside it, not used as the yardstick:
   where it is poor, a lenient yardstick would pass anything. A change is predicted ("the
   hybrid predicts this") when every judged quantity of a rate mode is; else "this needs a
   new DEM run", with the failing quantities of the mode that came nearest.
4. :func:`library_law_verdicts` -- beside those routes, each run that is also a run of the
   shipped DEM library predicted by the library's law fitted without it (``pbmdem
   predict``'s model, :mod:`workflows.prediction`): predicted when its mean residence time,
   RTD variance, Little's-law time and hold-up, and all but two of its other quantities, lie
   inside the DEM's interval widened by the seed scatter.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from coupling.errors import ConfigError, OutputError, error_line, os_reason
from coupling.files import replace_file, writable_directory
from coupling.jsonable import json_ready, write_json
from dem.run import can_resume, prepare_run
from workflows.analysis.budget import budget_study
from workflows.analysis.step import step_comparison
from workflows.analysis.validation import (
    LawVerdict,
    campaign_span_s,
    law_verdicts,
    library_law,
    predictions,
    verdicts,
)
from workflows.config import Config, load_preset, override
from workflows.pipeline.log import Log, stderr_log
from workflows.pipeline.stages import DemSide, dem_stage
from workflows.prediction import calibration
from workflows.prediction.library import load_model
from workflows.products.campaign import Campaign, load_campaign
from workflows.report.budget import plot_budget
from workflows.report.step import plot_step, step_html
from workflows.report.validation import plot_parity, plot_profiles, render_report
from workflows.shipped import LIBRARY_MODEL, STEP_DIR, VALIDATION_DIR


def campaign_configs(base: Config | None = None, campaign: Campaign | None = None) -> dict[str, Config]:
    """Each change's configuration (``campaign``, default the shipped validation campaign,
    on ``base``, default its preset), every one validated before any run starts."""
    campaign = campaign if campaign is not None else load_campaign()
    return campaign.configs(base)


def run_campaign(
    runs_root: str | Path = "runs/validation",
    fresh: bool = False,
    nprocs: int | None = None,
    log: Log = stderr_log,
    reference_dir: Path = VALIDATION_DIR,
    configs: dict[str, Config] | None = None,
    solver: bool = True,
) -> dict[str, DemSide]:
    """Every run of the campaign, in the campaign file's order: from the cache under
    ``runs_root``, the shipped results, else LIGGGHTS (an interrupted run continues from its
    newest restart file). ``fresh`` reruns every solver run; ``solver=False`` never starts
    LIGGGHTS: a run that is neither cached nor shipped is left out, with a line in the log
    (the baseline cannot be: LookupError)."""
    configs = configs if configs is not None else campaign_configs()
    sides = {}
    for name, config in configs.items():
        log(f"validation run {name}: starting, resuming or reusing")
        t0 = time.monotonic()
        try:
            sides[name] = campaign_run(config, runs_root, fresh, nprocs, log, reference_dir, solver)
        except LookupError:
            if name == "baseline":
                raise
            log(f"validation run {name}: neither cached nor shipped, and LIGGGHTS may not run: left out")
            continue
        log(f"validation run {name}: {sides[name].source} ({time.monotonic() - t0:.0f} s)")
    return sides


# --------------------------------------------------------------------------- the report
#: The DEM budgets studied on the baseline, as fractions of its duration.
BUDGET_FRACTIONS = (0.25, 0.3, 0.45, 0.6, 0.75, 1.0)


def validation_report(
    out_dir: str | Path = "results/validation",
    runs_root: str | Path = "runs/validation",
    fresh: bool = False,
    nprocs: int | None = None,
    log: Log = stderr_log,
    reference_dir: Path = VALIDATION_DIR,
    solver: bool = True,
) -> Path:
    """``make validate``: the campaign (:func:`run_campaign`), every prediction and verdict,
    ``summary.json``, the figures and ``report.html`` in ``out_dir``. Returns the page."""
    out_dir = writable_directory(out_dir, "validation output directory")
    changes = load_campaign()
    configs = changes.configs()
    sides = run_campaign(
        runs_root, fresh=fresh, nprocs=nprocs, log=log, reference_dir=reference_dir, configs=configs, solver=solver
    )
    preds = predictions(sides, configs, log=log)
    judged = verdicts(preds)
    law = library_law_verdicts(sides, log)
    campaign = _campaign_rows(sides, changes.labels())
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
        # the baseline's own law: the step predicted from that one steady DEM run alone
        step = step_comparison(step_side, sides["baseline"], step_config(), library_law(sides, ["baseline"]))
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
        write_json(
            out_dir / "summary.json",
            json_ready(
                {
                    "campaign": campaign,
                    "campaign_elapsed_s": span_s,
                    "verdicts": [v.record() for v in judged],
                    "library_law": [v.record() for v in law],
                    "dem_budget": None if budget is None else budget.record(),
                    "step_response": None if step is None else step.record(),
                    "predictions": [
                        {"run": p.run, "source": p.source, "note": p.note, "agreement": [r.record() for r in p.rows]}
                        for p in preds
                    ],
                }
            ),
        )
        page = out_dir / "report.html"
        replace_file(
            page,
            render_report(
                campaign,
                judged,
                figures,
                budget,
                span_s,
                None if step is None else step_html(step, figures.get("step")),
                law,
            ),
            "report",
        )
    except OSError as exc:
        raise OutputError(f"cannot write the validation report in {out_dir}: {os_reason(exc)}") from exc
    return page


def library_law_verdicts(sides: dict[str, DemSide], log: Log = stderr_log) -> list[LawVerdict]:
    """Each campaign run predicted by the shipped library's law fitted without it
    (:func:`workflows.analysis.validation.law_verdicts`); none, with a line in the log, when
    the library model is missing or unreadable."""
    try:
        model = load_model(LIBRARY_MODEL)
    except ConfigError as exc:
        log(f"no prediction from the library's law: {error_line(exc)}")
        return []
    log("the library's law: each campaign run predicted without it")
    return law_verdicts(sides, calibration.check(model))


STEP_OVERRIDES = ("dem.operation.step_time_s=80", "dem.operation.step_factor_a=2", "dem.operation.duration_s=170")


def step_config(base: Config | None = None) -> Config:
    """The validation preset with feeder A's step (validated before anything runs)."""
    base = base if base is not None else load_preset("validation")
    return override(base, *STEP_OVERRIDES).model_copy(update={"name": f"{base.name}-step_a_x2"})


def run_step(
    runs_root: str | Path = "runs/validation",
    fresh: bool = False,
    nprocs: int | None = None,
    log: Log = stderr_log,
    reference_dir: Path = STEP_DIR,
    solver: bool = True,
    config: Config | None = None,
) -> DemSide:
    """The step run: cached, shipped, or LIGGGHTS (an interrupted run resumes)."""
    config = config if config is not None else step_config()
    return campaign_run(config, runs_root, fresh, nprocs, log, reference_dir, solver)


def campaign_run(
    config: Config, runs_root: str | Path, fresh: bool, nprocs: int | None, log: Log, reference_dir: Path, solver: bool
) -> DemSide:
    """One run of the campaign through the DEM stage: cached, shipped, or LIGGGHTS; an
    interrupted run resumes from its restart file."""
    resume = solver and not fresh and can_resume(prepare_run(config.dem), runs_root)
    return dem_stage(
        config,
        runs_root=runs_root,
        np=nprocs,
        resume=resume,
        fresh=fresh,
        progress=False,
        log=log,
        reference_dir=reference_dir,
        solver=solver,
    )


def _campaign_rows(sides: dict[str, DemSide], labels: dict[str, str]) -> list[dict[str, Any]]:
    rows = []
    for name, side in sides.items():
        summary = side.results.summary
        pooled, steady = summary.pooled_rtd, summary.steady
        rows.append(
            {
                "run": name,
                "change": labels.get(name, name),
                "source": side.source,
                "key": side.key,
                "dem_wall_time_s": side.provenance.get("wall_time_s"),
                "holdup": (steady.get("holdup") or {}).get("value"),
                "mean_residence_time_s": pooled.mean_residence_time_s.value if summary.has_pooled_rtd else None,
                "tracers": None if pooled is None else pooled.n_entered,
                "recovered": pooled.recovered_fraction.value if summary.has_pooled_rtd else None,
            }
        )
    return rows
