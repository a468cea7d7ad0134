"""Results cache: generic parts round trip (and DEM results through them), reuse by key,
corrupt/foreign/incomplete files, atomic writes."""

import h5py
import numpy as np
import pytest

from coupling.cache import CacheEntry, cache_path, load_entry, save_entry, stable_hash, try_load_entry
from coupling.errors import CacheError
from dem.post import DemResults, postprocess
from tests.known_dumps import config, write_synthetic


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    directory = tmp_path_factory.mktemp("dumps")
    cfg = config()
    write_synthetic(directory, cfg)
    return postprocess(str(directory / "dump.*.txt"), cfg, provenance={"input_hash": "abc"})


def provenance(key="k1"):
    return {"key": key, "liggghts_version": "LIGGGHTS-PUBLIC 3.8.0", "config_toml": 'name = "x"\n', "wall_time_s": 12.5}


def save(path, results, key="k1"):
    return save_entry(path, results.to_cache_entry(provenance(key)))


def load(path, key=None):
    entry = load_entry(path, key)
    return entry.table, DemResults.from_cache_entry(entry), entry.provenance


def test_round_trip(tmp_path, results):
    path = save(cache_path(tmp_path, "k1"), results)
    assert path.name == "dem-k1.h5"
    table, loaded, prov = load(path, key="k1")
    np.testing.assert_array_equal(table.vx_pos, results.table.vx_pos)
    np.testing.assert_array_equal(table.n_samples, results.table.n_samples)
    assert table.attrs["input_hash"] == "abc"
    assert prov == provenance()
    for name in ("timeseries", "holdup", "rtd"):
        a, b = getattr(loaded, name), getattr(results, name)
        assert list(a.columns) == list(b.columns)
        np.testing.assert_array_equal(a.to_numpy(), b.to_numpy())
    np.testing.assert_array_equal(loaded.rsd_by_slice, results.rsd_by_slice)
    np.testing.assert_array_equal(loaded.residence_times_s, results.residence_times_s)
    for key, value in results.summary.record().items():
        if isinstance(value, float) and np.isnan(value):
            assert np.isnan(loaded.summary.record()[key])
        else:
            assert loaded.summary.record()[key] == value, key


def test_other_key_is_refused(tmp_path, results):
    path = save(tmp_path / "c.h5", results, "k1")
    with pytest.raises(CacheError, match="holds results for inputs k1, not k2"):
        load_entry(path, key="k2")


@pytest.mark.parametrize("damage", ["truncate", "garbage", "foreign", "incomplete", "no_table"])
def test_damaged_files_are_detected_not_trusted(tmp_path, results, damage):
    path = save(tmp_path / "c.h5", results)
    if damage == "truncate":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 3])
    elif damage == "garbage":
        path.write_bytes(b"not an hdf5 file at all" * 100)
    elif damage == "foreign":
        with h5py.File(path, "w") as h5:
            h5.create_dataset("something", data=[1, 2, 3])
    elif damage == "incomplete":
        with h5py.File(path, "a") as h5:
            h5.attrs["complete"] = False
    elif damage == "no_table":
        with h5py.File(path, "a") as h5:
            del h5["velocity_table/vx_pos"]
    with pytest.raises(CacheError):
        load_entry(path, key="k1")
    loaded, reason = try_load_entry(path, key="k1")
    assert loaded is None and reason


def test_missing_file(tmp_path):
    loaded, reason = try_load_entry(tmp_path / "nope.h5")
    assert loaded is None and "does not exist" in reason


def test_write_is_atomic(tmp_path, results):
    path = save(tmp_path / "c.h5", results, "old")
    before = path.read_bytes()

    class Broken(dict):
        def items(self):
            raise RuntimeError("disk full halfway")

    entry = results.to_cache_entry(provenance("new"))
    with pytest.raises(RuntimeError, match="halfway"):
        save_entry(path, CacheEntry(entry.table, entry.summary, entry.frames, Broken(), entry.provenance))
    assert path.read_bytes() == before  # the old file is intact
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.h5"]  # no temporary left behind
    assert load_entry(path).key == "old"


