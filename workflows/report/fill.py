"""The feed library's predictions as a figure (``pbmdem study fill``): hold-up and mean
residence time against the feed rate, the DEM with its 95 % interval, each source's PBM."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

SOURCE_STYLES = {"linear": ("#969696", ":"), "baseline law": ("#e6550d", "--"), "library law": ("#3182bd", "-")}
MODE_MARKERS = {"velocity": "o", "measured": "s", "phases": "^"}
PANELS = (("holdup", "steady hold-up [particles]"), ("mean_residence_time_s", "mean residence time [s]"))


def plot_fill(record: dict[str, Any], path: Path) -> Path:
    """One panel per quantity: the DEM's value and interval at every predicted feed, and
    each (source, rate mode) prediction, from the study's JSON record."""
    fig = Figure(figsize=(11, 4.5), layout="constrained")
    axes = fig.subplots(1, len(PANELS))
    feeds = {p["run"]: p["feed_per_s"] for p in record["predictions"]}
    for ax, (quantity, label) in zip(axes, PANELS):
        rows = [p for p in record["predictions"] if p["quantity"] == quantity]
        dem = {p["run"]: p for p in rows}
        order = sorted(dem, key=feeds.get)
        x = [feeds[r] for r in order]
        ax.errorbar(
            x,
            [dem[r]["dem"] for r in order],
            yerr=[
                [dem[r]["dem"] - dem[r]["dem_ci"][0] for r in order],
                [dem[r]["dem_ci"][1] - dem[r]["dem"] for r in order],
            ],
            fmt="D",
            color="#b2182b",
            ms=6,
            capsize=3,
            label="DEM (95 %)",
        )
        for source, (colour, ls) in SOURCE_STYLES.items():
            for mode, marker in MODE_MARKERS.items():
                mine = {p["run"]: p["pbm"] for p in rows if p["source"].split(" (")[0] == source and p["mode"] == mode}
                if not mine:
                    continue
                runs = [r for r in order if r in mine]
                ax.plot(
                    [feeds[r] for r in runs],
                    [mine[r] for r in runs],
                    color=colour,
                    ls=ls,
                    marker=marker,
                    mfc="none",
                    lw=1,
                    label=f"{source}, {mode}",
                )
        ax.set_xlabel("total feed [particles/s]")
        ax.set_ylabel(label)
    axes[0].legend(fontsize=7, ncol=2)
    fig.suptitle("Feed rates predicted without their own DEM run (leave one out; unseen runs from the whole library)")
    fig.savefig(path, dpi=110)
    return path
