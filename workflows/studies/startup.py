"""``pbmdem study startup``: the phase model's start-up from empty against its steady state.

The comparison judges each side's steady hold-up as the mean of its own hold-up curve from
its own steady-state time on (one rule, :class:`coupling.metrics.SteadyStateRule`), and
both start empty. The DEM's bed fills in a few tens of seconds; the linear phase model
fills as the sum of its modes, and its slowest ones (a dead zone, a phase whose rates the
fit drove to ~0 in a slice) take minutes. The rule's 2 % tolerance then calls the PBM
steady while it is still filling, and the mean it judges sits below the model's own
steady state. This study separates the two on any set of results files (by default the
shipped reduced run and the validation campaign): per run the DEM's steady hold-up with
its interval, the hold-up the comparison judges (:func:`workflows.analysis.agreement.pbm_steady`
of the same run), the model's exact steady state (its stationary occupancy
``-G^-1 b``, :func:`pbm.frequency.stationary_system`), its slowest time scale, and how long
it takes from empty to come within 1 % of that steady state against the DEM's steady-state
time; and the same PBM with the fill law (``rate_law = "fill"``, :mod:`pbm.fill`, its
exponents fitted to the run's own windows): rates that follow each slice's fill let the
model fill as fast as the DEM, where the linear model's rates, fitted at the steady fill,
move an empty blender's first particles as slowly as a full one's. Writes
``startup.json`` and ``startup.png`` (the hold-up curves) and prints a table.

Why no linear model can do better: a linear, time-invariant blender started empty under a
constant feed F holds N(t) = F E[min(tau, t)] at time t, tau its residence time, whatever
its inner structure (phases, zones, compartments). With the DEM's own pooled tracers for
tau (exact for t up to the horizon, beyond which min(tau, t) = t for the unrecovered), this
is the hold-up any linear model that reproduced the DEM's RTD exactly would have. The
study reports it at the DEM's steady-state time as a share of the DEM's steady hold-up,
beside the phase model's own share then: when both sit well below 1, the DEM's fast
start-up is its own nonlinearity (an emptier bed passes its particles on more slowly),
and only a law that follows the fill can reach it.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from coupling.errors import ConfigError
from coupling.files import writable_directory
from coupling.intervals import inside
from coupling.jsonable import write_json
from coupling.metrics import rtd_pooled
from dem.summary import Estimate
from pbm.frequency import stationary_system
from pbm.simulate import simulate
from workflows.analysis.agreement import pbm_steady
from workflows.pipeline.results import load_results, pbm_config_for
from workflows.studies import add_runs_arguments, distinct_runs

HELP = "the phase model's hold-up from empty against its own steady state and the DEM's, run by run"
OUT = Path("results/startup")
#: "filled": within this share of the model's steady hold-up
WITHIN = 0.01


@dataclass(frozen=True)
class Startup:
    """One run: the DEM's steady hold-up (with interval) and steady-state time; the PBM's
    judged hold-up (mean after its own steady time, as the comparison takes it), its exact
    steady hold-up, its slowest time scale [s], and the time [s] it takes from empty to come
    within :data:`WITHIN` of the steady hold-up (NaN: not within the run); at the DEM's
    steady-state time, the hold-up of a linear blender with the DEM's RTD
    (:func:`linear_holdup`) and the PBM's, as shares of the DEM's steady hold-up."""

    results: str
    name: str
    dem_holdup: Estimate
    dem_steady_time_s: float
    pbm_judged_holdup: float
    pbm_steady_time_s: float
    pbm_stationary_holdup: float
    slowest_time_scale_s: float
    pbm_filled_s: float
    fill_law_judged_holdup: float
    fill_law_steady_time_s: float
    fill_law_filled_s: float
    dem_rtd_linear_share: float
    pbm_share_at_dem_steady: float
    times_s: np.ndarray
    pbm_holdup: np.ndarray
    fill_law_holdup: np.ndarray
    dem_times_s: np.ndarray
    dem_holdup_curve: np.ndarray
    linear_times_s: np.ndarray
    dem_rtd_linear_curve: np.ndarray

    def _inside(self, holdup: float) -> bool:
        return bool(inside(holdup, self.dem_holdup.low, self.dem_holdup.high))

    @property
    def judged_inside(self) -> bool:
        return self._inside(self.pbm_judged_holdup)

    @property
    def fill_law_inside(self) -> bool:
        return self._inside(self.fill_law_judged_holdup)

    @property
    def stationary_inside(self) -> bool:
        return self._inside(self.pbm_stationary_holdup)

    def record(self) -> dict:
        return {
            "results": self.results,
            "name": self.name,
            "dem_holdup": self.dem_holdup.record(),
            "dem_steady_time_s": self.dem_steady_time_s,
            "pbm_judged_holdup": self.pbm_judged_holdup,
            "pbm_judged_inside": self.judged_inside,
            "pbm_steady_time_s": self.pbm_steady_time_s,
            "pbm_stationary_holdup": self.pbm_stationary_holdup,
            "pbm_stationary_inside": self.stationary_inside,
            "slowest_time_scale_s": self.slowest_time_scale_s,
            "pbm_filled_within_1pct_s": self.pbm_filled_s,
            "fill_law_judged_holdup": self.fill_law_judged_holdup,
            "fill_law_judged_inside": self.fill_law_inside,
            "fill_law_steady_time_s": self.fill_law_steady_time_s,
            "fill_law_filled_within_1pct_s": self.fill_law_filled_s,
            "dem_rtd_linear_share_at_dem_steady": self.dem_rtd_linear_share,
            "pbm_share_at_dem_steady": self.pbm_share_at_dem_steady,
        }


def filled_time(times_s: np.ndarray, holdup: np.ndarray, stationary: float, within: float = WITHIN) -> float:
    """The first time from which ``holdup`` stays within ``within`` (a share) of
    ``stationary``; NaN when it never does."""
    off = np.abs(np.asarray(holdup, float) / stationary - 1.0) > within
    if off[-1]:
        return float("nan")
    last_off = np.flatnonzero(off)
    return float(times_s[last_off[-1] + 1]) if last_off.size else float(times_s[0])


def linear_holdup(residence_s: np.ndarray, feed_per_s: float, t_s: float) -> float:
    """F E[min(tau, t)]: the hold-up at time ``t_s`` of a linear, time-invariant blender
    started empty under the constant feed ``feed_per_s`` [1/s] whose residence times are
    the sample ``residence_s`` [s] (inf for a tracer not seen to leave)."""
    return float(feed_per_s * np.minimum(np.asarray(residence_s, float), t_s).mean())


def _dem_residence_times(results) -> tuple[np.ndarray, float]:
    """The DEM's pooled tracers' residence times (inf for those still inside after the
    horizon) and the horizon [s]; min(tau, t) is known for t up to the horizon. Empty
    and a horizon of 0 s for a run without a pooled RTD."""
    if not results.summary.has_pooled_rtd:
        return np.empty(0), 0.0
    spec = results.summary.pooled_rtd
    particles = results.particles
    pooled = rtd_pooled(particles["entry_t_s"], particles["exit_t_s"], spec.entry_window_s, spec.horizon_s)
    unrecovered = np.full(pooled.n_entered - pooled.residence_s.size, np.inf)
    return np.concatenate([pooled.residence_s, unrecovered]), float(spec.horizon_s)


def _steady_time(run) -> float:
    t_ss = run.summary.steady_time
    return float("nan") if t_ss is None else t_ss


def startup(path: str | Path) -> Startup:
    """:class:`Startup` of the results file ``path``. Raises ConfigError naming the file
    when it has no phase model or no steady state; CacheError for a missing or corrupt file."""
    results, config = load_results(path)
    summary = results.summary
    if not results.table.has_phases:
        raise ConfigError(f"{path}: the results carry no phase model")
    if summary.steady_time is None or not summary.steady:
        raise ConfigError(f"{path}: the DEM run never reached a steady state to compare with")
    pbm_config = pbm_config_for(config, results.table, None).model_copy(update={"rates": "phases"})
    run = simulate(results.table, pbm_config, steady=config.steady_state)
    fill_run = simulate(results.table, pbm_config.model_copy(update={"rate_law": "fill"}), steady=config.steady_state)
    system = stationary_system(results.table, pbm_config, t_start_s=summary.steady_time)
    feed = np.array([pbm_config.feed_rate_a_per_s, pbm_config.feed_rate_b_per_s])
    stationary = float(np.linalg.solve(-system.generator, system.feed @ feed).sum())
    rates = np.linalg.eigvals(system.generator).real
    holdup = run.counts.sum(axis=(1, 2, 3))
    fill_holdup = fill_run.counts.sum(axis=(1, 2, 3))
    dem_curve = results.timeseries
    dem_holdup = Estimate.from_record(summary.steady["holdup"])
    at_dem_steady = float(np.interp(summary.steady_time, run.times, holdup))
    tau, horizon = _dem_residence_times(results)
    linear_times = np.asarray(run.times, float)[run.times <= horizon] if tau.size else np.empty(0)
    linear = np.array([linear_holdup(tau, float(feed.sum()), t) for t in linear_times])
    return Startup(
        results=str(path),
        name=config.name,
        dem_holdup=dem_holdup,
        dem_steady_time_s=float(summary.steady_time),
        pbm_judged_holdup=float(pbm_steady(run, summary.steady)["holdup"]),
        pbm_steady_time_s=_steady_time(run),
        pbm_stationary_holdup=stationary,
        slowest_time_scale_s=float(1.0 / -rates.max()),
        pbm_filled_s=filled_time(run.times, holdup, stationary),
        fill_law_judged_holdup=float(pbm_steady(fill_run, summary.steady)["holdup"]),
        fill_law_steady_time_s=_steady_time(fill_run),
        fill_law_filled_s=filled_time(fill_run.times, fill_holdup, stationary),
        dem_rtd_linear_share=(
            linear_holdup(tau, float(feed.sum()), summary.steady_time) / dem_holdup.value
            if summary.steady_time <= horizon
            else float("nan")
        ),
        pbm_share_at_dem_steady=at_dem_steady / dem_holdup.value,
        times_s=np.asarray(run.times, float),
        pbm_holdup=holdup,
        fill_law_holdup=fill_holdup,
        dem_times_s=dem_curve["t_s"].to_numpy(float),
        dem_holdup_curve=(dem_curve["holdup_A"] + dem_curve["holdup_B"]).to_numpy(float),
        linear_times_s=linear_times,
        dem_rtd_linear_curve=linear,
    )


def markdown(rows: list[Startup]) -> str:
    """One line per run: the DEM's steady hold-up, the PBM's judged and exact steady
    hold-ups (each ✓ inside the DEM's interval, ✗ not), the slowest time scale and the
    times to steady; at the DEM's steady time, the shares of its steady hold-up that a
    linear blender with its RTD and the PBM hold."""
    lines = [
        "| run | DEM steady hold-up | PBM judged (mean after its steady time) | PBM steady state "
        "| slowest time scale [s] | DEM steady from [s] | PBM within 1 % from [s] "
        "| fill law: judged | fill law: within 1 % from [s] "
        "| at the DEM's steady time: linear with the DEM's RTD / PBM |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        d = r.dem_holdup
        lines.append(
            f"| {r.name} | {d.value:.0f} [{d.low:.0f}, {d.high:.0f}] | {r.pbm_judged_holdup:.0f} "
            f"{'✓' if r.judged_inside else '✗'} | {r.pbm_stationary_holdup:.0f} {'✓' if r.stationary_inside else '✗'} "
            f"| {r.slowest_time_scale_s:.0f} | {r.dem_steady_time_s:.0f} | {r.pbm_filled_s:.0f} "
            f"| {r.fill_law_judged_holdup:.0f} {'✓' if r.fill_law_inside else '✗'} | {r.fill_law_filled_s:.0f} "
            f"| {r.dem_rtd_linear_share:.3f} / {r.pbm_share_at_dem_steady:.3f} |"
        )
    judged = sum(r.judged_inside for r in rows)
    exact = sum(r.stationary_inside for r in rows)
    fill = sum(r.fill_law_inside for r in rows)
    lines += [
        "",
        f"inside the DEM's interval: judged {judged} of {len(rows)}, steady state {exact} of {len(rows)}, "
        f"with the fill law judged {fill} of {len(rows)}",
    ]
    return "\n".join(lines)


def plot_startup(rows: list[Startup], path: Path) -> Path:
    """Each run's hold-up from empty, relative to the DEM's steady mean: the DEM's curve,
    its interval as a band, the PBM's curve with and without the fill law, its exact
    steady state, and the fill of a linear blender with the DEM's RTD (up to the horizon)."""
    from matplotlib.figure import Figure

    n = len(rows)
    cols = min(3, n)
    fig = Figure(figsize=(3.6 * cols, 2.6 * ((n + cols - 1) // cols)), layout="constrained")
    axes = np.atleast_1d(fig.subplots((n + cols - 1) // cols, cols, squeeze=False)).ravel()
    for ax, r in zip(axes, rows):
        ref = r.dem_holdup.value
        ax.axhspan(r.dem_holdup.low / ref, r.dem_holdup.high / ref, color="#bdbdbd", alpha=0.6, lw=0)
        ax.plot(r.dem_times_s, r.dem_holdup_curve / ref, color="#b2182b", lw=0.8, label="DEM")
        ax.plot(r.linear_times_s, r.dem_rtd_linear_curve / ref, color="k", lw=1.0, ls=":", label="linear, DEM's RTD")
        ax.plot(r.times_s, r.pbm_holdup / ref, color="#2166ac", lw=1.2, label="PBM, phases")
        ax.plot(r.times_s, r.fill_law_holdup / ref, color="#1b7837", lw=1.2, ls="--", label="PBM, phases + fill law")
        ax.axhline(r.pbm_stationary_holdup / ref, color="#2166ac", ls=":", lw=1, label="PBM steady state")
        ax.axvline(r.dem_steady_time_s, color="#b2182b", ls="--", lw=0.6)
        ax.set(title=r.name, ylim=(0.85, 1.05), xlabel="t [s]")
        ax.grid(alpha=0.3)
    for ax in axes[n:]:
        ax.set_visible(False)
    axes[0].set_ylabel("hold-up / DEM steady mean")
    axes[0].legend(fontsize=7, loc="lower right")
    fig.savefig(path, dpi=110)
    return path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_runs_arguments(parser, "a phase model", str(OUT))


def run(args: argparse.Namespace) -> int:
    rows = [startup(path) for path in distinct_runs(args.results)]
    out = writable_directory(args.out, "--out")  # after the inputs are read: a bad one leaves nothing
    print(markdown(rows))
    written = write_json(out / "startup.json", {"within": WITHIN, "runs": [r.record() for r in rows]})
    print(f"wrote {written} and {plot_startup(rows, out / 'startup.png')}")
    return 0
