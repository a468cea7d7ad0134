"""Every study that reads DEM results files refuses a missing one in one line naming it,
and writes nothing."""

import pytest

from workflows.cli.main import main

#: (study, the option that names its results files)
STUDIES = (
    ("lag", "--results"),
    ("phases", "--results"),
    ("composition", "--results"),
    ("sizes", "--results"),
    ("holdout", "--results"),
    ("startup", "--results"),
    ("feeders", "--results"),
    ("blocks", "--results"),
    ("vrr", "--reference"),
    ("budget", "--reference"),
    ("law", "--results"),
)


@pytest.mark.parametrize(("study", "option"), STUDIES)
def test_a_missing_results_file_is_one_line(study, option, tmp_path, capsys):
    missing = tmp_path / "missing.h5"
    out = "--out-file" if study == "lag" else "--out"  # lag writes one JSON file
    assert main(["study", study, option, str(missing), out, str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0], err
    assert not (tmp_path / "out").exists()
