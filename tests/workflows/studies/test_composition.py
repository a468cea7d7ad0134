"""The composition study: a random deal at known counts has a known RSD, and on the
shipped reduced run the DEM's outlet RSD is that of a random mixture at its own counts,
which the PBM, sampled at those counts dump by dump, reproduces (the command run end to
end); a missing file is one line."""

import json
import math

import numpy as np
import pytest

from workflows.cli.main import main
from workflows.shipped import REDUCED_RUN
from workflows.studies.composition import random_mixture_at


def test_a_random_deal_at_known_counts():
    """One A and one B over two compartments of one particle each: fractions 1 and 0,
    RSD sqrt(2) at every deal; two A over (1, 1): RSD 0."""
    rng = np.random.default_rng(1)
    totals = np.ones((50, 2), np.int64)
    assert random_mixture_at(np.tile([[1, 0]], (50, 1)), totals, 3, rng) == pytest.approx(math.sqrt(2))
    assert random_mixture_at(np.tile([[1, 1]], (50, 1)), totals, 3, rng) == 0.0


def test_the_shipped_runs_outlet_is_a_random_mixture_at_its_counts(tmp_path, capsys):
    """Through the command line: what it writes is the study's answer."""
    assert main(["study", "composition", "--results", str(REDUCED_RUN), "--out", str(tmp_path)]) == 0
    study = json.loads((tmp_path / "composition.json").read_text())
    low, high = study["dem_rsd"]["low"], study["dem_rsd"]["high"]
    assert low <= study["dem_rsd"]["estimate"] <= high
    assert low <= study["random_mixture_rsd"] <= high
    shares = zip(study["a_fraction_by_compartment"], study["mean_particles_by_compartment"])
    assert max(abs(f - 0.5) for f, n in shares if n > 10) < 0.05
    assert set(study["pbm_at_dump_counts"]) == {"velocity", "measured", "phases"}
    for mode, value in study["pbm_at_dump_counts"].items():
        assert low <= value <= high, mode
        assert study["pbm_at_mean_counts"][mode] < low, mode  # the mean counts' basis: too uniform
    assert "| measured |" in capsys.readouterr().out
