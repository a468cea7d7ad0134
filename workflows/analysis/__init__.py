"""Compute only: each module takes DEM results and PBM runs and returns typed results (no
files, no figures, no printing); ``report/`` presents them."""
