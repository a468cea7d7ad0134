"""A dynamic check: the outlet's answer to a step in feeder A's rate, DEM against PBM.

One real LIGGGHTS run of the ``validation`` preset in which a second feeder of A starts
after the steady state (:data:`STEP_OVERRIDES`: A's rate doubles at 80 s, so the feed's
A share goes from 1/2 to 2/3), run and cached like any other (:func:`run_step`); its
results ship in ``workflows/reference/step``.

The PBM is fed the same step (``PbmConfig.feed_step_s``, on the PBM's 1-s feed grid; the
DEM's second feeder starts half an insertion batch, 0.025 s, later) and predicts the
outlet C_A per sampling interval. Two PBMs are judged, each in both rate modes:

* ``self``: the step run's own tables (what the hybrid does when the DEM saw the change);
* ``baseline``: the steady baseline's tables, velocities unchanged by the step (what the
  hybrid predicts from a steady DEM run alone -- the use of a PBM for control).

The DEM's outlet C_A per interval is a binomial sample of n particles. Two numbers judge
each PBM (:func:`judge`):

* the share of the intervals after the step whose DEM count of A lies in the PBM's central
  95 % binomial range (Binomial(n, C_PBM)); about 0.95 if the PBM were the DEM's truth;
* the response's mean delay, sum over the intervals after the step of
  (C_after - C(t)) dt / (C_after - C_before), with the levels the feed's A share before
  and after the step. For a linear blender it is the mean residence time of A (less the
  part of the response after the run's end, cut the same way on both sides). The DEM's carries a 95 %
  interval from a parametric bootstrap of its binomial counts; the PBM's, by the same rule
  on its own series, must fall inside it.
"""

from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from scipy.stats import chi2

from coupling.errors import ConfigError
from dem.run import can_resume, prepare_run
from pbm.model import RATE_MODES
from pbm.simulate import simulate
from workflows.config import Config, load_preset, override
from workflows.pipeline import DemSide, Log, dem_stage, pbm_config_for, stderr_log
from workflows.report import fmt

REFERENCE_DIR = Path(__file__).resolve().parent / "reference" / "step"
STEP_OVERRIDES = ("dem.operation.step_time_s=80", "dem.operation.step_factor_a=2", "dem.operation.duration_s=170")
#: The deviance's p-value below which the PBM's response is rejected as a whole.
P_MIN = 0.05
#: Range searched for the time-scale factor, and the 95 % chi-square quantile (1 dof).
ALPHA_RANGE = (0.25, 4.0)
CHI2_95_ONE_DOF = 3.841458820694124
N_BOOT = 2000
SEED = 2013


def step_config(base: Config | None = None) -> Config:
    """The validation preset with feeder A's step (validated before anything runs)."""
    base = base if base is not None else load_preset("validation")
    return override(base, *STEP_OVERRIDES).model_copy(update={"name": f"{base.name}-step_a_x2"})


def run_step(runs_root: str | Path = "runs/validation", fresh: bool = False, nprocs: int | None = None,
             log: Log = stderr_log, reference_dir: Path = REFERENCE_DIR, solver: bool = True,
             config: Config | None = None) -> DemSide:
    """The step run: cached, shipped, or LIGGGHTS (an interrupted run resumes)."""
    config = config if config is not None else step_config()
    resume = solver and not fresh and can_resume(prepare_run(config.dem), runs_root)
    return dem_stage(config, runs_root=runs_root, np=nprocs, resume=resume, fresh=fresh, progress=False, log=log,
                     reference_dir=reference_dir, solver=solver)


def dem_counts(timeseries: pd.DataFrame, interval_s: float) -> pd.DataFrame:
    """Particles of A and B discharged per sampling interval (t_s: the interval's end)."""
    n_a = np.rint(timeseries["outflow_A_per_s"].to_numpy() * interval_s)
    n_b = np.rint(timeseries["outflow_B_per_s"].to_numpy() * interval_s)
    return pd.DataFrame({"t_s": timeseries["t_s"].to_numpy(), "n_A": n_a, "n_B": n_b})


