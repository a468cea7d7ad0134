"""Multidimensional compartment population balance model driven by DEM velocity tables."""
