"""Configuration files, the ``pbmdem`` CLI and the pipelines that chain DEM, coupling and PBM."""
