"""``pbmdem library build`` / ``status``: the refusals made before any run or job, the
results added to the folder, a Slurm command's failure told in one line (no LIGGGHTS, no
Slurm)."""

import os
import shutil

import pytest

from coupling.errors import SolverRunError
from workflows.cli.main import main
from workflows.pipeline.slurm import ArrayTask, Manifest, TaskStatus, refuse_live_build, write_manifest
from workflows.pipeline.slurm import _slurm as slurm_command
from workflows.products.library_build import add_to_library
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


def test_a_copy_cut_short_leaves_no_results_file_that_a_later_status_would_keep(tmp_path, monkeypatch):
    source = tmp_path / "cache" / "dem-0123456789abcdef.h5"
    source.parent.mkdir()
    source.write_bytes(b"x" * 100_000)
    library = tmp_path / "lib"
    library.mkdir()
    state = TaskStatus(ArrayTask(0, "a", "configs/a.toml", "0123456789abcdef", "7", 1), "completed", results=source)

    def no_link(src, dst):  # the cache on another file system
        raise OSError(18, "Invalid cross-device link")

    def cut(src, dst):
        with open(dst, "wb") as out:
            out.write(b"x" * 1000)
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "link", no_link)
    monkeypatch.setattr(shutil, "copy2", cut)
    with pytest.raises(KeyboardInterrupt):
        add_to_library(library, (state,))
    assert list(library.iterdir()) == []
    monkeypatch.undo()
    monkeypatch.setattr(os, "link", no_link)
    (added,) = add_to_library(library, (state,))
    assert added.results == library / source.name and added.results.read_bytes() == source.read_bytes()
    assert sorted(p.name for p in library.iterdir()) == [source.name]


def test_a_slurm_command_that_fails_over_several_lines_is_told_in_one():
    script = "echo 'sbatch: error: no controller' >&2; echo 'sbatch: fatal: no configuration' >&2; exit 1"
    with pytest.raises(SolverRunError) as err:
        slurm_command(["sh", "-c", script], None)
    assert str(err.value).endswith("failed: sbatch: error: no controller; sbatch: fatal: no configuration")
    assert "\n" not in str(err.value)


def test_an_earlier_build_without_jobs_is_not_live_whatever_its_files(tmp_path):
    # a local build's manifest whose configurations are gone: no job, so nothing to wait for
    manifest = Manifest(str(tmp_path / "runs"), None, None, (), (ArrayTask(0, "a", "configs/a.toml", None, None, 0),))
    write_manifest(tmp_path, manifest)
    assert refuse_live_build(tmp_path) is None


def test_resubmitting_a_run_that_failed_in_a_local_build_says_how_to_resume_it(tmp_path, capsys):
    # a local build whose run left no results: no Slurm job to resubmit
    (tmp_path / "configs").mkdir()
    shutil.copyfile(CONFIG, tmp_path / "configs" / "a.toml")
    manifest = Manifest(str(tmp_path / "runs"), None, None, (), (ArrayTask(0, "a", "configs/a.toml", None, None, 0),))
    write_manifest(tmp_path, manifest)
    assert main(["library", "status", "--library", str(tmp_path), "--resubmit-failed"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "a failed in a build run here" in err and "--scheduler local" in err
