"""Multidimensional compartment population balance model driven by DEM velocity tables.

The API the pipeline calls:

* :func:`simulate` (table, config, rtd_pulse_s=None) -> :class:`PbmResult`
* :func:`write_outputs` (result, out_dir) -> paths of timeseries.csv, rtd.csv, summary.json, PNGs
* :mod:`pbm.plots` ``plot_*`` (result, ax=None) -> Axes, to overlay DEM curves
* :func:`noise_ensemble` / :func:`noise_study`: feed-noise bands (paper Figs 5-6)
* :func:`scale_blender` / :func:`regrid`: modified tables for geometry and grid studies;
  :func:`geometry_study` / :func:`grid_study` run them
* :func:`synthetic_table`: a DEM-like table to try the PBM without DEM
"""

from pbm.config import PbmConfig
from pbm.ensemble import EnsembleResult, noise_ensemble, noise_study
from pbm.geometry import geometry_study, grid_study, regrid, scale_blender
from pbm.model import fill_missing_velocities
from pbm.simulate import PbmResult, simulate, write_outputs
from pbm.synthetic import synthetic_table

__all__ = [
    "EnsembleResult",
    "PbmConfig",
    "PbmResult",
    "fill_missing_velocities",
    "geometry_study",
    "grid_study",
    "noise_ensemble",
    "noise_study",
    "regrid",
    "scale_blender",
    "simulate",
    "synthetic_table",
    "write_outputs",
]
