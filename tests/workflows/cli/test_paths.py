"""Every subcommand against paths that cannot work: a missing input, an output under a
regular file, an output that is an existing file. One line naming the path, exit code 2,
no traceback, and nothing expensive started first (these run without the solver)."""

import pytest

from workflows.cli.main import main


@pytest.fixture
def paths(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory\n")
    table = tmp_path / "table.h5"
    assert main(["pbm", "synth", "--out-file", str(table), "--nx", "3", "--ny", "2", "--windows", "2"]) == 0
    return {"file": blocker, "under_file": blocker / "sub", "table": table, "missing": tmp_path / "missing"}


COMMANDS = {
    "config: missing file": lambda p: ["config", "--config", str(p["missing"] / "c.toml")],
    "pbm run: missing table": lambda p: [
        "pbm",
        "run",
        "--tables",
        str(p["missing"] / "t.h5"),
        "--out",
        str(p["missing"]),
    ],
    "pbm run: out under a file": lambda p: ["pbm", "run", "--tables", str(p["table"]), "--out", str(p["under_file"])],
    "pbm run: out is a file": lambda p: ["pbm", "run", "--tables", str(p["table"]), "--out", str(p["file"])],
    "pbm synth: out under a file": lambda p: ["pbm", "synth", "--out-file", str(p["under_file"] / "t.h5")],
    "dem deck: out under a file": lambda p: ["dem", "deck", "--preset", "smoke", "--out", str(p["under_file"])],
    "dem run: runs dir under a file": lambda p: [
        "dem",
        "run",
        "--preset",
        "smoke",
        "--runs-dir",
        str(p["under_file"]),
        "--no-progress",
    ],
    "dem post: missing dumps": lambda p: [
        "dem",
        "post",
        "--preset",
        "smoke",
        "--dumps",
        str(p["missing"] / "d.*.txt"),
        "--out-file",
        str(p["missing"].parent / "r.h5"),
    ],
    "dem post: out under a file": lambda p: [
        "dem",
        "post",
        "--preset",
        "smoke",
        "--dumps",
        str(p["missing"] / "*.txt"),
        "--out-file",
        str(p["under_file"] / "r.h5"),
    ],
    "dem refit-phases: missing file": lambda p: ["dem", "refit-phases", str(p["missing"] / "dem-x.h5")],
    "dem refit-phases: not a results file": lambda p: ["dem", "refit-phases", str(p["file"])],
    "dem slurm: out under a file": lambda p: [
        "dem",
        "slurm",
        "--preset",
        "paper",
        "--out",
        str(p["under_file"]),
        "--holdup",
        "1000",
        "--throughput",
        "1e6",
    ],
    "compare: results under a file": lambda p: [
        "compare",
        "--preset",
        "smoke",
        "--out",
        str(p["under_file"]),
        "--runs-dir",
        str(p["missing"]),
        "--no-progress",
    ],
    "compare: runs under a file": lambda p: [
        "compare",
        "--preset",
        "smoke",
        "--runs-dir",
        str(p["under_file"]),
        "--out",
        str(p["missing"]),
        "--no-progress",
    ],
}


@pytest.mark.parametrize("name", COMMANDS)
def test_bad_paths_give_one_line(name, paths, capsys):
    capsys.readouterr()
    argv = COMMANDS[name](paths)
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pbmdem: error:"), err
    assert "Traceback" not in err
    bad = next(a for a in argv if a.startswith(str(paths["file"].parent)))
    assert any(part in lines[0] for part in (bad, str(paths["file"]), str(paths["missing"]))), lines[0]


def test_dem_post_refuses_dumps_of_another_deck(tmp_path, capsys):
    """Dumps in a run directory written by `dem deck` (deck.json) or by a run (status.json)
    are post-processed only with the configuration that made them."""
    import json

    import numpy as np

    from dem.dumps import format_snapshot
    from workflows.config import load_preset

    run_dir = tmp_path / "run"
    assert main(["dem", "deck", "--preset", "smoke", "--out", str(run_dir)]) == 0
    step = int(round(5.0 / load_preset("smoke").dem.timestep_s))  # covers the first 5-s velocity window
    columns = ("id", "type", "x", "y", "z", "vx", "vy", "vz", "radius")
    rows = np.array([[1, 1, 0.01, 0.01, 0, 0.1, 0, 0, 0.003], [2, 2, 0.2, -0.01, 0, 0.1, 0, 0, 0.003]])
    (run_dir / "dumps" / f"dump.{step}.txt").write_bytes(format_snapshot(step, columns, rows))
    dumps = str(run_dir / "dumps" / "dump.*.txt")
    capsys.readouterr()
    assert main(["dem", "post", "--preset", "reduced", "--dumps", dumps, "--out-file", str(tmp_path / "r.h5")]) == 2
    assert "deck.json differs" in capsys.readouterr().err
    assert main(["dem", "post", "--preset", "smoke", "--dumps", dumps, "--out-file", str(tmp_path / "r.h5")]) == 0
    (run_dir / "status.json").write_text(json.dumps({"deck_hash": "0123456789abcdef", "state": "completed"}))
    capsys.readouterr()
    assert main(["dem", "post", "--preset", "smoke", "--dumps", dumps, "--out-file", str(tmp_path / "r.h5")]) == 2
    assert "come from deck 0123456789abcdef" in capsys.readouterr().err


@pytest.fixture
def small_mounts(tmp_path):
    """A full disk (a 64 KiB tmpfs) and a read-only file system, which root cannot write
    either (permission bits would not stop root, who runs CI)."""
    import os
    import subprocess

    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root (CI runs as root)")
    mounts = {"full": tmp_path / "full", "readonly": tmp_path / "readonly"}
    for name, options in (("full", "size=64k"), ("readonly", "ro,size=64k")):
        mounts[name].mkdir()
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(mounts[name])], capture_output=True)
        if done.returncode != 0:
            pytest.fail(f"cannot mount a tmpfs: {done.stderr.decode(errors='replace')}")
    yield mounts
    for path in mounts.values():
        subprocess.run(["umount", str(path)], capture_output=True)


