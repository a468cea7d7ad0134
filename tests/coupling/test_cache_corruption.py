"""Damaged cache and table files: never trusted, never a traceback.

Hundreds of seeded random corruptions (bit flips, truncations, garbage blocks) of a real
cache entry must each either raise CacheError or load data identical to the original; a
change in the JSON attributes (not covered by HDF5's own checksums) is caught by the
digest; the shipped reference file carries a valid digest."""

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from coupling.cache import DIGEST_ATTR, RESULTS_GROUP, cache_path, load_entry, save_entry, try_load_entry
from coupling.errors import CacheError, TableError
from coupling.tables import read_table, write_table
from dem.post import postprocess
from tests.known_dumps import config, write_synthetic
from workflows.shipped import REFERENCE_DIR

REFERENCE = REFERENCE_DIR
TABLE_FIELDS = ("t", "x_edges", "y_edges", "vx_pos", "vx_neg", "vy_pos", "vy_neg", "count_A", "count_B", "n_samples")


@pytest.fixture(scope="module")
def entry(tmp_path_factory):
    directory = tmp_path_factory.mktemp("dumps")
    cfg = config()
    write_synthetic(directory, cfg)
    results = postprocess(str(directory / "dump.*.txt"), cfg, provenance={"input_hash": "abc"})
    prov = {
        "key": "k1",
        "liggghts_version": "LIGGGHTS-PUBLIC 3.8.0",
        "config_toml": 'name = "x"\n',
        "wall_time_s": 12.5,
    }
    return results.to_cache_entry(prov)


