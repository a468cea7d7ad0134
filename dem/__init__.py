"""DEM stage: blender geometry, LIGGGHTS deck, solver runs and dump post-processing."""
