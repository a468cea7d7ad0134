"""Does flow that follows the fill predict a new feed rate? The feed library, each run
predicted without it (``pbmdem study fill``).

The runs are the validation campaign's that differ from its baseline only in the feed
rate (shipped or cached). Each is predicted three ways, in every rate mode, and judged
against its own DEM's 95 % intervals:

* ``linear``: the baseline's table, the rates of its windows (the paper's PBM);
* ``baseline law``: the baseline's steady rates under the law fitted to the baseline's
  own windows (its filling transient: one DEM run, no other);
* ``library law``: the steady rates of the nearest other run in feed under the law fitted
  to the steady points of all the other runs (leave one out).

``--unseen FILE ...``: DEM results of the same blender and speed at feeds outside the
campaign, each predicted the same three ways from the whole library.

Prints the hold-up, the outflow and the pooled RTD's mean and variance against the DEM's,
and writes ``results/bench/fill.json`` (every value, interval, the laws' exponents and each
library run's steady slice fills and rates) and
``fill.png`` beside it (hold-up and mean residence time against the feed).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from coupling.errors import ConfigError
from coupling.jsonable import json_ready, write_json
from pbm.fill import fill_samples, fit_fill_law
from pbm.model import supported_modes
from pbm.rtd import pooled_rtd
from pbm.simulate import simulate
from workflows.analysis.agreement import PbmMode, agreement_rows
from workflows.analysis.validation import feed_library, prediction_config
from workflows.config import same_but_feed
from workflows.pipeline.log import stderr_log
from workflows.pipeline.results import load_results
from workflows.products.validate import campaign_configs, run_campaign
from workflows.report.fill import plot_fill
from workflows.studies import distinct_runs

HELP = "the feed library: each feed rate predicted by the linear PBM and the fill law, leave one out"
OUT = Path("results/bench/fill.json")
QUANTITIES = ("holdup", "outflow_per_s", "mean_residence_time_s", "rtd_variance_s2")
MODES = ("measured", "velocity", "phases")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs-root", default="runs/validation", help="campaign runs and cache (default: %(default)s)")
    parser.add_argument("--out-file", type=Path, default=OUT, help="JSON written (default: %(default)s)")
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    parser.add_argument(
        "--unseen",
        nargs="*",
        default=[],
        metavar="FILE",
        help="DEM results files of the same blender and speed at other feeds, predicted from the whole library",
    )


def library_runs(runs_root: str) -> tuple[dict, dict]:
    """(sides, configs) of the campaign's feed library (shipped or cached)."""
    configs = campaign_configs()
    library = {name: configs[name] for name in feed_library(configs)}
    sides = run_campaign(runs_root, configs=library, solver=False, log=lambda _m: None)
    return sides, {name: library[name] for name in sides}


def predict(table, config, dem, mode: str, exponents=None, rate_law: str = "table"):
    cfg = prediction_config(config, table, dem.summary).model_copy(
        update={"rates": mode, "rate_law": rate_law, "fill_exponents": exponents}
    )
    result = simulate(table, cfg, steady=config.steady_state)
    spec = dem.summary.pooled_rtd
    pooled = pooled_rtd(
        table, cfg, entry_window=spec.entry_window_s, horizon_s=spec.horizon_s, schedule=result.schedule
    )
    rows = agreement_rows(dem.summary, dem.particles, {mode: PbmMode(mode, result, pooled)}, dem.steady_outlet_counts())
    return {r.key: r for r in rows}


def run(args: argparse.Namespace) -> int:
    unseen = distinct_runs(args.unseen, "--unseen")  # before the library's runs are read
    sides, configs = library_runs(args.runs_root)
    if "baseline" not in sides or len(sides) < 3:
        stderr_log(f"the feed library needs the baseline and two other feed rates; found {sorted(sides)}")
        return 1
    feed = {name: c.dem.operation.feed_rate_total_per_s for name, c in configs.items()}
    # targets: every library run (predicted from the others), then the unseen runs (from all)
    targets = [(name, sides[name].results, configs[name]) for name in sorted(sides, key=feed.get)]
    same = same_but_feed(configs["baseline"])
    for path in unseen:
        results, config = load_results(path)
        if same_but_feed(config) != same:
            raise ConfigError(f"{path}: not a run of the feed library's blender and speed (it differs beyond the feed)")
        targets.append((f"{Path(path).name} ({config.dem.operation.feed_rate_total_per_s:g} /s)", results, config))
    record: dict = {"runs": feed, "predictions": [], "laws": {}, "steady_points": {}}
    base = sides["baseline"].table
    for mode in args.modes:
        samples = {name: fill_samples(side.table, mode) for name, side in sides.items()}
        record["steady_points"][mode] = {
            name: {"slice_fill": s.steady_fill.tolist(), "forward_backward_rates": s.steady_rates()[0].tolist()}
            for name, s in samples.items()
        }
        own = fit_fill_law([samples["baseline"]])
        record["laws"][f"{mode}/baseline"] = {"form": own.form, "beta": own.beta.tolist(), "scores": own.scores}
        for target, dem, cfg in targets:
            if target == "baseline":
                continue
            others = [n for n in sides if n != target]
            lib = fit_fill_law([samples[n] for n in others])
            record["laws"][f"{mode}/without {target}"] = {"form": lib.form, "beta": lib.beta.tolist()}
            # the nearest other run whose table carries this mode (the phase model needs sequences)
            usable = [n for n in others if mode in supported_modes(sides[n].table)]
            wanted = cfg.dem.operation.feed_rate_total_per_s
            nearest = min(usable, key=lambda n: abs(np.log(feed[n] / wanted)))
            sources = {
                "linear": predict(base, cfg, dem, mode),
                "baseline law": predict(base, cfg, dem, mode, own.beta.tolist(), "fill"),
                f"library law ({nearest})": predict(sides[nearest].table, cfg, dem, mode, lib.beta.tolist(), "fill"),
            }
            for source, rows in sources.items():
                line = [f"{mode:9s} {target:10s} {source:24s}"]
                for q in QUANTITIES:
                    r = rows.get(q)
                    if r is None:
                        continue
                    v = r.value(mode)
                    line.append(
                        f"{q} {v:7.1f} [{r.dem_ci_low:.1f}, {r.dem_ci_high:.1f}]{'*' if r.inside(mode) else ' '}"
                    )
                    record["predictions"].append(
                        {
                            "mode": mode,
                            "run": target,
                            "feed_per_s": wanted,
                            "source": source,
                            "quantity": q,
                            "pbm": v,
                            "dem": r.dem,
                            "dem_ci": [r.dem_ci_low, r.dem_ci_high],
                            "inside": r.inside(mode),
                        }
                    )
                print("  ".join(line), flush=True)
    write_json(args.out_file, json_ready(record))
    figure = plot_fill(record, args.out_file.with_suffix(".png"))
    print(f"(* inside the DEM's 95 % interval) written {args.out_file} and {figure}")
    return 0
