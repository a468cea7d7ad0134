"""The VRR comparison as a figure, an HTML section and a text table: each reads the
:class:`workflows.analysis.vrr.VrrComparison` that :mod:`workflows.analysis.vrr` computes."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from pbm.frequency import FEEDERS
from workflows.analysis.vrr import RatioPoint, VrrComparison
from workflows.report.comparison import DEM_COLOUR, MODE_STYLES, PBM_COLOUR


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each run of True in ``mask``."""
    out, start = [], None
    for i, m in enumerate(mask):
        if m and start is None:
            start = i
        if not m and start is not None:
            out.append((start, i - 1))
            start = None
    if start is not None:
        out.append((start, len(mask) - 1))
    return out


def plot_vrr(comparison: VrrComparison, path: str | Path) -> Path:
    """Per feeder, top: VRR(f) on log-log axes, the DEM's estimate with its 95 % band, each
    PBM mode as a line, the frequencies where the DEM is at its sampling floor shaded;
    bottom: the same divided by the DEM's estimate, where misses of a few % show."""
    freqs = np.asarray(comparison.frequency_hz, dtype=float)
    # edges halfway (geometrically) between frequencies, so a shaded point owns its span
    mids = np.sqrt(freqs[:-1] * freqs[1:])
    edges = np.concatenate([[freqs[0]], mids, [freqs[-1]]])
    fig = Figure(figsize=(11.0, 7.6), layout="constrained")
    axes = fig.subplots(2, len(FEEDERS), sharex=True, sharey="row", height_ratios=(3, 2))
    for col, f in enumerate(FEEDERS):
        top_ax, ratio_ax = axes[0][col], axes[1][col]
        d = comparison.dem[f]
        vrr = {k: np.asarray(v, dtype=float) for k, v in zip(("value", "low", "high"), d.vrr)}
        resolved = np.asarray(d.resolved, dtype=bool)
        # the PBM's VRR grows like f^(2 n) beyond the floor: 1e12 at 1 Hz would flatten the
        # resolved part, so the axis stops a decade above the DEM's largest measurable VRR
        ceiling = 10 * float(d.n_recovered)
        for ax, scale in ((top_ax, np.ones_like(freqs)), (ratio_ax, vrr["value"])):
            ax.fill_between(
                freqs,
                vrr["low"] / scale,
                np.minimum(vrr["high"], ceiling) / scale,
                color=DEM_COLOUR,
                alpha=0.2,
                lw=0,
                label="DEM 95 % interval (block bootstrap)",
            )
            ax.plot(
                freqs,
                vrr["value"] / scale,
                "o-",
                ms=3,
                color=DEM_COLOUR,
                lw=1,
                label=f"DEM, N = {d.n_recovered} recovered",
            )
            for mode, m in comparison.pbm.items():
                style, label = MODE_STYLES[mode]
                ax.plot(freqs, np.asarray(m.feeders[f].vrr, dtype=float) / scale, style, color=PBM_COLOUR, label=label)
            for n, (a, b) in enumerate(_runs(~resolved)):
                ax.axvspan(
                    edges[a],
                    edges[b + 1],
                    color="0.85",
                    zorder=0,
                    label="DEM unresolved (sampling floor)" if n == 0 else None,
                )
            ax.set_xscale("log")
            ax.grid(alpha=0.3, which="both")
        top_ax.set_yscale("log")
        top_ax.axhline(
            1.0 / (comparison.resolved_factor * d.floor) ** 2,
            color="0.4",
            ls=":",
            lw=1,
            label=f"resolution limit: |H| = {comparison.resolved_factor:g}/sqrt(N)",
        )
        top_ax.set_ylim(0.8, ceiling)
        top_ax.set_title(f"feeder {f}: mean residence {d.mean_residence_time_s:.1f} s (DEM)")
        ratio_ax.axhline(1.0, color="k", lw=0.8)
        ratio_ax.set_ylim(0.5, 2.5)  # linear: the resolved misses are a few %
        ratio_ax.set_xlabel("feeder fluctuation frequency f [Hz]")
    axes[0][0].set_ylabel("VRR = 1 / |H(f)|^2")
    axes[1][0].set_ylabel("VRR / VRR_DEM")
    axes[0][-1].legend(fontsize=7, loc="upper left")
    fig.suptitle("Variance reduction of a sinusoidal feeder fluctuation: PBM vs DEM")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


def _ratio(point: RatioPoint | None, none: str, prefix: str = "feeder ") -> str:
    """A worst point as "ratio (feeder F, f Hz)", ``none`` when there is none."""
    if point is None:
        return none
    return f"{point.ratio_pbm_to_dem:.3g} ({prefix}{point.feeder}, {point.frequency_hz:.3g} Hz)"


