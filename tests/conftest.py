"""Shared fixtures. Plots are headless: matplotlib's Agg backend, pyvista off screen."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")

import numpy as np
import pytest


@pytest.fixture
def rng():
    return np.random.default_rng(20130101)
