"""``pbmdem study error-structure``: kriging a held-out error from the other runs' errors
removes a smooth one and cannot remove noise; the shipped library's page is rebuilt."""

import numpy as np
import pytest

from workflows.cli.main import main
from workflows.studies.error_structure import kriged_errors


def _points(n: int = 40) -> np.ndarray:
    return np.random.default_rng(1).uniform(0.0, 1.0, (n, 3))


def test_a_smooth_error_is_kriged_away_from_its_neighbours():
    x = _points()
    errors = 0.05 * np.sin(3 * x[:, 0]) + 0.03 * x[:, 1]
    left = kriged_errors(x, errors, ell=0.5, ratio=1e4)
    assert np.sqrt(np.mean(left**2)) < 0.1 * np.sqrt(np.mean(errors**2))


def test_noise_is_not_kriged_away_and_no_signal_leaves_the_errors_as_they_are():
    x = _points()
    errors = np.random.default_rng(2).normal(0.0, 0.02, len(x))
    left = kriged_errors(x, errors, ell=0.2, ratio=1.0)
    assert np.sqrt(np.mean(left**2)) > 0.95 * np.sqrt(np.mean(errors**2))
    assert kriged_errors(x, errors, ell=0.2, ratio=0.0) == pytest.approx(errors, rel=1e-12)


def test_a_missing_error_is_neither_kriged_nor_used():
    x = _points(5)
    errors = np.array([0.01, np.nan, 0.02, 0.03, 0.01])
    left = kriged_errors(x, errors, ell=0.3, ratio=4.0)
    assert np.isnan(left[1]) and np.all(np.isfinite(np.delete(left, 1)))
    assert left[0] == pytest.approx(kriged_errors(np.delete(x, 1, 0), np.delete(errors, 1), 0.3, 4.0)[0])


def test_the_shipped_librarys_page_is_written_with_every_quantity(tmp_path, capsys):
    assert main(["study", "error-structure", "--out", str(tmp_path)]) == 0
    page = (tmp_path / "error-structure.md").read_text()
    assert "| lacey_outlet |" in page and "| holdup_slice_10 |" in page and "runs of 0.33 m" in page
