"""``pbmdem study suggest``: its synthetic truths have the discrepancy they claim, a
design judged at the held-out points of a truth it can follow meets the targets, and a
target's count is the run from which it stays met."""

import math

import numpy as np
import pytest

from workflows.prediction.library import DEFAULT_CORRECTION, load_model
from workflows.prediction.suggest import target_half_width, term_columns
from workflows.shipped import LIBRARY_MODEL
from workflows.studies.suggest import Library, first_met, make_setting, make_truth


@pytest.fixture(scope="module")
def setting():
    return make_setting(load_model(LIBRARY_MODEL), np.random.default_rng(0))[0]


def test_a_truths_discrepancy_is_what_the_line_cannot_follow_at_the_stated_size(setting):
    truth = make_truth(setting, 0.5, np.random.default_rng(1))
    x = setting.held_terms[:, term_columns(DEFAULT_CORRECTION)]
    for key in ("holdup", "holdup_slice_3"):
        names, coefficients = setting.lines[key]
        rest = (
            truth.mean(key, setting.held_terms, setting.held_u)
            - setting.held_terms[:, term_columns(names)] @ coefficients
        )
        assert math.sqrt(np.mean(rest**2)) == pytest.approx(0.5 * target_half_width(key)[1] / 1.96, rel=1e-9)
        assert np.linalg.lstsq(x, rest, rcond=None)[0] == pytest.approx(np.zeros(x.shape[1]), abs=1e-12)


def test_a_line_the_truth_is_without_discrepancy_meets_the_targets_with_the_candidate_grid(setting):
    """phi 0: the truth is the line plus seed noise; the whole 7^3 grid pins it down."""
    truth = make_truth(setting, 0.0, np.random.default_rng(2))
    library = Library(truth, np.random.default_rng(3))
    for c in setting.candidates:
        library.run(c)
    judged = library.judged()
    assert judged.met and judged.coverage == pytest.approx(0.95, abs=0.02)


def test_a_target_counts_from_the_run_after_which_it_stays_met():
    met = [{"x": v} for v in (False, True, False, True, True)]
    assert first_met(met, "x", start=3) == 6
    assert first_met([{"x": True}] * 3, "x", start=3) == 3
    assert first_met([{"x": True}, {"x": False}], "x") is None
