"""The memory check (:mod:`workflows.analysis.memory`) as a figure and an HTML section."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from workflows.analysis.memory import MemoryCheck
from workflows.report.comparison import DEM_COLOUR, PBM_COLOUR, fmt

#: the line of a chain by its number of phases: the memoryless chain dashed
_STYLE = {1: "--"}


def plot_ck(check: MemoryCheck, path: Path) -> Path:
    """Chapman-Kolmogorov test: from the first, middle and last slice, the probability of
    being still in that slice and of having been discharged after each lag, observed (with
    two standard errors) against each chain's prediction."""
    first = check.chains[0].ck
    nx = first.observed.shape[1]
    slices = sorted({0, nx // 2, nx - 1})
    fig = Figure(figsize=(3.2 * len(slices), 4.0), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(slices), sharey=True))
    for ax, i in zip(axes, slices):
        lags = first.lags_s
        for column, label, marker in ((i, "still in the slice", "o"), (nx, "discharged", "s")):
            ax.errorbar(
                lags,
                first.observed[:, i, column],
                yerr=2 * first.standard_error[:, i, column],
                fmt=marker,
                color=DEM_COLOUR,
                ms=4,
                capsize=2,
                label=f"DEM: {label}",
            )
            for chain in check.chains:
                ax.plot(
                    lags,
                    chain.ck.predicted[:, i, column],
                    _STYLE.get(chain.n_phases, "-"),
                    color=PBM_COLOUR,
                    marker=marker,
                    mfc="none",
                    ms=4,
                    label=f"K = {chain.n_phases}: {label}",
                )
        ax.set(title=f"from slice {i + 1} of {nx}", xlabel="lag [s]", ylim=(-0.02, 1.02))
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("probability")
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncol=3, fontsize=7)
    fig.savefig(path, dpi=110)
    return path


