"""What a user runs, in rooms by floor (each imports only its own floor or lower ones):

* ``cli/`` -- ``pbmdem``, the one command line;
* ``products/`` -- the comparison, the validation campaign, the design tool;
* ``report/`` -- the figures and pages of each analysis;
* ``analysis/`` -- compute only, typed results (agreement, VRR, step, DEM budget, ...);
* ``pipeline/`` -- the stages: DEM through the cache, the PBM of a DEM run, the cluster path;
* ``shipped.py`` -- the DEM results that ship with the repository;
* ``config.py`` -- the typed configuration and its presets.

``studies/`` and ``bench/`` import the product; only ``cli/`` imports them.
"""
