"""``pbmdem study holdout``: the phase model out of sample, run by run.

The memory check (:func:`workflows.analysis.memory.out_of_sample`) refits a run's phase
model to the particles that entered in the first half of its steady entries and predicts
the pooled RTD of those that entered in the second half; ``compare`` runs it on the
preset's run alone. This study runs it on any set of results files (by default the shipped
reduced run and the whole validation campaign), so that how often the check passes, and
whether a miss is beyond the two halves' noise, is measured over runs rather than read
from one. It needs only what the results store (the compartment sequences and the
particle records). Writes ``holdout.json`` and ``holdout.png`` (each run's refit against
the DEM's two halves) and prints a table.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from coupling.errors import ConfigError
from coupling.files import writable_directory
from coupling.jsonable import write_json
from dem.phases import phases_per_kind
from workflows.analysis.memory import OutOfSample, out_of_sample
from workflows.pipeline.results import load_results, pbm_config_for
from workflows.studies import add_runs_arguments, distinct_runs

HELP = "the phase model refitted on each run's first half against the DEM's second half, over many runs"
OUT = Path("results/holdout")


@dataclass(frozen=True)
class Holdout:
    """One run's out-of-sample check: its file and configuration name, its own model's
    phases per kind (what the refit must repeat), the check, and the seconds it took."""

    results: str
    name: str
    run_phases_per_kind: int
    check: OutOfSample
    wall_time_s: float

    def record(self) -> dict:
        return {
            "results": self.results,
            "name": self.name,
            "run_phases_per_kind": self.run_phases_per_kind,
            "wall_time_s": self.wall_time_s,
            **self.check.record(),
        }


def holdout(path: str | Path) -> Holdout:
    """:class:`Holdout` of the results file ``path``. Raises ConfigError naming the file
    when the run has no phase model, no sequences, or halves too short to fit and judge;
    CacheError for a missing or corrupt file."""
    started = time.perf_counter()
    results, config = load_results(path)
    if results.sequences is None or not results.table.has_phases:
        raise ConfigError(f"{path}: the results carry no phase model with compartment sequences to refit")
    try:
        check = out_of_sample(results, pbm_config_for(config, results.table, None))
    except ValueError as exc:
        raise ConfigError(f"{path}: no out-of-sample check: {exc}") from exc
    return Holdout(str(path), config.name, phases_per_kind(results.table.phases), check, time.perf_counter() - started)


def _judged(pbm: float, dem, first, within: bool | None, digits: int) -> str:
    inside = "✓" if dem.low <= pbm <= dem.high else "✗"
    noise = "" if inside == "✓" or within is None else (" (within noise)" if within else " (beyond noise)")
    first_text = "" if first is None else f"{first.value:.{digits}f}"
    return (
        f"{pbm:.{digits}f} {inside}{noise} | {dem.value:.{digits}f} [{dem.low:.{digits}f}, {dem.high:.{digits}f}] "
        f"| {first_text}"
    )


def markdown(rows: list[Holdout]) -> str:
    """One line per run: the refit's prediction against the DEM's second half (the
    verdict, and whether a miss is within the two halves' noise), the first half beside it."""
    lines = [
        "| run | tracers | phases per kind, run / refit | refit mean [s] | DEM 2nd half | DEM 1st half "
        "| refit variance [s²] | DEM 2nd half | DEM 1st half |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        c = row.check
        lines.append(
            f"| {row.name} | {c.n_entered} | {row.run_phases_per_kind} / {c.refit_phases_per_kind} | "
            f"{_judged(c.pbm_mean_s, c.dem_mean_s, c.dem_fit_half_mean_s, c.mean_within_halves_noise, 2)} | "
            f"{_judged(c.pbm_variance_s2, c.dem_variance_s2, c.dem_fit_half_variance_s2, c.variance_within_halves_noise, 0)} |"
        )
    means = sum(r.check.mean_inside for r in rows)
    variances = sum(r.check.variance_inside for r in rows)
    both = sum(r.check.mean_inside and r.check.variance_inside for r in rows)
    lines += ["", f"inside: mean {means} of {len(rows)}, variance {variances} of {len(rows)}, both {both}"]
    return "\n".join(lines)


def plot_holdout(rows: list[Holdout], path: Path) -> Path:
    """Each run's refit against the DEM's halves, relative to the second half: its 95 %
    interval as a bar, the first half as a hollow mark, the refit as a filled one; the
    mean on the left, the variance on the right."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 0.5 * len(rows) + 1.6), layout="constrained")
    axes = fig.subplots(1, 2, sharey=True)
    y = np.arange(len(rows))[::-1]
    for ax, what, pbm_of, second_of, first_of in (
        (axes[0], "pooled mean", lambda c: c.pbm_mean_s, lambda c: c.dem_mean_s, lambda c: c.dem_fit_half_mean_s),
        (
            axes[1],
            "pooled variance",
            lambda c: c.pbm_variance_s2,
            lambda c: c.dem_variance_s2,
            lambda c: c.dem_fit_half_variance_s2,
        ),
    ):
        for yi, row in zip(y, rows):
            second, first = second_of(row.check), first_of(row.check)
            ax.plot([second.low / second.value, second.high / second.value], [yi, yi], color="#9e9e9e", lw=6)
            if first is not None:
                ax.plot(first.value / second.value, yi, "o", mfc="none", mec="#1f77b4")
            inside = second.low <= pbm_of(row.check) <= second.high
            ax.plot(pbm_of(row.check) / second.value, yi, "D", color="#2ca02c" if inside else "#d62728")
        ax.axvline(1.0, color="k", lw=0.6)
        ax.set(xlabel=f"{what} / the DEM's second half", title=what)
        ax.grid(alpha=0.3)
    axes[0].set_yticks(y, [row.name for row in rows])
    axes[0].plot([], [], color="#9e9e9e", lw=6, label="DEM 2nd half, 95 %")
    axes[0].plot([], [], "o", mfc="none", mec="#1f77b4", label="DEM 1st half (fitted on)")
    axes[0].plot([], [], "D", color="#2ca02c", label="refit: inside")
    axes[0].plot([], [], "D", color="#d62728", label="refit: outside")
    axes[0].legend(fontsize=7, loc="best")
    fig.savefig(path, dpi=110)
    return path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_runs_arguments(parser, "compartment sequences and a phase model", str(OUT))


def run(args: argparse.Namespace) -> int:
    rows = []
    for path in distinct_runs(args.results):
        rows.append(holdout(path))
        print(f"{Path(path).name}: {rows[-1].wall_time_s:.0f} s", flush=True)
    print(markdown(rows))
    out = writable_directory(args.out, "--out")
    written = write_json(out / "holdout.json", {"runs": [r.record() for r in rows]})
    print(f"wrote {written} and {plot_holdout(rows, out / 'holdout.png')}")
    return 0
