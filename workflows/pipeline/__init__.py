"""The stages as the products see them: the DEM stage through the cache, the PBM
configuration of a DEM run, the cluster path."""
