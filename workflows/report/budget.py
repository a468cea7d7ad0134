"""The DEM-budget study as a figure and a text table (computed by
:mod:`workflows.analysis.budget`)."""

from __future__ import annotations

import math
from pathlib import Path

from matplotlib import colormaps
from matplotlib.figure import Figure

from workflows.analysis.budget import BudgetStudy


# ----------------------------------------------------------------------------- figure
def plot_budget(study: BudgetStudy, path: Path) -> Path:
    """Per mode a panel: |pbm_T - pbm_whole| / half width against T, one line per quantity
    (the axial hold-up slices thin and grey: ten lines that tell one story), the line 1."""
    modes = list(study.whole)
    fig = Figure(figsize=(6.5 * len(modes), 6.0))
    axes = fig.subplots(1, len(modes), sharey=True, squeeze=False)
    for ax, mode in zip(axes[0], modes):
        series: dict[str, tuple[str, list, list]] = {}
        for budget in study.budgets:
            for row in budget.modes[mode].rows if mode in budget.modes else ():
                label, ts, ds = series.setdefault(row.key, (row.quantity, [], []))
                ts.append(budget.t_s)
                ds.append(row.deviation)
        slice_label = False
        colours = iter(c for n, c in enumerate(colormaps["tab10"].colors) if n != 7)  # grey is the slices'
        for key, (label, ts, ds) in series.items():
            if key.startswith("holdup_slice_"):
                ax.plot(
                    ts,
                    ds,
                    color="0.65",
                    lw=0.8,
                    marker=".",
                    label=None if slice_label else "hold-up of each axial slice",
                )
                slice_label = True
            else:
                ax.plot(ts, ds, lw=1.5, marker="o", ms=3, label=label, color=next(colours, "k"))
        ax.axhline(1.0, color="k", ls="--", lw=1, label="half width of the DEM 95 % interval")
        for smallest, style, text in (
            (study.smallest_T, ":", "smallest T"),
            (study.smallest_T_without_slices, "-.", "smallest T without the slices"),
        ):
            best = smallest[mode][0]
            if best is not None:
                ax.axvline(best, color="tab:green", lw=1, ls=style, label=f"{text} = {best:g} s")
        holding = study.holding[mode]  # the steady table against the per-window one
        ax.scatter(
            [study.t_end_s] * len(holding.rows),
            [row.deviation for row in holding.rows],
            marker="x",
            color="tab:red",
            s=18,
            zorder=3,
            label="steady table vs per-window table (whole run)",
        )
        ax.set_yscale("symlog", linthresh=0.1)
        ax.set_xlabel("DEM used: first T seconds [s]")
        ax.set_title(f"PBM rates: {mode}")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("|PBM(first T s) - PBM(whole run)| / half width")
    handles, labels = axes[0][-1].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=7, loc="lower center", ncol=3, frameon=False)
    fig.suptitle(f"How little DEM does the PBM need? (full run {study.t_end_s:g} s)")
    fig.tight_layout(rect=(0, 0.2, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


# ----------------------------------------------------------------------------- CLI
def print_table(study: BudgetStudy) -> None:
    modes = list(study.whole)
    print(f"{'T [s]':>6} {'T/full':>6}  " + "  ".join(f"{mode + ': inside, worst (deviation)':<38}" for mode in modes))
    for budget in study.budgets:
        cells = []
        for mode in modes:
            m = budget.modes.get(mode)
            worst = None if m is None else m.worst
            cells.append(
                f"{'failed':<38}"
                if m is None
                else f"{'yes' if m.all_inside else 'no':<3} {m.n_inside:>2}/{len(m.rows):<2} "
                f"{worst.key if worst else '-'} ({worst.deviation if worst else math.nan:.2f})".ljust(38)
            )
        print(
            f"{budget.t_s:>6g} {budget.fraction:>6.2f}  "
            + "  ".join(cells)
            + (f"  {budget.error}" if budget.error else "")
        )
    for mode, m in study.holding.items():
        worst = m.worst
        print(
            f"steady table vs per-window table (whole run), {mode} rates: {'yes' if m.all_inside else 'no'} "
            f"{m.n_inside}/{len(m.rows)}, worst {worst.key if worst else None} "
            f"({worst.deviation if worst else math.nan:.2f}); without the slice "
            f"hold-ups: {'yes' if m.all_inside_without_slices else 'no'}"
        )
    for title, smallest in (
        ("smallest T", study.smallest_T),
        ("without the slice hold-ups", study.smallest_T_without_slices),
    ):
        for mode, (t_s, fraction) in smallest.items():
            text = "none of the T studied" if t_s is None else f"{t_s:g} s ({fraction:.0%} of the run)"
            print(f"{title}, {mode} rates: {text}")
