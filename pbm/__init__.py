"""Multidimensional compartment population balance model driven by DEM velocity tables.

The API the pipeline calls:

* :func:`simulate` (table, config, rtd_pulse_s=None, steady=SteadyStateRule()) -> :class:`PbmResult`
* :func:`write_outputs` (result, out_dir) -> paths of timeseries.csv, rtd.csv, summary.json, PNGs
* :mod:`pbm.plots` ``plot_*`` (result, ax=None) -> Axes, to overlay DEM curves
* :func:`noise_ensemble` / :func:`noise_study`: feed-noise bands (paper Figs 5-6)
* :func:`scale_blender` / :func:`regrid`: modified tables for geometry and grid studies;
  :func:`geometry_study` / :func:`grid_study` run them
* :func:`synthetic_table`: a DEM-like table to try the PBM without DEM

The CQAs (RSD and its empty rule, C_A, the steady-state rule) are those of
:mod:`coupling.metrics`, shared with the DEM. Conventions of this package (each documented
and tested at the function named):

* Missing samples (``table.valid`` False): :func:`fill_missing_velocities` -- the same
  compartment's nearest valid window in time, else the mean of the same slice's valid
  compartments, else the nearest valid slice, else the table-wide mean; never a zero.
* Output times: rates and C_A average over (t - dt, t], exactly (accumulated discharge);
  counts, hold-ups and RSDs are instantaneous at t. E(t) is reported at bin centres.
* Regridding: :func:`regrid` -- particle-flux weighted overlap averages (ratio of sums, as
  the DEM post-processing would bin), counts conserved.
* Feed noise: factor N(1, sigma) per stream, clipped at 0, redrawn every
  ``noise_interval_s``; the members drawn one after the other from one generator seeded
  ``seed`` (member 0 is the single run).
"""

from coupling.lazy import lazy_names
from pbm.config import PbmConfig
from pbm.model import fill_missing_velocities
from pbm.simulate import PbmResult, simulate

# The ensemble, the studies and the figures (matplotlib) are imported on first use: a
# command that needs one of them does not pay for the others. ``simulate`` stays eager:
# it is also its module's name, which a later import of pbm.simulate would rebind.
_HOMES = {
    "EnsembleResult": "pbm.ensemble",
    "geometry_study": "pbm.studies",
    "grid_study": "pbm.studies",
    "noise_ensemble": "pbm.ensemble",
    "noise_study": "pbm.ensemble",
    "regrid": "pbm.studies",
    "scale_blender": "pbm.studies",
    "synthetic_table": "pbm.synthetic",
    "write_outputs": "pbm.outputs",
}

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


__getattr__, __dir__ = lazy_names(__name__, _HOMES)
