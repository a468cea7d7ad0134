import pytest

from tests.workflows.prediction.small_library import fit_small_library


@pytest.fixture(scope="session")
def library(tmp_path_factory):
    """The small library's folder, fitted once; a test that changes it works on a copy."""
    return fit_small_library(tmp_path_factory.mktemp("library"))