def vrr_html(c: VrrComparison, figure: str | None = None) -> str:
    """The report's section: per rate mode how many resolved frequencies have the PBM's
    VRR inside the DEM's interval, and the noise VRRs with the DEM's interval."""

    parts = [
        "<h2>Feeder-noise filtering (variance reduction ratio)</h2>",
        f"<p>{html.escape(c.note)}</p><table><tr><th>PBM rates</th><th>VRR(f) inside the DEM interval</th>"
        "<th>worst PBM/DEM outside it</th></tr>",
    ]
    for mode, m in c.pbm.items():
        worst = _ratio(m.worst_outside, "–")
        parts.append(f"<tr><td>{mode}</td><td>{m.n_inside}/{m.n_judged} resolved points</td><td>{worst}</td></tr>")
    parts.append(
        f"</table><p>Band-limited feeder noise on [0, {c.noise_f_max_hz:g} Hz] (first order, "
        "correlation time τ; 0 = white):</p><table><tr><th>feeder, τ [s]</th><th>DEM [95 %]</th>"
        + "".join(f"<th>PBM, {mode} rates</th>" for mode in c.pbm)
        + "</tr>"
    )
    for f in FEEDERS:
        for i, tau in enumerate(c.noise_taus_s):
            dn = c.dem[f].noise[i]
            cells = "".join(
                f"<td>{m.feeders[f].noise[i].vrr:.4g} {'✓' if m.feeders[f].noise[i].inside else '✗'}</td>"
                for m in c.pbm.values()
            )
            parts.append(
                f"<tr><td>{f}, {tau:g}</td><td>{dn.estimate:.4g} [{dn.low:.4g}, {dn.high:.4g}]</td>{cells}</tr>"
            )
    parts.append("</table>")
    parts.append(
        "<p>The same PBM in the time domain: a noise ensemble, both feeders redrawn every "
        "noise interval, on the steady windows' mean table; the spread of its outlet C_A against the "
        "transfer functions' prediction for that noise (zero-order hold, output-interval means).</p>"
        "<table><tr><th>PBM rates</th><th>σ</th><th>members</th><th>SD of C_A, time domain</th>"
        "<th>predicted</th><th>difference</th></tr>"
    )
    for mode, m in c.pbm.items():
        for row in m.ensemble_check:
            parts.append(
                f"<tr><td>{mode}</td><td>{row.sigma:g}</td><td>{row.members}</td>"
                f"<td>{row.sd_time_domain:.4g}</td><td>{row.sd_frequency_domain:.4g}</td>"
                f"<td>{row.relative_difference:+.2%}</td></tr>"
            )
    parts.append("</table>")
    if figure:
        parts.append(
            f'<p><img src="{html.escape(figure)}" alt="Variance reduction ratio against frequency for each '
            "feeder: the DEM's estimate with its 95 % band and each PBM rate mode, and each divided by the "
            'DEM\'s" style="max-width:100%"></p>'
        )
    return "\n".join(parts)


def print_table(c: VrrComparison) -> None:
    """The comparison as a short text table on stdout."""
    for f, d in c.dem.items():
        print(
            f"DEM feeder {f}: N = {d.n_recovered} recovered of {d.n_entered} in {d.n_blocks} blocks, "
            f"floor 1/sqrt(N) = {d.floor:.4f}, resolved {int(np.sum(d.resolved))}/"
            f"{len(d.resolved)} frequencies (up to "
            f"{max((fr for fr, r in zip(c.frequency_hz, d.resolved) if r), default=float('nan')):.3g} Hz)"
        )
    for mode, m in c.pbm.items():
        worst = _ratio(m.worst, "-")
        outside = _ratio(m.worst_outside, "-", prefix="")
        print(
            f"{mode:>9}: VRR(f) inside the DEM interval at {m.n_inside}/{m.n_judged} resolved points "
            f"({m.inside_fraction:.0%}); worst PBM/DEM {worst}; worst outside the interval {outside}"
        )
    print(f"noise VRR on [0, {c.noise_f_max_hz:g} Hz]: DEM [95 % interval] | PBM per mode (* = inside)")
    for f in FEEDERS:
        for i, tau in enumerate(c.noise_taus_s):
            dn = c.dem[f].noise[i]
            cells = "  ".join(
                f"{mode} {m.feeders[f].noise[i].vrr:8.4g}{'*' if m.feeders[f].noise[i].inside else ' '}"
                for mode, m in c.pbm.items()
            )
            print(f"  {f} tau {tau:>4g} s: DEM {dn.estimate:8.4g} [{dn.low:.4g}, {dn.high:.4g}]  {cells}")
    print("time-domain ensemble vs the transfer functions: SD of the outlet C_A")
    for mode, m in c.pbm.items():
        for row in m.ensemble_check:
            print(
                f"  {mode}, sigma {row.sigma:g}, {row.members} members: {row.sd_time_domain:.4g} vs "
                f"{row.sd_frequency_domain:.4g} predicted ({row.relative_difference:+.2%})"
            )
