"""``pbmdem study suggest``: DEM runs chosen one at a time by ``pbmdem library suggest``'s
rule against grids over the same domain: how many runs until the prediction targets are
met (coverage of the 95 % intervals at least 90 %; median half-widths at most 4 % of the
mean residence time and of the hold-up, 15 % of the RTD variance, 8 % of each slice's
hold-up).

(a) Synthetic libraries from a known truth. The prediction of a quantity is the law's
value moved by the correction line fitted to the residuals log(DEM / law) at the runs
(:mod:`workflows.prediction.predict`); the law is held fixed here (a refit of the law per
added run takes about 35 minutes of EM), so a library is fully described by its residual
surface, and only the correction is refitted as runs are added. Each truth, per target
quantity: the shipped library's correction line for that quantity (its coefficients in
log speed, log length, log gap and log feed) plus a smooth nonlinear discrepancy the line
cannot follow (a random quadratic in the three axes, less its least-squares line, scaled
so its root mean square over the domain is ``phi`` times the target half-width / 1.96),
plus the DEM's seed noise at the shipped library's measured scatter (0.2-2 %, per
quantity). ``phi`` sets how close to its target the best possible interval is (near 1:
the targets are out of reach of the line); the shipped runs' own misfits correspond to
phi of about 0.6 for the hold-up and 1.1-1.3 for the mean residence time and the slices.
A design is judged at 200 random held-out points of the domain: the expected coverage of
a new DEM value there (the truth plus seed noise; the probability computed, not drawn)
pooled over the quantities and points, and each target's median half-width. A synthetic
library has no laws left out, hence no floors: the rule and the judge take the line's
intervals with the bias term.

Compared, each from the same truths: the rule (a 7-run star, the domain's centre and the
two ends of each axis, then one suggested run at a time from the 7^3 candidate grid, the
criterion over the whole domain), the same star then runs drawn at random from the same
grid (what stopping early gains without the rule), and full grids (2^3 + the centre, 3^3,
4^3, 5^3): the count is the number of runs when the targets are first met, for a grid the
size of the smallest one that meets them.

(b) The shipped runs, by leave-out. From a random 3-run start, the remaining shipped runs
are added one at a time, either the one the rule ranks best among them (criterion over the
library's whole domain, the intervals with the floors of the runs held so far, as the
product ranks them) or in a random order. After each addition the library of those
runs is checked as ``pbmdem library fit`` checks it (:func:`workflows.prediction.calibration.check`
of :func:`~workflows.prediction.calibration.restricted`): each run predicted by the law
fitted without it, corrected by the line of its misses on the others; no law is refitted
(the laws left out are the shipped ones, fitted to the 15 other runs, so the check is of
the correction's design). A target counts once at least 5 of the runs are interpolations
(their medians are over those, as the product's).

Reading (the tables below; the correction's form is the product's: speed, length, gap,
feed and last). On the synthetic libraries the sequential runs reach the targets with far
fewer runs than the smallest full grid that reaches them: 84 % fewer at phi 0.25 (10 runs
against 64) and 83 % at phi 0.5 (21.5 against 125), at least 30 % fewer for every truth;
at phi 0.7 neither does within the counts tried (the rule met them for 2 truths of 8, by
53 and 63 runs; no grid up to 125 runs met them for any). The saving is stopping, not the
rule: runs drawn at random after the same 7-run star stop about as early (12.5 against 10
at phi 0.25) or earlier (18 against 21.5 at phi 0.5). The form's gap and last are set by
the blender's length through its blade stations, so a run at a length the library lacks
comes first in the rule until the line identifies them (without it the rule kept to the
domain's corners, two lengths, and met no target). The rule on the line's intervals alone
piles its runs onto the corners and, once the line misses a curvature half the target's
size, meets the targets for 2 truths of 8 (phi 0.5): the bias term is what makes the rule
usable. On the shipped runs, left out: the targets of the mean residence time, the hold-up
and the RTD variance are met from 13-14 runs of 16 in the rule's order and 11-12 in random
orders (medians), the coverage from 3 in both (ranked without the floors, the rule's order
met them alike: 12-14 runs); the slices' half-widths are not met in any order (the
restricted libraries take them from the correction's lines, while their other quantities
keep the whole library's zone-law time scale). What would meet the rest is a better law,
not more runs of this design.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.special import ndtr

from coupling.errors import ConfigError
from coupling.files import regular_file, replace_file, writable_directory
from coupling.jsonable import write_json
from workflows.config import load_preset
from workflows.prediction import calibration
from workflows.prediction.library import DEFAULT_CORRECTION, LibraryModel, load_model
from workflows.prediction.predict import corrections, domain, fit_correction, floors, least_gap
from workflows.prediction.suggest import (
    CANDIDATE_LEVELS,
    REGION_LEVELS,
    Candidate,
    Least,
    Quantity,
    Region,
    candidates_over,
    covariate_terms,
    domain_region,
    half_widths,
    library_quantities,
    point_at,
    rank,
    target_half_width,
    term_columns,
)
from workflows.shipped import LIBRARY_MODEL

HELP = "sequential DEM runs by `library suggest`'s rule against grids: runs until the prediction targets are met"
OUT = Path("results/suggest-study")
#: the coverage the targets ask of the 95 % intervals
COVERAGE = 0.90
#: the discrepancies' sizes (module docstring)
PHIS = (0.25, 0.5, 0.7)
#: the full grids compared: levels per axis (2: with the centre)
GRID_LEVELS = (2, 3, 4, 5)
#: runs after which a sequence stops unmet
MAX_RUNS = 64
HELD_OUT = 200
#: interpolated runs a subset's check needs before its medians count (b)
LEAST_INTERPOLATED = 5


# ------------------------------------------------------------------ (a) synthetic libraries
@dataclass(frozen=True)
class Setting:
    """What every synthetic library shares: the domain, the base configuration's points
    (candidates, the criterion's region, the held-out points, each as covariate terms),
    the truth's lines and the seed noise per quantity."""

    span: Region
    candidates: tuple[Candidate, ...]
    region_points: tuple
    held_out: tuple
    held_terms: np.ndarray
    held_u: np.ndarray
    lines: dict[str, tuple[tuple[str, ...], np.ndarray]]
    noise: dict[str, float]
    #: the blade pattern of every point's stations
    pattern: str

    def unit(self, speed: float, length: float, feed: float) -> np.ndarray:
        """The point's log axes scaled to -1..1 over the domain."""
        out = []
        for v, (low, high) in zip((speed, length, feed), (self.span.speed, self.span.length, self.span.feed)):
            out.append(2 * (math.log(v) - math.log(low)) / max(math.log(high / low), 1e-12) - 1)
        return np.array(out)


def _quadratic(u: np.ndarray) -> np.ndarray:
    u = np.atleast_2d(u)
    a, b, c = u[:, 0], u[:, 1], u[:, 2]
    return np.column_stack([a * a, b * b, c * c, a * b, a * c, b * c])


@dataclass(frozen=True)
class Truth:
    """One synthetic library's residual surface per target quantity (module docstring)."""

    setting: Setting
    shapes: dict[str, np.ndarray]  # key -> (6,) quadratic coefficients, scaled
    projections: dict[str, np.ndarray]  # key -> the quadratic's line, removed

    def mean(self, key: str, terms: np.ndarray, u: np.ndarray) -> np.ndarray:
        names, coefficients = self.setting.lines[key]
        linear = terms[:, term_columns(names)] @ coefficients
        cols = term_columns(DEFAULT_CORRECTION)
        return linear + _quadratic(u) @ self.shapes[key] - terms[:, cols] @ self.projections[key]


def make_truth(setting: Setting, phi: float, rng: np.random.Generator) -> Truth:
    shapes, projections = {}, {}
    quad = _quadratic(setting.held_u)
    x = setting.held_terms[:, term_columns(DEFAULT_CORRECTION)]
    for key in setting.lines:
        c = rng.normal(size=6)
        beta = np.linalg.lstsq(x, quad @ c, rcond=None)[0]
        rest = quad @ c - x @ beta
        scale = phi * target_half_width(key)[1] / 1.96 / math.sqrt(float(np.mean(rest**2)))
        shapes[key], projections[key] = c * scale, beta * scale
    return Truth(setting, shapes, projections)


@dataclass(frozen=True)
class Judged:
    """A design judged at the held-out points: the pooled expected coverage and each
    target's median half-width [fraction of the value]."""

    coverage: float
    medians: dict[str, float]

    @property
    def met(self) -> bool:
        return self.coverage >= COVERAGE and all(v <= calibration.USEFUL_HALF_WIDTH[k] for k, v in self.medians.items())

    @property
    def worst(self) -> float:
        """The largest median half-width as a multiple of its target."""
        return max(v / calibration.USEFUL_HALF_WIDTH[k] for k, v in self.medians.items())


def judge(truth: Truth, points: list, residuals: dict[str, list[float]]) -> Judged:
    s = truth.setting
    covered, widths = [], {}
    for key, values in residuals.items():
        line = fit_correction(points, values, DEFAULT_CORRECTION, s.pattern)
        h = half_widths(line, s.held_terms)
        if not np.all(np.isfinite(h)):
            return Judged(0.0, {k: math.inf for k in calibration.USEFUL_HALF_WIDTH})
        bias = s.held_terms[:, term_columns(line.names)] @ line.coefficients - truth.mean(key, s.held_terms, s.held_u)
        sd = s.noise[key]
        covered.append(ndtr((h - bias) / sd) - ndtr((-h - bias) / sd))
        widths.setdefault(target_half_width(key)[0], []).append(np.sinh(h))
    return Judged(
        float(np.mean(covered)), {name: float(np.median(np.concatenate(parts))) for name, parts in widths.items()}
    )


class Library:
    """A synthetic library growing run by run: its points and each quantity's residuals
    (the truth plus a seed-noise draw)."""

    def __init__(self, truth: Truth, rng: np.random.Generator) -> None:
        self.truth, self.rng = truth, rng
        self.points: list = []
        self.residuals: dict[str, list[float]] = {key: [] for key in truth.setting.lines}

    def run(self, candidate: Candidate) -> None:
        s = self.truth.setting
        terms = covariate_terms([candidate.point], s.pattern)
        u = s.unit(candidate.speed, candidate.length, candidate.feed)[None, :]
        self.points.append(candidate.point)
        for key in self.residuals:
            self.residuals[key].append(float(self.truth.mean(key, terms, u)[0] + self.rng.normal(0, s.noise[key])))

    def quantities(self) -> list[Quantity]:
        return [Quantity(k, tuple(self.points), tuple(v)) for k, v in self.residuals.items()]

    def judged(self) -> Judged:
        return judge(self.truth, self.points, self.residuals)


def star(setting: Setting, base, gap: float) -> list[Candidate]:
    """The domain's centre and the two ends of each axis, the others at the centre."""
    ranges = (setting.span.speed, setting.span.length, setting.span.feed)
    mid = [float(f"{math.sqrt(lo * hi):.4g}") for lo, hi in ranges]
    out = [tuple(mid)]
    for axis, (lo, hi) in enumerate(ranges):
        for end in (lo, hi):
            values = list(mid)
            values[axis] = end
            out.append(tuple(values))
    return [Candidate(s, x, f, point_at(base, s, x, f, gap)) for s, x, f in out]


#: how a sequence picks its next run: the product's rule (the residuals' spread expected
#: to change with the design, from the seed scatter), the rule with the spread taken to
#: stay, at random
HOW = ("rule", "line rule", "random")


def sequential(truth: Truth, seed: list[Candidate], rng: np.random.Generator, how: str) -> tuple[int, list]:
    """Runs until the targets are met (MAX_RUNS + 1: never), from ``seed``, each next run
    picked as ``how`` says (:data:`HOW`); and each step's :class:`Judged`."""
    s = truth.setting
    library = Library(truth, rng)
    for c in seed:
        library.run(c)
    history = [library.judged()]
    while not history[-1].met and len(library.points) < MAX_RUNS:
        if how != "random":
            pure = s.noise if how == "rule" else None
            best = rank(
                library.quantities(), DEFAULT_CORRECTION, s.span, s.region_points, s.candidates, None, pure, s.pattern
            )[0]
            chosen = Candidate(best.speed, best.length, best.feed, best.point)
        else:
            chosen = s.candidates[int(rng.integers(len(s.candidates)))]
        library.run(chosen)
        history.append(library.judged())
    n = len(library.points) if history[-1].met else MAX_RUNS + 1
    return n, history


def grid_design(setting: Setting, base, gap: float, levels: int) -> list[Candidate]:
    cells = setting.span.grid(levels)
    if levels == 2:
        cells.append(
            tuple(
                float(f"{math.sqrt(lo * hi):.4g}")
                for lo, hi in (setting.span.speed, setting.span.length, setting.span.feed)
            )
        )
    return [Candidate(s, x, f, point_at(base, s, x, f, gap)) for s, x, f in cells]


def make_setting(model: LibraryModel, rng: np.random.Generator) -> tuple[Setting, Any, float]:
    """The :class:`Setting` of the library's domain (HELD_OUT random held-out points), the
    base configuration and the least gap to the weir."""
    base = load_preset("validation")
    points = [r.point for r in model.runs]
    span = domain_region(domain(points, model.blade_pattern))
    gap = least_gap(points)
    held = [
        tuple(
            float(math.exp(rng.uniform(math.log(lo), math.log(hi)))) for lo, hi in (span.speed, span.length, span.feed)
        )
        for _ in range(HELD_OUT)
    ]
    held_points = tuple(point_at(base, *h, gap) for h in held)
    lines = {
        key: (line.names, line.coefficients)
        for key, line in corrections(model).items()
        if target_half_width(key) is not None
    }
    scatter = calibration.seed_scatter(model).sd
    setting = Setting(
        span,
        tuple(candidates_over(base, span, gap, CANDIDATE_LEVELS)),
        tuple(point_at(base, s, x, f, gap) for s, x, f in span.grid(REGION_LEVELS)),
        held_points,
        covariate_terms(held_points, model.blade_pattern),
        np.zeros((0, 3)),
        lines,
        {key: scatter.get(key, 0.004) for key in lines},
        model.blade_pattern,
    )
    return Setting(**{**setting.__dict__, "held_u": np.array([setting.unit(*h) for h in held])}), base, gap


def synthetic(model: LibraryModel, truths: int, seed: int = 0) -> dict[str, Any]:
    """Part (a) (module docstring): per phi, per truth, the runs each way needs."""
    rng = np.random.default_rng(seed)
    setting, base, gap = make_setting(model, rng)
    seed_design = star(setting, base, gap)
    grids = {levels: grid_design(setting, base, gap, levels) for levels in GRID_LEVELS}
    out: dict[str, Any] = {"phis": {}}
    for phi in PHIS:
        rows = []
        for t in range(truths):
            truth = make_truth(setting, phi, rng)
            rule, rule_history = sequential(truth, seed_design, np.random.default_rng(1000 * t + 1), "rule")
            plain, _ = sequential(truth, seed_design, np.random.default_rng(1000 * t + 1), "line rule")
            rand, _ = sequential(truth, seed_design, np.random.default_rng(1000 * t + 2), "random")
            grid_n, grid_judged = len_grid(GRID_LEVELS[-1]) + 1, {}
            for levels, design in grids.items():
                library = Library(truth, np.random.default_rng(1000 * t + 3 + levels))
                for c in design:
                    library.run(c)
                judged = library.judged()
                grid_judged[len(design)] = judged
                if judged.met and grid_n > len(design):
                    grid_n = len(design)
            rows.append(
                {
                    "rule": rule,
                    "line_rule": plain,
                    "random": rand,
                    "grid": grid_n,
                    "rule_worst": [h.worst for h in rule_history],
                    "rule_coverage": [h.coverage for h in rule_history],
                    "grids": {
                        n: {"coverage": j.coverage, "worst": j.worst, "met": j.met} for n, j in grid_judged.items()
                    },
                }
            )
            print(f"phi {phi}, truth {t}: rule {rule}, line rule {plain}, random {rand}, grid {grid_n}", flush=True)
        out["phis"][str(phi)] = rows
    out["seed_runs"] = len(seed_design)
    out["candidates"] = len(setting.candidates)
    out["noise"] = setting.noise
    return out


# ------------------------------------------------------------------ (b) the shipped runs
def targets(check: calibration.Check) -> dict[str, bool]:
    """Each target of a subset's check met (module docstring)."""
    interpolated = sum(1 for r in check.runs() if check.of_run(r)[0].interpolated)
    out = {"coverage": check.coverage(None) >= COVERAGE}
    for key, target in calibration.USEFUL_HALF_WIDTH.items():
        out[key] = interpolated >= LEAST_INTERPOLATED and check.median_half_width(key) <= target
    return out


def shipped_orders(model: LibraryModel, starts: int, randoms: int, seed: int = 0) -> dict[str, Any]:
    """Part (b) (module docstring): per start, the rule's order and ``randoms`` random
    orders; for each, after each run, which targets its check meets."""
    base = load_preset("validation")
    points = [r.point for r in model.runs]
    span = domain_region(domain(points, model.blade_pattern))
    gap = least_gap(points)
    region_points = [point_at(base, s, x, f, gap) for s, x, f in span.grid(REGION_LEVELS)]
    names = model.calibration.covariates
    scatter = calibration.seed_scatter(model).sd
    rng = np.random.default_rng(seed)
    n_runs = len(model.runs)

    def walk(start: list[int], by_rule: bool, order_rng: np.random.Generator) -> tuple[list[int], list[dict]]:
        held = list(start)
        met = [targets(calibration.check(calibration.restricted(model, held)))]
        while len(held) < n_runs:
            rest = [n for n in range(n_runs) if n not in held]
            if by_rule:
                sub = calibration.restricted(model, held)
                cands = [Candidate(0.0, 0.0, 0.0, model.runs[n].point) for n in rest]
                least = Least(floors(sub), tuple(model.runs[n].point for n in held), model.blade_pattern)
                ranked = rank(
                    library_quantities(sub),
                    names,
                    span,
                    region_points,
                    cands,
                    None,
                    scatter,
                    model.blade_pattern,
                    least=least,
                )
                chosen = rest[next(i for i, c in enumerate(cands) if c.point is ranked[0].point)]
            else:
                chosen = rest[int(order_rng.integers(len(rest)))]
            held.append(chosen)
            met.append(targets(calibration.check(calibration.restricted(model, held))))
        return held, met

    out = []
    for s in range(starts):
        start = [int(n) for n in rng.choice(n_runs, 3, replace=False)]
        order, met = walk(start, True, rng)
        randoms_met = [walk(start, False, np.random.default_rng(100 * s + r))[1] for r in range(randoms)]
        out.append(
            {"start": start, "rule_order": [model.runs[n].file for n in order], "rule": met, "random": randoms_met}
        )
        print(f"start {s}: rule {first_all(met)}, random {[first_all(m) for m in randoms_met]}", flush=True)
    return {"starts": out, "runs": n_runs}


def first_met(met: list[dict], key: str, start: int = 3) -> int | None:
    """The number of runs from which ``key``'s target stays met to the end, None if it
    is not met with every run."""
    if not met[-1][key]:
        return None
    n = len(met)
    while n > 0 and met[n - 1][key]:
        n -= 1
    return start + n


def first_all(met: list[dict], start: int = 3) -> int | None:
    both = [{"all": all(m.values())} for m in met]
    return first_met(both, "all", start)


# ------------------------------------------------------------------ the page
def _median(values: list[float]) -> float:
    return float(np.median(values))


def markdown(result: dict[str, Any]) -> str:
    syn = result["synthetic"]
    lines = [
        "## (a) Synthetic libraries",
        "",
        f"Runs until the targets are met, over {len(next(iter(syn['phis'].values())))} random truths per phi "
        f"(seed design: {syn['seed_runs']} runs; candidates: a {CANDIDATE_LEVELS}^3 grid; {MAX_RUNS + 1} = not met "
        f"by {MAX_RUNS}; {len_grid(GRID_LEVELS[-1]) + 1} = no grid meets them). The grid's count is the size of the smallest full grid "
        f"({', '.join(str(len_grid(levels)) for levels in GRID_LEVELS)} runs) that meets them.",
        "",
        "Runs: median (range) over the truths. Saving: 1 - the rule's runs / the grid's, median over the truths "
        "the rule met the targets for (a grid that never meets them is taken at its limit, so that saving is a "
        "lower bound; a truth the rule never met counts as no saving).",
        "",
        "| phi | rule | rule on the line's intervals alone | random order after the same seed | smallest grid "
        "| saving of the rule against the grid | truths where the rule needs at least 30 % fewer than the grid "
        "| saving of the rule against the random order |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for phi, rows in syn["phis"].items():
        rule, line, rand, grid = ([r[k] for r in rows] for k in ("rule", "line_rule", "random", "grid"))
        met = [a <= MAX_RUNS for a in rule]
        savings = [1 - a / b for a, b, m in zip(rule, grid, met, strict=True) if m]
        against_random = [1 - a / b for a, b, m in zip(rule, rand, met, strict=True) if m]
        lines.append(
            f"| {phi} | {_range(rule)} | {_range(line)} | {_range(rand)} | {_range(grid)} | {_percent(savings)} | "
            f"{sum(s >= 0.3 for s in savings)}/{len(rows)} | {_percent(against_random, '+')} |"
        )
    ship = result["shipped"]
    lines += [
        "",
        "## (b) The shipped runs, by leave-out",
        "",
        f"{len(ship['starts'])} random 3-run starts; after each, the rule's order and "
        f"{len(ship['starts'][0]['random'])} random orders of the other shipped runs. Runs from which each target "
        f"stays met (of {ship['runs']}; '-': not met with all of them):",
        "",
        "| target | rule: median (range) | random orders: median (range) |",
        "| --- | --- | --- |",
    ]
    keys = ["coverage", *calibration.USEFUL_HALF_WIDTH]
    for key in keys:
        rule = [first_met(s["rule"], key) for s in ship["starts"]]
        rand = [first_met(m, key) for s in ship["starts"] for m in s["random"]]
        lines.append(f"| {key} | {_spread(rule)} | {_spread(rand)} |")
    return "\n".join(lines)


def _percent(values: list[float], sign: str = "") -> str:
    return f"{_median(values):{sign}.0%}" if values else "-"


def _range(values: list[int]) -> str:
    return f"{_median(values):g} ({min(values)}-{max(values)})"


def len_grid(levels: int) -> int:
    return levels**3 + (1 if levels == 2 else 0)


def _spread(values: list[int | None]) -> str:
    reached = [v for v in values if v is not None]
    if not reached:
        return f"- ({len(values)} of {len(values)} never)"
    never = len(values) - len(reached)
    return f"{_median(reached):g} ({min(reached)}-{max(reached)})" + (
        f"; never in {never} of {len(values)}" if never else ""
    )


def plot(result: dict[str, Any], path: Path) -> Path:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.2), layout="constrained")
    left, right = fig.subplots(1, 2)
    syn = result["synthetic"]["phis"]
    for i, rows in enumerate(syn.values()):
        for j, (what, colour) in enumerate(
            (("rule", "#2ca02c"), ("line_rule", "#9467bd"), ("random", "#1f77b4"), ("grid", "#d62728"))
        ):
            values = [r[what] for r in rows]
            x = i + (j - 1.5) * 0.2 + np.random.default_rng(j).uniform(-0.05, 0.05, len(values))
            left.plot(x, values, "o", color=colour, alpha=0.6, label=what if i == 0 else None)
    left.set_xticks(range(len(syn)), [f"phi {p}" for p in syn])
    left.axhline(MAX_RUNS + 1, color="k", lw=0.5, ls=":")
    left.set(ylabel="DEM runs until the targets are met", title="(a) synthetic truths", yscale="log")
    left.legend(fontsize=8)
    left.grid(alpha=0.3)
    ship = result["shipped"]
    n_runs = ship["runs"]
    x = np.arange(3, n_runs + 1)
    for what, colour in (("rule", "#2ca02c"), ("random", "#1f77b4")):
        for key, style in (("holdup", "-"), ("mean_residence_time_s", "--"), ("coverage", ":")):
            if what == "rule":
                share = np.mean([[m[key] for m in s["rule"]] for s in ship["starts"]], axis=0)
            else:
                share = np.mean([[m[key] for m in r] for s in ship["starts"] for r in s["random"]], axis=0)
            right.plot(x, share, style, color=colour, label=f"{what}: {key}")
    right.set(xlabel="shipped runs held", ylabel="share of orders meeting the target", title="(b) shipped runs")
    right.legend(fontsize=7)
    right.grid(alpha=0.3)
    fig.savefig(path, dpi=110)
    return path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--library", default=str(LIBRARY_MODEL), help="a calibrated library model (default: %(default)s)"
    )
    parser.add_argument("--truths", type=int, default=8, help="synthetic truths per phi (default: %(default)s)")
    parser.add_argument("--starts", type=int, default=8, help="3-run starts on the shipped runs (default: %(default)s)")
    parser.add_argument("--randoms", type=int, default=10, help="random orders per start (default: %(default)s)")
    parser.add_argument(
        "--from-json", default=None, help="write the page and figure of a suggest-study.json made before, no rerun"
    )
    parser.add_argument("--out", default=str(OUT), help="output folder (default: %(default)s)")