def _equal(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")


def differences(a, b) -> list[str]:
    """What differs between two cache entries (empty: identical, NaN equal to NaN)."""
    diff = [f"table.{n}" for n in TABLE_FIELDS if not _equal(getattr(a.table, n), getattr(b.table, n))]
    if (a.table.window_s, a.table.min_samples, a.table.attrs) != (b.table.window_s, b.table.min_samples, b.table.attrs):
        diff.append("table attributes")
    if sorted(a.frames) != sorted(b.frames) or sorted(a.arrays) != sorted(b.arrays):
        return diff + ["frame or array names"]
    for name in a.frames:
        fa, fb = a.frames[name], b.frames[name]
        if list(fa.columns) != list(fb.columns) or not all(
            _equal(fa[c].to_numpy(), fb[c].to_numpy()) for c in fa.columns
        ):
            diff.append(f"frame {name}")
    diff += [f"array {n}" for n in a.arrays if not _equal(a.arrays[n], b.arrays[n])]
    # the JSON text compares NaN as equal to NaN, which == on dicts does not
    if json.dumps(a.summary, sort_keys=True) != json.dumps(b.summary, sort_keys=True):
        diff.append("summary")
    if a.provenance != b.provenance:
        diff.append("provenance")
    return diff


def damage(data: bytes, kind: str, rng: np.random.Generator) -> bytes:
    buf = bytearray(data)
    if kind == "flip":
        for _ in range(int(rng.integers(1, 9))):
            buf[int(rng.integers(len(buf)))] ^= 1 << int(rng.integers(8))
    elif kind == "truncate":
        buf = buf[: int(rng.integers(len(buf)))]
    else:
        size, offset = int(rng.integers(1, 513)), int(rng.integers(len(buf)))
        buf[offset : offset + size] = rng.integers(0, 256, size, dtype=np.uint8).tobytes()[: len(buf) - offset]
    return bytes(buf)


def damaged_loads(entry, directory: Path, count: int = 300, seed: int = 20261123):
    """Load ``count`` seeded damaged copies of ``entry``'s cache file (bit flips,
    truncations, garbage blocks in turn). Returns (outcomes, changed, crashed): how many
    were refused or loaded identical data, and the ones that loaded changed data or raised
    anything but CacheError."""
    original_path = save_entry(directory / "original.h5", entry)
    original = load_entry(original_path, key="k1")
    assert differences(original, entry) == []
    data = original_path.read_bytes()
    rng = np.random.default_rng(seed)
    outcomes = {"refused": 0, "identical": 0}
    changed, crashed = [], []
    for i in range(count):
        kind = ("flip", "truncate", "garbage")[i % 3]
        path = directory / f"dem-{i}.h5"
        path.write_bytes(damage(data, kind, rng))
        try:
            loaded = load_entry(path, key="k1")
        except CacheError as exc:
            assert str(path) in str(exc)
            outcomes["refused"] += 1
        except Exception as exc:  # noqa: BLE001 - the point is that none escapes
            crashed.append(f"{kind} #{i}: {type(exc).__name__}: {exc}")
        else:
            diff = differences(loaded, original)
            if diff:
                changed.append(f"{kind} #{i}: {diff}")
            else:
                outcomes["identical"] += 1
        path.unlink()
    return outcomes, changed, crashed


def test_randomly_damaged_cache_files_are_refused_or_identical(tmp_path, entry):
    outcomes, changed, crashed = damaged_loads(entry, tmp_path)
    assert crashed == [], crashed[:5]
    assert changed == [], changed[:5]
    # the damage is real: most files are refused (measured: 173 of 300 since the datasets are
    # gzip-compressed in chunks; the others were damaged in bytes HDF5 leaves unused, so they
    # load the original data)
    assert outcomes["refused"] >= 150, outcomes


@pytest.mark.parametrize("where", ["summary", "provenance"])
def test_changed_json_attribute_is_caught_by_the_digest(tmp_path, entry, where):
    """A digit changed inside the JSON held in an attribute, where no HDF5 checksum looks."""
    path = save_entry(tmp_path / "c.h5", entry)
    data = bytearray(path.read_bytes())
    needle = b'"wall_time_s": 12.5' if where == "provenance" else b'"inserted": '
    offset = data.find(needle)
    assert offset >= 0, f"{needle!r} not found in the file"
    digit = offset + len(needle) + (-1 if where == "provenance" else 0)
    assert chr(data[digit]).isdigit()
    data[digit] = ord("7") if data[digit] != ord("7") else ord("3")
    path.write_bytes(bytes(data))
    with h5py.File(path, "r") as h5:  # the file is still perfectly readable HDF5
        assert h5.attrs["format"] == "pbmdem-cache"
    with pytest.raises(CacheError, match="does not match its sha256 digest"):
        load_entry(path, key="k1")


def test_file_without_digest_is_refused(tmp_path, entry):
    path = save_entry(tmp_path / "c.h5", entry)
    with h5py.File(path, "a") as h5:
        del h5.attrs[DIGEST_ATTR]
    loaded, reason = try_load_entry(path, key="k1")
    assert loaded is None and "no 'sha256' integrity digest" in reason


def test_cache_path_that_is_a_directory(tmp_path):
    directory = cache_path(tmp_path, "k1")
    directory.mkdir()
    with pytest.raises(CacheError, match="is a directory"):
        load_entry(directory)
    loaded, reason = try_load_entry(directory, key="k1")
    assert loaded is None and "is a directory" in reason


def test_unexpected_error_type_while_reading_becomes_cache_error(tmp_path, entry, monkeypatch):
    """h5py reports some damage as RuntimeError ("bad local heap signature"): still CacheError."""
    path = save_entry(tmp_path / "c.h5", entry)

    def broken(*args, **kwargs):
        raise RuntimeError("Unable to synchronously open object (bad local heap signature)")

    monkeypatch.setattr("coupling.cache.table_from_group", broken)
    with pytest.raises(CacheError, match=r"c\.h5 is corrupt or unreadable: RuntimeError: .*bad local heap"):
        load_entry(path, key="k1")


def test_shipped_reference_file_loads_with_a_valid_digest(tmp_path):
    files = sorted(REFERENCE.glob("dem-*.h5"))
    assert files, f"no shipped reference cache file in {REFERENCE}"
    for path in files:
        key = path.stem.removeprefix("dem-")
        loaded = load_entry(path, key=key)
        assert loaded.key == key
        # a copy with one byte of one velocity changed in place is refused
        copy = tmp_path / path.name
        shutil.copy(path, copy)
        with h5py.File(copy, "r") as h5:
            offset = h5["velocity_table/t"].id.get_offset()  # uncompressed, contiguous
        data = bytearray(copy.read_bytes())
        data[offset] ^= 0x01
        copy.write_bytes(bytes(data))
        with pytest.raises(CacheError):
            load_entry(copy, key=key)


def test_randomly_damaged_table_files_raise_table_error_only(tmp_path, entry):
    original_path = write_table(tmp_path / "original.h5", entry.table)
    original = read_table(original_path)
    data = original_path.read_bytes()
    rng = np.random.default_rng(7)
    crashed = []
    for i in range(150):
        kind = ("flip", "truncate", "garbage")[i % 3]
        path = tmp_path / f"t-{i}.h5"
        path.write_bytes(damage(data, kind, rng))
        try:
            read_table(path)
        except TableError as exc:
            assert str(path) in str(exc)
        except Exception as exc:  # noqa: BLE001 - the point is that none escapes
            crashed.append(f"{kind} #{i}: {type(exc).__name__}: {exc}")
        path.unlink()
    assert crashed == [], crashed[:5]
    assert original.n_windows == entry.table.n_windows
    directory = tmp_path / "dir.h5"
    directory.mkdir()
    with pytest.raises(TableError, match="is a directory"):
        read_table(directory)


if (
    __name__ == "__main__"
):  # python tests/coupling/test_cache_corruption.py: the same damage with and without the digest
    import tempfile
    from unittest import mock

    import coupling.cache

    with tempfile.TemporaryDirectory() as tmp:
        cfg = config()
        write_synthetic(Path(tmp), cfg)
        results = postprocess(str(Path(tmp) / "dump.*.txt"), cfg, provenance={"input_hash": "abc"})
        sample = results.to_cache_entry({"key": "k1", "config_toml": 'name = "x"\n'})
        for label, check in (("digest checked", None), ("digest not checked", "off")):
            with mock.patch.object(
                coupling.cache,
                "file_digest",
                (lambda h5, values=None: h5.attrs.get(DIGEST_ATTR, "unchecked"))
                if check
                else coupling.cache.file_digest,
            ):
                outcomes, changed, crashed = damaged_loads(sample, Path(tmp))
            print(f"{label:20s} {outcomes}, loaded changed data: {len(changed)}, other exceptions: {len(crashed)}")


# ----------------------------------------------------------------------------- issue 22: one verified loader
def _edit_dataset(path, name, change):
    with h5py.File(path, "a") as h5:
        data = h5[name][()]
        h5[name][...] = change(data)


def test_edited_cache_file_is_refused_by_read_table_too(tmp_path, entry):
    """`pbmdem pbm run --tables` reads a results file through read_table: a dataset edited
    after writing (mean residence time 18.72 -> 3.05 s in the probe) is refused, naming the file."""
    path = save_entry(tmp_path / "dem-k1.h5", entry)
    assert read_table(path).n_windows == entry.table.n_windows  # intact: readable as a table
    _edit_dataset(path, "velocity_table/vx_pos", lambda v: v * 5)
    with pytest.raises(TableError, match=r"dem-k1\.h5 is corrupt or was edited: .*sha256 digest"):
        read_table(path)
    with pytest.raises(CacheError, match="does not match its sha256 digest"):
        load_entry(path)


def test_table_files_carry_a_digest_and_an_edit_is_refused(tmp_path, entry):
    path = write_table(tmp_path / "t.h5", entry.table)
    with h5py.File(path, "r") as h5:
        assert h5.attrs["format"] == "pbmdem-table" and len(h5.attrs[DIGEST_ATTR]) == 64
    _edit_dataset(path, "velocity_table/vy_pos", lambda v: v + 0.01)
    with pytest.raises(TableError, match=r"t\.h5 is corrupt or was edited"):
        read_table(path)
    # a file that says it is ours but lost its digest is refused; a foreign table without
    # one (written by another tool following the schema) is read and validated
    path = write_table(tmp_path / "u.h5", entry.table)
    with h5py.File(path, "a") as h5:
        del h5.attrs[DIGEST_ATTR]
    with pytest.raises(TableError, match="carries no 'sha256' integrity digest"):
        read_table(path)
    with h5py.File(path, "a") as h5:
        del h5.attrs["format"]
    assert read_table(path).n_windows == entry.table.n_windows


def test_every_shipped_h5_file_reads_through_the_verified_loader():
    files = sorted(REFERENCE.rglob("*.h5"))
    assert len(files) >= 7, files
    for path in files:
        assert read_table(path).n_windows >= 1, path


def _foreign_table(path, entry, **changes):
    """A signed table file with ``changes`` applied to its datasets or attributes."""
    from coupling.files import sign_h5

    write_table(path, entry.table)
    with h5py.File(path, "a") as h5:
        group = h5["velocity_table"]
        for name, value in changes.items():
            if name in group.attrs:
                group.attrs[name] = value
            else:
                group[name][...] = value(group[name][()])
    sign_h5(path)
    return path


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"vx_pos": lambda v: v * 1e300}, r"dataset 'vx_pos' holds .*e\+29\d m/s .*values up to 100 m/s are physical"),
        ({"vy_neg": lambda v: v + 150.0}, "dataset 'vy_neg' holds 15"),
        (
            {name: (lambda v: v * 0) for name in ("vx_pos", "vx_neg", "vy_pos", "vy_neg")},
            "every velocity is 0 in all .* compartment-windows with samples",
        ),
        ({"schema_version": 2.5}, r"'schema_version' = .*2\.5.* is not an integer; valid versions: \(1, 2, 3\)"),
        ({"schema_version": "2"}, "'schema_version' = '2' .*is not an integer"),
        ({"schema_version": True}, "is not an integer"),
        ({"min_samples": 2.5}, "'min_samples' = 2.5 .*is not an integer"),
        ({"count_A": lambda v: v + 1e17}, "dataset 'count_A' holds 1e\\+17"),
        ({"x_edges": lambda v: v * 1e6}, "compartment edges within 1000 m"),
        ({"t": lambda v: v + 1e12}, "window times within 1e\\+09 s"),
    ],
)
def test_absurd_table_values_are_refused_by_name(tmp_path, entry, changes, message):
    path = _foreign_table(tmp_path / "t.h5", entry, **changes)
    with pytest.raises(TableError, match=message) as info:
        read_table(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_fifo_and_symlink_loop_as_input_files_are_refused_in_one_line(tmp_path):
    import os

    fifo = tmp_path / "tables.h5"
    os.mkfifo(fifo)
    with pytest.raises(TableError, match=r"tables\.h5 is a FIFO \(named pipe\), not a regular file"):
        read_table(fifo)  # would block forever in open()
    with pytest.raises(CacheError, match="is a FIFO"):
        load_entry(fifo)
    loop = tmp_path / "loop.h5"
    os.symlink(tmp_path / "other.h5", loop)
    os.symlink(loop, tmp_path / "other.h5")
    with pytest.raises(TableError, match=r"loop\.h5 is a symlink loop") as info:
        read_table(loop)
    assert "\n" not in str(info.value)


def test_output_over_an_input_is_refused_before_writing(tmp_path):
    import os

    from coupling.errors import OutputError
    from coupling.files import output_directory_path, refuse_output_over_inputs

    dump = tmp_path / "dump.1.txt"
    dump.write_text("x")
    config = tmp_path / "c.toml"
    config.write_text("y")
    link = tmp_path / "link.txt"
    os.symlink(dump, link)
    hard = tmp_path / "hard.txt"
    os.link(config, hard)
    for out in (dump, link, hard, tmp_path / "sub" / ".." / "c.toml"):
        with pytest.raises(OutputError, match="is one of this command's inputs"):
            refuse_output_over_inputs(out, [dump, config, None], "--out")
    assert refuse_output_over_inputs(tmp_path / "new.h5", [dump, config], "--out") == (tmp_path / "new.h5").resolve()
    assert dump.read_text() == "x" and config.read_text() == "y"
    os.symlink(tmp_path / "b", tmp_path / "a")
    os.symlink(tmp_path / "a", tmp_path / "b")
    with pytest.raises(OutputError, match="is a symlink loop") as info:
        output_directory_path(tmp_path / "a", "--runs-dir")
    assert "\n" not in str(info.value)
    with pytest.raises(OutputError, match="is a file, not a directory"):
        output_directory_path(config / "runs", "--runs-dir")
    assert output_directory_path(tmp_path / "new" / "runs", "--runs-dir") == tmp_path / "new" / "runs"


def test_a_cache_file_is_read_once_for_its_digest_and_its_data(tmp_path, entry, monkeypatch):
    """The digest check hands the loader what it read: no results dataset is decompressed
    twice, and what is loaded is what was saved."""
    path = save_entry(tmp_path / "dem-k1.h5", entry)
    reads: dict[str, int] = {}
    original = h5py.Dataset.__getitem__

    def counted(self, key):
        reads[self.name] = reads.get(self.name, 0) + 1
        return original(self, key)

    monkeypatch.setattr(h5py.Dataset, "__getitem__", counted)
    loaded = load_entry(path)
    results = {name: count for name, count in reads.items() if name.startswith(f"/{RESULTS_GROUP}/")}
    assert results and max(results.values()) == 1, results
    for name, array in entry.arrays.items():
        np.testing.assert_array_equal(loaded.arrays[name], array)
    for name, frame in entry.frames.items():
        np.testing.assert_array_equal(loaded.frames[name].to_numpy(), frame.to_numpy())
