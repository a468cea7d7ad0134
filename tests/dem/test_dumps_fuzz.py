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

from coupling.errors import DumpFormatError
from dem.config import DemConfig, TablesConfig
from dem.dumps import TruncatedDumpWarning
from dem.post import postprocess

SMOKE = sorted((Path(__file__).parent / "static" / "smoke_dumps").glob("dump.*.txt"))
N_VARIANTS = 2000
SEED = 20261123
HEADER_LINES = 9

SUBSTITUTES = [b"0", b"7", b"9", b"-", b".", b"e", b"E", b"+", b"x", b"a", b" ", b"\n", b"\t", b"\r",
               b"inf", b"-inf", b"nan", b"NaN", b"Infinity", b"\xff", b"\x80", b"\xc3", b"\xe2\x82", b"\x00",
               b"9e12", b"1e308", b"1e400", b"-1", b"0.5"]
HEADER_EDITS = [
    # (header line index, replacement)
    (1, b"-5"), (1, b"1e3"), (1, b"99999999999999999999"), (1, b"\xff\xfe"),
    (3, b"0"), (3, b"-1"), (3, b"1000000000000"), (3, b"72"), (3, b"74"),
    (4, b"ITEM: BOX BOUNDS xy xz yz ff ff ff"), (4, b"ITEM: BOX BOUNDS \xff\xfe ff"),
    (5, b"-0.005"), (5, b"0.35 -0.005"), (5, b"-0.005 inf"), (5, b"nan 0.35"), (5, b"-0.005 0.35 0.0"),
    (6, b""), (6, b"0.1 0.1"), (7, b"-0.055 0.055 0.01 7"), (7, b"a b"),
    (8, b"ITEM: ATOMS id type x y z vx vy vz"), (8, b"ITEM: ATOMS id id x y z vx vy vz radius"),
    (8, b"ITEM: ATOMS id type x y z vx vy"), (8, b"ITEM: ATOMS id type x \xff z vx vy vz radius"),
    (8, b"ITEM: ATOMS"), (8, b"ITEM: ATOMS type id x y z vx vy vz radius extra"),
    (0, b"ITEM: TIMESTEPS"), (2, b"ITEM: NUMBER OF ATOMS \xc3"),
]


def config():
    return DemConfig(tables=TablesConfig(nx=4, ny=2, window_s=5.0, sample_interval_s=1.0, min_samples=1))


def mutate(data: bytes, rng: random.Random) -> tuple[str, bytes]:
    """One corrupted copy of ``data`` and the name of the corruption."""
    kind = rng.choice(["flip", "flip", "sub", "sub", "sub", "truncate", "dup", "delete", "header", "header",
                       "multi"])
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
        fields[rng.randrange(len(fields) - 1)] = rng.choice([b"inf", b"-inf", b"nan", b"9e12", b"-3", b"1.5",
                                                              b"0", b"1e300", b"2147483648"])
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
    for k, original in enumerate(originals):
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