@pytest.mark.parametrize("where", ["full", "readonly"])
def test_full_disk_and_read_only_directory_give_one_line(where, paths, small_mounts, capsys):
    target = small_mounts[where]
    for argv in (
        ["pbm", "run", "--tables", str(paths["table"]), "--out", str(target / "out")],
        ["dem", "deck", "--preset", "smoke", "--out", str(target / "deck")],
        ["pbm", "synth", "--out-file", str(target / "t.h5")],
    ):
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("pbmdem: error:") and "Traceback" not in err, err
        assert str(target) in lines[0] and ("No space" in lines[0] or "Read-only" in lines[0]), lines[0]


def _smoke_run_with_one_dump(tmp_path):
    """A `dem deck` run directory of the smoke preset holding one dump past its first window,
    and the preset's configuration as a file beside it."""
    import numpy as np

    from dem.dumps import format_snapshot
    from workflows.config import dump_toml, load_preset

    run_dir = tmp_path / "run"
    assert main(["dem", "deck", "--preset", "smoke", "--out", str(run_dir)]) == 0
    config = load_preset("smoke")
    step = int(round(5.0 / config.dem.timestep_s))
    columns = ("id", "type", "x", "y", "z", "vx", "vy", "vz", "radius")
    rows = np.array([[1, 1, 0.01, 0.01, 0, 0.1, 0, 0, 0.003], [2, 2, 0.2, -0.01, 0, 0.1, 0, 0, 0.003]])
    dump = run_dir / "dumps" / f"dump.{step}.txt"
    dump.write_bytes(format_snapshot(step, columns, rows))
    config_file = tmp_path / "smoke.toml"
    config_file.write_text(dump_toml(config))
    return run_dir, dump, config_file


@pytest.mark.parametrize("target", ["config", "dump", "dump via a symlink"])
def test_no_output_over_an_input(tmp_path, capsys, target):
    run_dir, dump, config_file = _smoke_run_with_one_dump(tmp_path)
    victim = {"config": config_file, "dump": dump, "dump via a symlink": tmp_path / "link.h5"}[target]
    if target == "dump via a symlink":
        victim.symlink_to(dump)
    before = (dump if target != "config" else config_file).read_bytes()
    capsys.readouterr()
    code = main(
        [
            "dem",
            "post",
            "--config",
            str(config_file),
            "--dumps",
            str(run_dir / "dumps" / "dump.*.txt"),
            "--out-file",
            str(victim),
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "one of this command's inputs" in err and len(err.strip().splitlines()) == 1, err
    assert (dump if target != "config" else config_file).read_bytes() == before


def test_a_run_directory_never_replaces_its_configuration(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    config_file = out / "config.toml"
    config_file.write_text('name = "mine"\n[dem.run]\nnp = 1\n')
    before = config_file.read_text()
    for argv in (
        ["dem", "deck", "--config", str(config_file), "--out", str(out)],
        ["dem", "slurm", "--config", str(config_file), "--out", str(out), "--holdup", "1000", "--throughput", "1e6"],
    ):
        capsys.readouterr()
        assert main(argv) == 2
        assert "one of this command's inputs" in capsys.readouterr().err
        assert config_file.read_text() == before


def test_a_runs_directory_that_is_a_symlink_loop_is_one_line(tmp_path, capsys):
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    capsys.readouterr()
    assert main(["dem", "run", "--preset", "smoke", "--runs-dir", str(loop), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "symlink loop" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_too_many_noise_members_are_refused_before_the_dem(tmp_path, capsys):
    capsys.readouterr()
    assert (
        main(
            [
                "compare",
                "--preset",
                "smoke",
                "--noise-members",
                "100000000",
                "--runs-dir",
                str(tmp_path / "runs"),
                "--out",
                str(tmp_path / "results"),
                "--no-progress",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "members" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "runs").exists()  # nothing started