def test_provenance_needs_key(tmp_path, results):
    with pytest.raises(CacheError, match="key"):
        save_entry(tmp_path / "c.h5", results.to_cache_entry({"liggghts_version": "x"}))


def test_parts_are_generic(tmp_path, results):
    """Any side's results travel as named frames and arrays; NaN and infinity survive."""
    import pandas as pd

    entry = CacheEntry(
        results.table,
        {"a": float("nan"), "b": [1, float("inf")], "c": None},
        {"f": pd.DataFrame({"x": [1.0, 2.0], "n": [1, 2]})},
        {"v": np.arange(3)},
        {"key": "g"},
    )
    back = load_entry(save_entry(tmp_path / "g.h5", entry), key="g")
    assert np.isnan(back.summary["a"]) and back.summary["b"] == [1, float("inf")] and back.summary["c"] is None
    assert list(back.frames["f"].columns) == ["x", "n"] and back.frames["f"]["n"].tolist() == [1, 2]
    np.testing.assert_array_equal(back.arrays["v"], np.arange(3))


def test_stable_hash_ignores_key_order():
    assert stable_hash({"a": 1, "b": [1, 2]}) == stable_hash({"b": [1, 2], "a": 1})
    assert stable_hash({"a": 1}) != stable_hash({"a": 2})


def _edit(path, where, value):
    """Overwrite one dataset in place: a change a digest must notice."""
    with h5py.File(path, "a") as h5:
        data = h5[where][()]
        data.flat[0] = value
        del h5[where]
        h5.create_dataset(where, data=data)


def test_the_head_is_read_alone_and_checked_by_its_own_digest(tmp_path, results):
    """load_head gives what load_entry gives of the table, summary and provenance; a change
    in the table or the summary is refused by the head digest, a change in the bulk (the
    per-particle records) only by the whole file's, which load_head does not read."""
    from coupling.cache import load_head

    path = save(tmp_path / "c.h5", results)
    head, entry = load_head(path, key="k1"), load_entry(path, key="k1")
    assert head.summary == entry.summary and head.provenance == entry.provenance
    np.testing.assert_array_equal(head.table.vx_pos, entry.table.vx_pos)
    with pytest.raises(CacheError, match="holds results for inputs k1, not k2"):
        load_head(path, key="k2")

    bulk = save(tmp_path / "bulk.h5", results)
    _edit(bulk, "results/arrays/residence_times_s", -1.0)
    assert load_head(bulk).summary == entry.summary
    with pytest.raises(CacheError, match="does not match its sha256 digest"):
        load_entry(bulk)

    table = save(tmp_path / "table.h5", results)
    _edit(table, "velocity_table/vx_pos", 123.0)
    summary = save(tmp_path / "summary.h5", results)
    with h5py.File(summary, "a") as h5:
        h5["results"].attrs["summary"] = h5["results"].attrs["summary"].replace("0", "1", 1)
    for damaged in (table, summary):
        for reader in (load_head, load_entry):
            with pytest.raises(CacheError, match="corrupt or was edited"):
                reader(damaged)


def test_a_file_without_a_head_digest_is_checked_whole(tmp_path, results):
    """A file written before the head digest existed: load_head checks the whole file, so a
    change in its bulk is refused as load_entry refuses it; the whole-file digest does not
    cover the head digest, so such a file's digest is what it was."""
    from coupling.cache import load_head
    from coupling.files import DIGEST_ATTR, HEAD_DIGEST_ATTR

    path = save(tmp_path / "c.h5", results)
    with h5py.File(path, "a") as h5:
        whole = h5.attrs[DIGEST_ATTR]
        del h5.attrs[HEAD_DIGEST_ATTR]
    assert load_head(path).summary == load_entry(path).summary
    with h5py.File(path) as h5:
        assert h5.attrs[DIGEST_ATTR] == whole
    _edit(path, "results/arrays/residence_times_s", -1.0)
    with pytest.raises(CacheError, match="does not match its sha256 digest"):
        load_head(path)