def pbm_response(table, config: Config, rates: str, step_s: float, t_end: float) -> pd.DataFrame:
    """The PBM's outlet C_A per sampling interval for ``table`` under the config's step."""
    op = config.dem.operation
    interval = float(config.dem.tables.sample_interval_s)
    pbm_config = pbm_config_for(config, table, None).model_copy(update={
        "rates": rates, "feed_step_s": step_s, "feed_step_factor_a": op.step_factor_a, "output_interval_s": interval,
        "noise_interval_s": interval, "duration_s": min(t_end, table.t_end)})
    result = simulate(table, pbm_config)
    return pd.DataFrame({"t_s": result.times, "C_A": result.C_A})


def feed_levels(config: Config) -> tuple[float, float]:
    """The feed's A share before and after the step: where the outlet's C_A starts and,
    for a blender that loses no particle, where it ends."""
    op = config.dem.operation
    a, b = op.feed_rate_a_per_s, op.feed_rate_b_per_s
    return a / (a + b), op.step_factor_a * a / (op.step_factor_a * a + b)


def mean_delay(t_s: np.ndarray, c_a: np.ndarray, step_s: float, interval_s: float, levels: tuple[float, float]) -> float:
    """sum over the intervals after the step of (C_after - C(t)) dt / (C_after - C_before),
    with the levels the feed's (:func:`feed_levels`): measuring them from the outlet would
    add their sampling noise to every interval of the sum."""
    c0, c1 = levels
    if not abs(c1 - c0) > 0:
        raise ConfigError(f"the feed's A share does not change across the step ({c0} -> {c1}): no response to time")
    response = (t_s > step_s) & np.isfinite(c_a)
    return float(np.sum(c1 - c_a[response]) * interval_s / (c1 - c0))


