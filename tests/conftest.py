"""Shared fixtures. Plots are headless: matplotlib's Agg backend, pyvista off screen."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")

import numpy as np
import pytest


@pytest.fixture
def rng():
    return np.random.default_rng(20130101)


@pytest.fixture(scope="session")
def smoke_runs_root(tmp_path_factory):
    """A runs directory holding one completed real LIGGGHTS run of the ``smoke`` preset
    (under mpirun, as the preset says). Shared by every test that needs real DEM output,
    so CI pays for the solver once."""
    from dem.run import prepare_run, run_dem
    from workflows.config import load_preset

    root = tmp_path_factory.mktemp("smoke-runs")
    run_dem(prepare_run(load_preset("smoke").dem), runs_root=root, progress=False)
    return root
