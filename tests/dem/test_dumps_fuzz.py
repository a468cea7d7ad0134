"""Fuzzing the dump reader and the post-processing with corrupted real LIGGGHTS dumps.

Every variant of ``tests/dem/static/smoke_dumps`` (bit flips, byte substitutions, truncations,
duplicated or deleted lines, header edits) must either post-process to finite results or
raise :class:`~coupling.errors.DumpFormatError`; any other exception, and any warning but
the documented :class:`~dem.dumps.TruncatedDumpWarning`, is a failure. The generator is
seeded, so a failing variant is reproduced by its index.
"""

from __future__ import annotations

import collections
import random
import warnings
from pathlib import Path

import numpy as np
import pytest

from coupling.errors import DumpFormatError
from dem.config import DemConfig, TablesConfig
from dem.dumps import TruncatedDumpWarning
from dem.post import postprocess

SMOKE = sorted((Path(__file__).parent / "static" / "smoke_dumps").glob("dump.*.txt"))
N_VARIANTS = 2000
SEED = 20261123
HEADER_LINES = 9

SUBSTITUTES = [
    b"0",
    b"7",
    b"9",
    b"-",
    b".",
    b"e",
    b"E",
    b"+",
    b"x",
    b"a",
    b" ",
    b"\n",
    b"\t",
    b"\r",
    b"inf",
    b"-inf",
    b"nan",
    b"NaN",
    b"Infinity",
    b"\xff",
    b"\x80",
    b"\xc3",
    b"\xe2\x82",
    b"\x00",
    b"9e12",
    b"1e308",
    b"1e400",
    b"-1",
    b"0.5",
]
HEADER_EDITS = [
    # (header line index, replacement)
    (1, b"-5"),
    (1, b"1e3"),
    (1, b"99999999999999999999"),
    (1, b"\xff\xfe"),
    (3, b"0"),
    (3, b"-1"),
    (3, b"1000000000000"),
    (3, b"72"),
    (3, b"74"),
    (4, b"ITEM: BOX BOUNDS xy xz yz ff ff ff"),
    (4, b"ITEM: BOX BOUNDS \xff\xfe ff"),
    (5, b"-0.005"),
    (5, b"0.35 -0.005"),
    (5, b"-0.005 inf"),
    (5, b"nan 0.35"),
    (5, b"-0.005 0.35 0.0"),
    (6, b""),
    (6, b"0.1 0.1"),
    (7, b"-0.055 0.055 0.01 7"),
    (7, b"a b"),
    (8, b"ITEM: ATOMS id type x y z vx vy vz"),
    (8, b"ITEM: ATOMS id id x y z vx vy vz radius"),
    (8, b"ITEM: ATOMS id type x y z vx vy"),
    (8, b"ITEM: ATOMS id type x \xff z vx vy vz radius"),
    (8, b"ITEM: ATOMS"),
    (8, b"ITEM: ATOMS type id x y z vx vy vz radius extra"),
    (0, b"ITEM: TIMESTEPS"),
    (2, b"ITEM: NUMBER OF ATOMS \xc3"),
]


def config():
    # 0.2-s windows: the dumps span t = 0.33-0.40 s at this config's timestep, and a window
    # longer than the dumps is refused (dem.post.check_windows_covered)
    return DemConfig(tables=TablesConfig(nx=4, ny=2, window_s=0.2, sample_interval_s=1.0, min_samples=1))


def mutate(data: bytes, rng: random.Random) -> tuple[str, bytes]:
    """One corrupted copy of ``data`` and the name of the corruption."""
    kind = rng.choice(["flip", "flip", "sub", "sub", "sub", "truncate", "dup", "delete", "header", "header", "multi"])
    buf = bytearray(data)
    if kind == "flip":
        for _ in range(rng.randint(1, 3)):
            at = rng.randrange(len(buf))
            buf[at] ^= 1 << rng.randrange(8)
    elif kind == "sub":
        at = rng.randrange(len(buf))
        buf[at : at + rng.randint(0, 3)] = rng.choice(SUBSTITUTES)
    elif kind == "truncate":
        del buf[rng.randrange(len(buf)) :]
    elif kind in ("dup", "delete"):
        lines = bytes(buf).split(b"\n")
        at = rng.randrange(len(lines) - 1)
        if kind == "dup":
            lines.insert(at, lines[at])
        else:
            del lines[at]
        buf = bytearray(b"\n".join(lines))
    elif kind == "header":
        lines = bytes(buf).split(b"\n")
        index, replacement = rng.choice(HEADER_EDITS)
        lines[index] = replacement
        buf = bytearray(b"\n".join(lines))
    else:  # a token of a random atom line replaced: the corruptions that parse as numbers
        lines = bytes(buf).split(b"\n")
        at = rng.randrange(HEADER_LINES, len(lines) - 1)
        fields = lines[at].split(b" ")
        fields[rng.randrange(len(fields) - 1)] = rng.choice(
            [b"inf", b"-inf", b"nan", b"9e12", b"-3", b"1.5", b"0", b"1e300", b"2147483648"]
        )
        lines[at] = b" ".join(fields)
        buf = bytearray(b"\n".join(lines))
    return kind, bytes(buf)