def run(args: argparse.Namespace) -> int:
    out = writable_directory(args.out, "--out")
    if args.from_json is not None:
        result = json.loads(regular_file(args.from_json, "--from-json", ConfigError).read_text())
    else:
        model = load_model(args.library)
        if model.calibration is None:
            model = calibration.calibrated(model)
        result = {
            "synthetic": synthetic(model, args.truths),
            "shipped": shipped_orders(model, args.starts, args.randoms),
            "command": f"pbmdem study suggest --truths {args.truths} --starts {args.starts} --randoms {args.randoms}",
        }
        write_json(out / "suggest-study.json", result)
    text = markdown(result)
    print(text)
    figure = plot(result, out / "suggest-study.png")
    page = replace_file(
        out / "SUGGEST.md",
        "# Sequential DEM runs against grids\n\n"
        f"Made by `{result.get('command', 'pbmdem study suggest')} --out DIR` (the numbers and `suggest-study.json`; `--from-json` rewrites "
        "this page and its figure from that file).\n\n"
        + (__doc__ or "")
        + "\n"
        + text
        + "\n\n![runs until the targets are met](suggest-study.png)\n",
        "study page",
    )
    print(f"wrote {'' if args.from_json else str(out / 'suggest-study.json') + ', '}{figure} and {page}")
    return 0
