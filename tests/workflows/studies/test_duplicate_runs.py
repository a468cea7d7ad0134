"""A study over several runs counts each run once: the same results file given twice, by
path, symlink, hard link or as a copy, is refused in one line naming both files, before
anything is read or written (issue 46: `study feeders --results V V` pooled one run as two
and narrowed its interval by 1/sqrt(2))."""

import os
import shutil
from pathlib import Path

import pytest

from coupling.errors import ConfigError
from coupling.files import content_digest, distinct_inputs
from workflows.cli.main import main

REFERENCE = Path(__file__).resolve().parents[3] / "workflows/reference/validation/dem-dccc770e3c39f48c.h5"
OTHER = Path(__file__).resolve().parents[3] / "workflows/reference/validation/dem-110115e4ee2e888e.h5"


def _twin(kind: str, tmp_path: Path) -> tuple[Path, str]:
    """A second name for the reference run and the words the refusal uses for it."""
    if kind == "same path":
        return REFERENCE, "is the same file as"
    if kind == "another spelling":
        return REFERENCE.parent / ".." / REFERENCE.parent.name / REFERENCE.name, "is the same file as"
    twin = tmp_path / f"{kind.replace(' ', '-')}.h5"
    if kind == "symlink":
        twin.symlink_to(REFERENCE)
        return twin, "is the same file as"
    if kind == "hard link":
        shutil.copyfile(REFERENCE, tmp_path / "original.h5")
        os.link(tmp_path / "original.h5", twin)
        return twin, "is the same file as"
    shutil.copyfile(REFERENCE, twin)
    return twin, "is a copy of"


KINDS = ("same path", "another spelling", "symlink", "hard link", "copy")


@pytest.mark.parametrize("kind", KINDS)
def test_distinct_inputs_refuses_one_run_twice_naming_both(kind, tmp_path):
    first = tmp_path / "original.h5" if kind == "hard link" else REFERENCE
    twin, words = _twin(kind, tmp_path)
    with pytest.raises(ConfigError, match="each run counts once") as info:
        distinct_inputs([first, OTHER, twin], "--results")
    assert str(info.value).startswith(f"--results {twin} {words} {first} ")


def test_distinct_inputs_keeps_different_runs_in_order(tmp_path):
    assert distinct_inputs([OTHER, str(REFERENCE)], "--results") == [OTHER, REFERENCE]
    # files that carry no digest are told apart by their bytes
    a, b, c = tmp_path / "a.json", tmp_path / "b.json", tmp_path / "c.json"
    a.write_text("[1]")
    b.write_text("[2]")
    c.write_text("[1]")
    assert distinct_inputs([a, b], "summaries") == [a, b]
    assert content_digest(a) == content_digest(c) != content_digest(b)
    with pytest.raises(ConfigError, match=rf"^summaries {c} is a copy of {a} \(the same content digest\)"):
        distinct_inputs([a, b, c], "summaries")
    with pytest.raises(ConfigError, match=rf"^--results {tmp_path / 'missing.h5'} does not exist$"):
        distinct_inputs([a, tmp_path / "missing.h5"], "--results")


@pytest.mark.parametrize("study", ["feeders", "startup", "holdout", "blocks", "law", "fill"])
@pytest.mark.parametrize("kind", KINDS)
def test_studies_over_runs_refuse_one_run_twice_before_any_work(study, kind, tmp_path, capsys):
    first = tmp_path / "original.h5" if kind == "hard link" else REFERENCE
    twin, words = _twin(kind, tmp_path)
    out = tmp_path / "out"
    option = "--unseen" if study == "fill" else "--results"
    argv = ["study", study, option, str(first), str(twin), "--out-file" if study == "fill" else "--out", str(out)]
    if study == "fill":  # the library would be read first: point it at nothing
        argv += ["--runs-root", str(tmp_path / "runs")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pbmdem: error: {option} {twin} {words} {first} (")
    assert err.count("\n") == 1 and "each run counts once" in err
    assert not out.exists() and not (tmp_path / "runs").exists()