def run_variant(index: int, directory: Path, cfg: DemConfig) -> str:
    """'ok', 'DumpFormatError' or the name of the unexpected exception (or warning)."""
    rng = random.Random(SEED * 100_003 + index)
    originals = [p.read_bytes() for p in SMOKE]
    which = rng.randrange(len(originals))
    kind, corrupted = mutate(originals[which], rng)
    paths = []
    for k, _original in enumerate(originals):
        if k == which:
            path = directory / f"variant.{k}.txt"
            path.write_bytes(corrupted)
            paths.append(path)
        else:
            paths.append(SMOKE[k])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.simplefilter("ignore", TruncatedDumpWarning)
        try:
            res = postprocess(paths, cfg)
        except DumpFormatError:
            return "DumpFormatError"
        except Exception as exc:  # noqa: BLE001 -- counted and reported
            return f"{type(exc).__name__} ({kind}, variant {index}): {str(exc)[:160]}"
    table = res.table
    for name in ("vx_pos", "vx_neg", "vy_pos", "vy_neg", "count_A", "count_B"):
        if not np.isfinite(getattr(table, name)).all():
            return f"non-finite {name} ({kind}, variant {index})"
    if not np.isfinite(res.holdup[["holdup_A", "holdup_B"]].to_numpy()).all():
        return f"non-finite hold-up ({kind}, variant {index})"
    if res.summary.accounting["inserted"] > 200:  # the three dumps hold 87 distinct particles
        return f"{res.summary.accounting['inserted']} particles inserted ({kind}, variant {index})"
    return "ok"


def fuzz(n: int, directory: Path) -> collections.Counter:
    cfg = config()
    return collections.Counter(run_variant(i, directory, cfg) for i in range(n))


def test_fuzzed_real_dumps_postprocess_or_raise_dump_format_error(tmp_path):
    outcomes = fuzz(N_VARIANTS, tmp_path)
    unexpected = {k: v for k, v in outcomes.items() if k not in ("ok", "DumpFormatError")}
    assert not unexpected, unexpected
    # both branches are exercised: the corruptions are neither all harmless nor all fatal
    assert outcomes["ok"] > 100 and outcomes["DumpFormatError"] > 500, outcomes


# ----------------------------------------------------------------------------- issue 22: duplicates, paths, counts
def _with_duplicates(data: bytes, rows: list[int]) -> bytes:
    """``data`` (one snapshot) with the atom lines ``rows`` (0-based) listed a second time at
    the end and the atom count raised to match."""
    lines = data.split(b"\n")
    atoms = lines[HEADER_LINES:-1]
    lines[3] = str(len(atoms) + len(rows)).encode()
    return b"\n".join(lines[:HEADER_LINES] + atoms + [atoms[r] for r in rows] + [b""])


@pytest.mark.parametrize("variant", range(40))
def test_duplicate_atom_ids_are_refused_naming_file_step_and_id(tmp_path, variant):
    """A few rows twice, or every row twice (the probe's hold-up 434 beside the solver's 217)."""
    rng = random.Random(SEED + variant)
    which = rng.randrange(len(SMOKE))
    data = SMOKE[which].read_bytes()
    n = int(data.split(b"\n")[3])
    rows = list(range(n)) if variant % 4 == 0 else rng.sample(range(n), rng.randint(1, 5))
    paths = list(SMOKE)
    paths[which] = tmp_path / SMOKE[which].name
    paths[which].write_bytes(_with_duplicates(data, rows))
    step = int(data.split(b"\n")[1])
    with pytest.raises(
        DumpFormatError,
        match=rf"{SMOKE[which].name}: line \d+: snapshot at step {step} lists atom id "
        rf"\d+ twice \(lines \d+ and \d+\)",
    ) as info:
        postprocess(paths, config())
    assert "\n" not in str(info.value)


def test_fifo_and_symlink_loop_in_a_dump_glob_are_refused_without_hanging(tmp_path):
    import os

    for path in SMOKE:
        (tmp_path / path.name).write_bytes(path.read_bytes())
    os.mkfifo(tmp_path / "dump.99999.txt")  # opening it for reading would block forever
    with pytest.raises(DumpFormatError, match=r"dump\.99999\.txt is a FIFO \(named pipe\), not a regular file"):
        postprocess(str(tmp_path / "dump.*.txt"), config())
    (tmp_path / "dump.99999.txt").unlink()
    os.symlink(tmp_path / "dump.99998.txt", tmp_path / "dump.99999.txt")
    os.symlink(tmp_path / "dump.99999.txt", tmp_path / "dump.99998.txt")
    with pytest.raises(DumpFormatError, match="is a symlink loop") as info:
        postprocess(str(tmp_path / "dump.*.txt"), config())
    assert "\n" not in str(info.value)


