"""Figures of the PBM's CQAs. Headless: figures are built with matplotlib's object API
(``Figure``, Agg canvas), never pyplot, so no display and no global state is involved.

Each ``plot_*`` draws into a given Axes (or a new figure) and returns the Axes, so the
comparison report can overlay DEM curves on the same axes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from pbm.simulate import PbmResult


def _axes(ax: Axes | None) -> Axes:
    if ax is not None:
        return ax
    return Figure(figsize=(6.0, 4.0), layout="constrained").add_subplot()


def plot_outflow(result: PbmResult, ax: Axes | None = None, label: str = "PBM") -> Axes:
    """Outflow rates of A, B and their total [particles/s] against time [s]."""
    ax = _axes(ax)
    ax.plot(result.times, result.outflow_A + result.outflow_B, label=f"{label} total")
    ax.plot(result.times, result.outflow_A, label=f"{label} A", lw=1)
    ax.plot(result.times, result.outflow_B, label=f"{label} B", lw=1)
    ax.set(xlabel="time [s]", ylabel="outflow [particles/s]", title="Outflow rate")
    ax.legend()
    return ax


def plot_composition(result: PbmResult, ax: Axes | None = None, label: str = "PBM") -> Axes:
    """C_A, the flux-weighted A fraction of the outflow, against time [s]."""
    ax = _axes(ax)
    ax.plot(result.times, result.C_A, label=label)
    ax.set(xlabel="time [s]", ylabel="C_A [-]", title="Fraction of A in the outflow", ylim=(0, 1))
    ax.legend()
    return ax


def plot_rsd_time(result: PbmResult, ax: Axes | None = None, label: str = "PBM") -> Axes:
    """RSD at the outlet and over the whole blender against time [s] (log scale)."""
    ax = _axes(ax)
    ax.plot(result.times, result.rsd_outlet, label=f"{label} outlet slice")
    ax.plot(result.times, result.rsd_blender, label=f"{label} whole blender", ls="--")
    ax.set(xlabel="time [s]", ylabel="RSD [-]", title="RSD of the A fraction")
    if np.any(np.nan_to_num(result.rsd_outlet) > 0):
        ax.set_yscale("log")
    ax.legend()
    return ax


def plot_rsd_by_slice(result: PbmResult, ax: Axes | None = None, label: str = "PBM") -> Axes:
    """RSD across each axial slice at the end time against the slice number (1 = inlet)."""
    ax = _axes(ax)
    ax.plot(np.arange(1, result.rsd_by_slice_final.size + 1), result.rsd_by_slice_final, marker="o", label=label)
    ax.set(xlabel="axial compartment (1 = inlet)", ylabel="RSD [-]", title=f"RSD(x) at t = {result.times[-1]:g} s")
    if np.any(np.nan_to_num(result.rsd_by_slice_final) > 0):
        ax.set_yscale("log")
    ax.legend()
    return ax


def plot_holdup(result: PbmResult, ax: Axes | None = None, label: str = "PBM") -> Axes:
    """Particles held in the blender (A, B, total) against time [s]."""
    ax = _axes(ax)
    ax.plot(result.times, result.holdup_A + result.holdup_B, label=f"{label} total")
    ax.plot(result.times, result.holdup_A, label=f"{label} A", lw=1)
    ax.plot(result.times, result.holdup_B, label=f"{label} B", lw=1)
    steady = result.summary.steady_state_time_s
    if steady is not None:
        ax.axvline(steady, color="grey", ls=":", label="steady state detected")
    ax.set(xlabel="time [s]", ylabel="hold-up [particles]", title="Hold-up")
    ax.legend()
    return ax


def plot_rtd(result: PbmResult, ax: Axes | None = None, label: str = "PBM") -> Axes:
    """E(t) [1/s] against residence time [s], with the mean residence time marked."""
    ax = _axes(ax)
    ax.step(result.rtd_t, result.rtd_E, where="mid", label=label)
    mean = result.summary.mean_residence_time_s
    if mean is not None and np.isfinite(mean):
        ax.axvline(mean, color="grey", ls=":", label=f"mean {mean:.1f} s")
    ax.set(xlabel="residence time [s]", ylabel="E(t) [1/s]", title=f"RTD (pulse at {result.rtd_pulse_s:g} s)")
    ax.legend()
    return ax


FIGURES = {
    "outflow": plot_outflow,
    "C_A": plot_composition,
    "rsd_time": plot_rsd_time,
    "rsd_by_slice": plot_rsd_by_slice,
    "holdup": plot_holdup,
    "rtd": plot_rtd,
}


def save_figures(result: PbmResult, out_dir: str | Path, dpi: int = 110) -> dict[str, Path]:
    """Write one PNG per CQA (``<name>.png`` for each key of :data:`FIGURES`)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, plot in FIGURES.items():
        ax = plot(result)
        path = out / f"{name}.png"
        ax.figure.savefig(path, dpi=dpi)
        paths[f"figure_{name}"] = path
    return paths


def plot_ensemble(ensembles: dict, quantity: str = "C_A", ax: Axes | None = None) -> Axes:
    """Mean and 5-95 % band of ``quantity`` ("C_A" or "rsd_outlet") against time, one
    curve per noise level: ``ensembles`` is :func:`pbm.ensemble.noise_study`'s dict
    (sigma -> EnsembleResult). Paper Figs 5 and 6(b).
    """
    if quantity not in ("C_A", "rsd_outlet"):
        raise ValueError(f"quantity must be 'C_A' or 'rsd_outlet', got {quantity!r}")
    ax = _axes(ax)
    for sigma, ens in sorted(ensembles.items()):
        mean = getattr(ens, f"{quantity}_mean")
        (line,) = ax.plot(ens.times, mean, label=f"sigma = {sigma:g}")
        ax.fill_between(
            ens.times,
            getattr(ens, f"{quantity}_p05"),
            getattr(ens, f"{quantity}_p95"),
            color=line.get_color(),
            alpha=0.2,
            lw=0,
        )
    ax.set(
        xlabel="time [s]",
        ylabel="C_A [-]" if quantity == "C_A" else "RSD at the outlet [-]",
        title=f"Feed noise: mean and 5-95 % band ({next(iter(ensembles.values())).members} members)",
    )
    if quantity == "rsd_outlet":
        ax.set_yscale("log")
    ax.legend()
    return ax


def plot_rsd_by_slice_family(results: dict, ax: Axes | None = None) -> Axes:
    """RSD(x) at the end for several runs (label -> PbmResult), e.g. a geometry study
    (paper Figs 3(b), 4(b)); x is the slice number 1..NX of each run."""
    ax = _axes(ax)
    for label, result in results.items():
        ax.plot(
            np.arange(1, result.rsd_by_slice_final.size + 1), result.rsd_by_slice_final, marker="o", label=str(label)
        )
    ax.set(xlabel="axial compartment (1 = inlet)", ylabel="RSD [-]", title="RSD(x) at the end time", yscale="log")
    ax.legend()
    return ax


def plot_rsd_time_family(results: dict, ax: Axes | None = None) -> Axes:
    """Outlet RSD against time for several runs (label -> PbmResult): paper Figs 3(a), 4(a)."""
    ax = _axes(ax)
    for label, result in results.items():
        ax.plot(result.times, result.rsd_outlet, label=str(label))
    ax.set(xlabel="time [s]", ylabel="RSD at the outlet [-]", title="Outlet RSD", yscale="log")
    ax.legend()
    return ax