def memory_html(check: MemoryCheck, figure: str | None) -> str:
    """The check's table (one row per chain) and figure."""
    rows = "".join(
        f"<tr><td>{c.n_phases}</td><td>{fmt(c.log_likelihood_per_step)}</td>"
        f"<td>{', '.join(fmt(t, 3) for t in c.timescales_s)}</td><td>{fmt(c.ck.max_z(), 3)}</td>"
        f"<td>{fmt(c.ck.max_abs_error(), 3)}</td><td>{'passed' if c.ck.passed else '<b>failed</b>'}</td></tr>"
        for c in check.chains
    )
    lags = ", ".join(f"{v:g}" for v in check.chains[0].ck.lags_s)
    out = (
        "<h2>Transport with memory: is the chain Markov?</h2>"
        f"<p>The particles that entered during the steady period ({check.fit_window_s[0]:.0f}–"
        f"{check.fit_window_s[1]:.0f} s: {check.n_particles} particles, {check.n_steps} particle-steps), "
        "on the axial slices. K = 1 is the memoryless chain fitted to them; the other row is the phase "
        "model the PBM's <i>phases</i> mode solves. Chapman–Kolmogorov test at "
        f"{html.escape(lags)} s: largest |predicted − observed| in standard errors (passed at ≤ "
        f"{fmt(check.chains[0].ck.z_limit, 2)}).</p>"
        "<table><tr><th>K</th><th>log-likelihood per particle-step</th><th>implied timescales [s]</th>"
        f"<th>CK max z</th><th>CK max |error|</th><th>CK</th></tr>{rows}</table>"
    )
    if figure:
        # full width: three panels side by side are unreadable at half the page
        out += (
            f'<figure class="wide"><img src="{html.escape(figure)}" alt="Chapman-Kolmogorov test: from the '
            "first, middle and last slice, the probability of being still in that slice and of having been "
            "discharged after each lag, the DEM's observed values with two standard errors against each "
            'chain\'s prediction" style="width:100%"></figure>'
        )
    out += _sizes_html(check)
    held = check.out_of_sample
    if held is None:
        out += f"<p>{html.escape(check.out_of_sample_note)}</p>"
        return out

    def interval(e) -> str:
        return "–" if e is None else f"{fmt(e.value)} [{fmt(e.low)}, {fmt(e.high)}]"

    def row(name: str, dem, pbm: float, inside: bool, fit_half, within_noise) -> str:
        verdict = "inside" if inside else "<b>outside</b>"
        if not inside and within_noise is not None:
            verdict += " (within the two halves' noise)" if within_noise else " (beyond the two halves' noise)"
        return (
            f"<tr><td>{name}</td><td>{fmt(dem.value)}</td><td>{fmt(dem.low)} – {fmt(dem.high)}</td><td>{fmt(pbm)}</td>"
            f"<td>{verdict}</td><td>{interval(fit_half)}</td></tr>"
        )

    out += (
        "<h3>Out of sample</h3>"
        f"<p>Phase model refitted on the particles that entered in {held.fit_window_s[0]:.0f}–{held.fit_window_s[1]:.0f} s "
        f"alone; pooled RTD of the {held.n_entered} particles that entered in {held.entry_window_s[0]:.0f}–"
        f"{held.entry_window_s[1]:.0f} s (horizon {held.horizon_s:g} s). The last column is the DEM's RTD of the "
        "particles the refit was fitted on: how far the run itself moved between its halves. A miss is "
        "within the two halves' noise when it is no larger than their 95 % half-widths combined (the refit "
        "carries the first half's sampling noise): the verdict stands, but the DEM cannot resolve that miss.</p>"
        "<table><tr><th>quantity</th><th>DEM</th><th>DEM 95 % interval</th><th>PBM, phases</th><th>verdict</th>"
        "<th>DEM, first half [95 %]</th></tr>"
        + row(
            "mean residence time [s]",
            held.dem_mean_s,
            held.pbm_mean_s,
            held.mean_inside,
            held.dem_fit_half_mean_s,
            held.mean_within_halves_noise,
        )
        + row(
            "RTD variance [s²]",
            held.dem_variance_s2,
            held.pbm_variance_s2,
            held.variance_inside,
            held.dem_fit_half_variance_s2,
            held.variance_within_halves_noise,
        )
        + "</table>"
    )
    return out


def _sizes_html(check: MemoryCheck) -> str:
    """The pooled RTD of each size class, DEM against the class's own chain; "" for a phase
    model of one chain."""
    if not check.by_size:
        return ""

    def interval(e) -> str:
        return f"{fmt(e.value)} [{fmt(e.low)}, {fmt(e.high)}]"

    def mark(inside: bool) -> str:
        return "inside" if inside else "<b>outside</b>"

    rows = "".join(
        f"<tr><td>{1e3 * c.diameter_m:.2f}</td><td>{c.share:.3f}</td><td>{c.n_entered}</td>"
        f"<td>{interval(c.dem_mean_s)}</td><td>{fmt(c.pbm_mean_s)} ({mark(c.mean_inside)})</td>"
        f"<td>{interval(c.dem_variance_s2)}</td><td>{fmt(c.pbm_variance_s2)} ({mark(c.variance_inside)})</td>"
        f"<td>{c.dem_beyond:.2%}</td><td>{c.pbm_beyond:.2%}</td></tr>"
        for c in check.by_size
    )
    return (
        "<h3>By particle size</h3><p>A particle keeps its size, and the sizes move at different speeds: "
        "the phase model is a chain per size class, fed in the classes' shares. The pooled RTD of each "
        "class's particles (the run's entry window and horizon) against its own chain.</p>"
        "<table><tr><th>diameter [mm]</th><th>share</th><th>tracers</th><th>DEM mean [s]</th><th>PBM mean</th>"
        "<th>DEM variance [s²]</th><th>PBM variance</th><th>DEM beyond the horizon</th><th>PBM beyond</th></tr>"
        f"{rows}</table>"
    )