def _dump_files(directory: Path, snapshots) -> None:
    from dem.dumps import format_snapshot

    columns = ("id", "type", "x", "y", "z", "vx", "vy", "vz", "radius")
    dt = config().timestep_s
    for t, rows in snapshots:
        step = int(round(t / dt))
        (directory / f"dump.{step}.txt").write_bytes(
            format_snapshot(step, columns, np.array(rows, float).reshape(-1, 9))
        )


def test_positions_outside_the_vessel_and_ids_after_discharge_are_counted(tmp_path):
    """Counted as warnings in the results, not refused: a particle centre 3 cm outside the
    barrel (inside the box), and one still dumped 1 s after its discharge record."""
    inside = (0.1, 0.0, -0.02)
    rows = lambda extra: [(1, 1, *inside, 0.1, 0, 0, 0.003), (2, 2, *inside, 0.1, 0, 0, 0.003), *extra]
    outside = (3, 1, 0.1, 0.0, 0.08, 0.1, 0, 0, 0.003)  # r = 80 mm in a 50 mm barrel
    _dump_files(tmp_path, [(t, rows([outside] if t < 1.0 else [])) for t in np.arange(0.0, 5.01, 0.5)])
    (tmp_path / "discharge_A.txt").write_text("# id time\n2 2.0\n")  # id 2 is in every dump, to 5 s
    res = postprocess(
        str(tmp_path / "dump.*.txt"),
        config(),
        massflow_dir=tmp_path,
        solver_counters={"atoms": 3, "step": int(round(5.0 / config().timestep_s))},
    )
    s = res.summary.record()  # the stored record: accounting keys and the new counts, by name
    assert s["positions_outside_vessel"] == 2  # id 3 at t = 0 and 0.5 s
    assert s["ids_seen_after_discharge"] == 1
    assert s["solver_atoms_diff"] == -1 and s["dumps_particles_last"] == 2
    text = " | ".join(s["warnings"])
    assert "2 particle-snapshots lie outside the vessel" in text
    assert "1 particles are still in the dumps after the time of their discharge record" in text
    assert "the last dump lists 2 particles, the solver's thermo 3" in text


def test_windows_longer_than_the_dumps_and_a_missing_massflow_dir_are_refused(tmp_path):
    from coupling.errors import ConfigError

    row = [(1, 1, 0.1, 0.0, -0.02, 0.1, 0, 0, 0.003)]
    _dump_files(tmp_path, [(t, row) for t in np.arange(0.5, 3.01, 0.5)])
    long = DemConfig(tables=TablesConfig(nx=4, ny=2, window_s=100.0, sample_interval_s=1.0, min_samples=1))
    with pytest.raises(
        ConfigError,
        match=r"tables\.window_s = 100 s is longer than the dumps, which end at t = 3 s.*"
        r"choose tables\.window_s <= 3 s",
    ):
        postprocess(str(tmp_path / "dump.*.txt"), long)
    with pytest.raises(ConfigError, match=r"massflow directory .*nowhere does not exist"):
        postprocess(str(tmp_path / "dump.*.txt"), config(), massflow_dir=tmp_path / "nowhere")


@pytest.mark.parametrize(
    ("nx", "message"),
    [
        (100_000, r"needs about .*TiB of memory; this machine has"),
        (200, r"measured-rate fit of tables\.nx x tables\.ny = 200 x 10 .*would take about .*limit 4\.0 h"),
    ],
)
def test_grids_that_cannot_be_held_or_fitted_are_refused_before_reading(tmp_path, nx, message):
    from coupling.errors import ResourceLimitError
    from dem.config import OperationConfig

    big = DemConfig(
        operation=OperationConfig(duration_s=40.0),
        tables=TablesConfig(nx=nx, ny=10, window_s=5.0, sample_interval_s=1.0, min_samples=1),
    )
    with pytest.raises(ResourceLimitError, match=message) as info:
        postprocess(str(tmp_path / "no-dumps-needed.*.txt"), big)
    assert "\n" not in str(info.value)


if __name__ == "__main__":  # python -m tests.test_dump_fuzz [N]: outcome counts
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        counts = fuzz(int(sys.argv[1]) if len(sys.argv) > 1 else N_VARIANTS, Path(tmp))
    by_type = collections.Counter(k.split(" ")[0] for k in counts.elements())
    print(dict(by_type))
    for key, count in counts.most_common():
        if key not in ("ok", "DumpFormatError"):
            print(count, key)
