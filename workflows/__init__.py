"""The pipeline for a notebook, and what a user runs, in rooms by floor.

The names a notebook needs, importable from here (units in the names and docstrings):

* :func:`load_results` (path) -> (:class:`dem.post.DemResults`, :class:`Config`): a DEM
  results file whole -- its velocity table ``.table``, its scalars ``.summary`` (every steady
  quantity with its 95 % interval, e.g. ``.summary.pooled_rtd.mean_residence_time_s``, an
  :class:`dem.summary.Estimate` in s), its time series -- and the configuration it was made with.
* :func:`pbm_inputs` (path, rates=VALIDATED_RATES) -> (table, :class:`pbm.PbmConfig`): the
  PBM configuration of the file's own run, in the rate mode the validation judges best.
* :func:`simulate` (table, pbm_config) -> :class:`pbm.PbmResult`: the PBM (``.summary``
  holds the same quantities as the DEM's, ``.times`` [s] and the CQAs over time).
* :func:`predict` (config, library=None, extrapolate=False) -> :class:`Prediction`: an
  operating point the DEM never ran, from the shipped library's law (or ``library``), every
  quantity with its 95 % prediction interval (``.quantity("holdup")``: value, low, high).
* :func:`override` (config, "dem.operation.impeller_rpm=225", ...) -> :class:`Config`, and
  :func:`load_config` / :func:`load_preset`: the configurations to predict or run.
* :func:`plot_composition` (pbm_result) -> matplotlib Axes: C_A [-] against time [s].
* :data:`REDUCED_RUN` (the ``reduced`` preset's run), :data:`VALIDATION_DIR` (the validation
  campaign's runs, inside the library's domain): shipped DEM results files.

Each is imported on first use (module ``__getattr__``), so ``import workflows`` -- which the
command line does -- costs nothing.

The rooms, each importing only its own floor or lower ones:

* ``cli/`` -- ``pbmdem``, the one command line;
* ``products/`` -- the comparison, the validation campaign, the library, prediction and design;
* ``report/`` -- the figures and pages of each analysis;
* ``analysis/`` -- compute only, typed results (agreement, VRR, step, DEM budget, ...);
* ``prediction/`` -- beside ``analysis/``: the DEM library's law, its calibrated intervals,
  a point's prediction, the next run to add and the design search;
* ``pipeline/`` -- the stages: DEM through the cache, the PBM of a DEM run, the cluster path;
* ``shipped.py`` -- the DEM results that ship with the repository;
* ``config.py`` -- the typed configuration and its presets.

``studies/`` and ``bench/`` import the product; only ``cli/`` imports them.
"""

# Nothing is imported here but the look-up of the names' homes, which hold their code:
# the command line imports this package first, and pays for none of it.
from coupling.lazy import lazy_names

_HOMES = {
    "Config": "workflows.config",
    "LIBRARY_MODEL": "workflows.shipped",
    "REDUCED_RUN": "workflows.shipped",
    "VALIDATED_RATES": "workflows.pipeline.results",
    "VALIDATION_DIR": "workflows.shipped",
    "load_config": "workflows.config",
    "load_preset": "workflows.config",
    "load_results": "workflows.pipeline.results",
    "override": "workflows.config",
    "pbm_inputs": "workflows.pipeline.results",
    "predict": "workflows.products.api",
    "plot_composition": "pbm.plots",
    "simulate": "pbm",
}

__all__ = sorted(_HOMES)


__getattr__, __dir__ = lazy_names(__name__, _HOMES)
