"""``pbmdem library build`` / ``status``: the refusals made before any run or job (no
LIGGGHTS, no Slurm)."""

from workflows.cli.main import main
from workflows.shipped import LIBRARY_DIR

CONFIG = str(LIBRARY_DIR / "rpm300.toml")


def test_a_local_build_refuses_fewer_than_one_rank_before_writing(tmp_path, capsys):
    library, runs = tmp_path / "lib", tmp_path / "runs"
    argv = ["library", "build", "--scheduler", "local", "--np", "0", "--library", str(library)]
    assert main([*argv, "--runs-dir", str(runs), CONFIG]) == 2
    assert capsys.readouterr().err.strip() == "pbmdem: error: np must be >= 1, got 0 (an integer number of MPI tasks)"
    assert not library.exists() and not runs.exists()


def test_status_of_a_folder_without_a_build_says_how_to_start_one(tmp_path, capsys):
    assert main(["library", "status", "--library", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert str(tmp_path) in err and "pbmdem library build" in err and len(err.strip().splitlines()) == 1