def binomial_deviance(k: np.ndarray, n: np.ndarray, p: np.ndarray) -> float:
    """2 sum [k ln(k / n p) + (n - k) ln((n - k) / n (1 - p))]: the likelihood-ratio
    statistic of counts k of n against probabilities p (chi-square with one degree of
    freedom per interval when p is the truth)."""
    p = np.clip(p, 1e-12, 1 - 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(k > 0, k * np.log(k / (n * p)), 0.0)
        b = np.where(n - k > 0, (n - k) * np.log((n - k) / (n * (1 - p))), 0.0)
    return float(2 * np.sum(a + b))


def time_scale(t_s: np.ndarray, k: np.ndarray, n: np.ndarray, pbm_t: np.ndarray, pbm_c: np.ndarray,
               step_s: float) -> dict[str, float | bool]:
    """The factor alpha by which the DEM's response runs faster than the PBM's (the DEM at
    step + dt matches the PBM at step + alpha dt), by binomial maximum likelihood over a
    log-spaced grid, with its 95 % profile-likelihood interval (deviance within 3.84 of
    its minimum). ``at_bound`` says the interval reaches the grid's end (0.25 or 4)."""
    alphas = np.geomspace(ALPHA_RANGE[0], ALPHA_RANGE[1], 1201)
    ok = np.isfinite(pbm_c)
    deviances = np.array([binomial_deviance(k, n, np.interp(step_s + (t_s - step_s) * a, pbm_t[ok], pbm_c[ok]))
                          for a in alphas])
    best = int(np.argmin(deviances))
    inside = alphas[deviances <= deviances[best] + CHI2_95_ONE_DOF]
    return {"value": float(alphas[best]), "low": float(inside.min()), "high": float(inside.max()),
            "at_bound": bool(inside.min() <= alphas[0] or inside.max() >= alphas[-1])}


def judge(dem: pd.DataFrame, pbm: pd.DataFrame, step_s: float, interval_s: float, levels: tuple[float, float],
          n_boot: int = N_BOOT, seed: int = SEED) -> dict[str, Any]:
    """One PBM's step response against the DEM's (module docstring): the response's time
    scale and the counts' deviance decide; the mean delay is reported with its interval.
    Only intervals after the step where the DEM discharged something and the PBM is defined."""
    merged = dem.merge(pbm, on="t_s", how="inner")
    n = (merged["n_A"] + merged["n_B"]).to_numpy()
    t = merged["t_s"].to_numpy()
    c_pbm = merged["C_A"].to_numpy()
    post = (t > step_s) & (n > 0) & np.isfinite(c_pbm)
    t, n, c_pbm, k = t[post], n[post], c_pbm[post], merged["n_A"].to_numpy()[post]
    if t.size == 0:
        raise ConfigError(f"no interval after the step at {step_s} s with particles discharged: nothing to judge")
    deviance = binomial_deviance(k, n, c_pbm)
    p_value = float(chi2.sf(deviance, t.size))
    scale = time_scale(t, k, n, pbm["t_s"].to_numpy(), pbm["C_A"].to_numpy(), step_s)
    dem_delay = mean_delay(t, k / n, step_s, interval_s, levels)
    rng = np.random.default_rng(seed)
    draws = rng.binomial(n.astype(np.int64), k / n, size=(n_boot, n.size))
    boot = [mean_delay(t, d / n, step_s, interval_s, levels) for d in draws]
    low, high = (float(q) for q in np.percentile(boot, [2.5, 97.5]))
    pbm_delay = mean_delay(t, c_pbm, step_s, interval_s, levels)
    scale_ok = scale["low"] <= 1.0 <= scale["high"]
    return {"intervals_after_step": int(t.size), "deviance": deviance, "deviance_p": p_value,
            "time_scale": scale, "time_scale_inside": bool(scale_ok),
            "dem_delay_s": {"value": dem_delay, "low": low, "high": high}, "pbm_delay_s": pbm_delay,
            "delay_inside": bool(low <= pbm_delay <= high),
            "predicted": bool(scale_ok and p_value >= P_MIN)}


def step_comparison(step: DemSide, baseline: DemSide | None, config: Config) -> dict[str, Any]:
    """Every PBM (own tables / the baseline's, each rate mode the table carries) judged
    against the step run's DEM; with the series for the figure."""
    op = config.dem.operation
    interval = float(config.dem.tables.sample_interval_s)
    # the PBM's feed changes on its interval grid; the DEM's second feeder starts 0.025 s later
    step_s = math.floor(op.step_time_s / interval + 1e-9) * interval
    t_end = float(step.results.timeseries["t_s"].max())
    dem = dem_counts(step.results.timeseries, interval)
    sources = {"self": step.table}
    if baseline is not None:
        sources["baseline"] = baseline.table
    rows, series = [], {}
    for source, table in sources.items():
        for mode in RATE_MODES:
            if mode == "measured" and not table.has_rates:
                continue
            pbm = pbm_response(table, config, mode, step_s, t_end)
            series[f"{source}/{mode}"] = pbm
            rows.append({"source": source, "mode": mode, **judge(dem, pbm, step_s, interval, feed_levels(config))})
    return {"step_s": step_s, "factor_a": op.step_factor_a, "interval_s": interval, "rows": rows,
            "dem": dem, "series": series}


def plot_step(comparison: dict[str, Any], path: str | Path) -> Path:
    """DEM outlet C_A per interval with its 95 % binomial range, and every PBM's."""
    from coupling.metrics import binomial_interval

    dem = comparison["dem"]
    n = (dem["n_A"] + dem["n_B"]).to_numpy()
    keep = n > 0
    t = dem["t_s"].to_numpy()[keep]
    lo, hi = binomial_interval(dem["n_A"].to_numpy()[keep], n[keep])
    fig = Figure(figsize=(9, 4.5), layout="constrained")
    ax = fig.subplots()
    ax.fill_between(t, lo, hi, step="pre", color="#bdbdbd", label="DEM, 95 % binomial range")
    ax.step(t, dem["n_A"].to_numpy()[keep] / n[keep], "k-", where="pre", lw=0.6, label="DEM")
    # 5-s pooled fractions: the trend the eye looks for under the per-interval noise
    block = np.floor((t - 1e-9) / 5.0)
    pooled = pd.DataFrame({"b": block, "k": dem["n_A"].to_numpy()[keep], "n": n[keep]}).groupby("b").sum()
    ax.plot(5.0 * pooled.index + 2.5, pooled["k"] / pooled["n"], "ko", ms=4, label="DEM, 5-s pooled")
    styles = {"self/velocity": ("#3182bd", "-"), "self/measured": ("#3182bd", "--"),
              "baseline/velocity": ("#e6550d", "-"), "baseline/measured": ("#e6550d", "--")}
    for key, pbm in comparison["series"].items():
        colour, ls = styles.get(key, ("#31a354", "-"))
        ax.plot(pbm["t_s"], pbm["C_A"], color=colour, ls=ls, lw=1.5, label=f"PBM, {key.replace('/', ' tables, ')} rates")
    ax.axvline(comparison["step_s"], color="#636363", lw=0.8, ls=":")
    start = max(0.0, comparison["step_s"] - 40)
    shown = t >= start
    ax.set(xlabel="time [s]", ylabel="outlet C_A",
           title=f"Feeder A x{comparison['factor_a']:g} at {comparison['step_s']:g} s: the outlet's response",
           xlim=(start, t.max()), ylim=(max(0.0, lo[shown].min() - 0.05), min(1.0, hi[shown].max() + 0.05)))
    ax.legend(fontsize=8, loc="lower right")
    out = Path(path)
    fig.savefig(out, dpi=120)
    return out


def step_html(comparison: dict[str, Any], figure: str | None) -> str:
    """The report section: one row per PBM, with the DEM's intervals and the verdict."""
    parts = [
        "<h2>A dynamic check: a step in feeder A</h2>",
        f"<p>One LIGGGHTS run of the validation preset in which feeder A's rate is multiplied by "
        f"{comparison['factor_a']:g} at {comparison['step_s']:g} s, predicted by PBMs on the run's own tables "
        "(<i>self</i>) and on the steady baseline's (<i>baseline</i>: the flow unchanged by the step). A PBM predicts "
        "the step when the DEM's response runs at its speed (the fitted time-scale factor's 95 % interval holds 1) "
        f"and the DEM's counts of A per {comparison['interval_s']:g}-s interval are consistent with it (binomial "
        f"deviance, p &ge; {P_MIN:g}). The mean delay (for a linear blender the mean residence time of A) is shown "
        "with the DEM's interval.</p>",
        "<table><tr><th>PBM tables</th><th>rates</th><th>DEM faster by [95 %]</th><th>deviance p</th>"
        "<th>mean delay, DEM [95 %]</th><th>mean delay, PBM</th><th>verdict</th></tr>"]
    for row in comparison["rows"]:
        d, a = row["dem_delay_s"], row["time_scale"]
        verdict = "predicts the step" if row["predicted"] else "does not"
        parts.append(
            f"<tr class='{'yes' if row['predicted'] else 'no'}'><td>{html.escape(row['source'])}</td>"
            f"<td>{row['mode']}</td><td>&times;{a['value']:.2f} [{a['low']:.2f}, {a['high']:.2f}] "
            f"{'&#10003;' if row['time_scale_inside'] else '&#10007;'}</td><td>{row['deviance_p']:.2f}</td>"
            f"<td>{fmt(d['value'])} [{fmt(d['low'])}, {fmt(d['high'])}] s</td><td>{fmt(row['pbm_delay_s'])} s "
            f"{'&#10003;' if row['delay_inside'] else '&#10007;'}</td><td>{verdict}</td></tr>")
    parts.append("</table>")
    if figure:
        parts.append(f"<p><img src='{figure}' style='max-width:100%'></p>")
    return "\n".join(parts)


def summary_rows(comparison: dict[str, Any]) -> dict[str, Any]:
    """The JSON-ready part of a comparison (no series)."""
    return {k: v for k, v in comparison.items() if k not in ("dem", "series")}
