"""The one interface between DEM and PBM: velocity tables in HDF5, and their cache.

``dem`` writes tables through this package and ``pbm`` reads them through it; the two
never import each other.
"""
