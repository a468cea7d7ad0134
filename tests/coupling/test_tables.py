"""The velocity-table interface: round trip, and every bad input named."""

import h5py
import numpy as np
import pytest

from coupling.errors import TableError
from coupling.files import sign_h5
from coupling.tables import RATE_NAMES, SCHEMA_VERSION, make_table, read_table, write_table


def _table(rng, k=3, nx=4, ny=5):
    shape = (k, nx, ny)
    return make_table(
        t=np.arange(k) * 5.0,
        x_edges=np.linspace(0, 0.33, nx + 1),
        y_edges=np.linspace(-0.05, 0.05, ny + 1),
        vx_pos=rng.uniform(0, 0.1, shape),
        vx_neg=rng.uniform(0, 0.05, shape),
        vy_pos=rng.uniform(0, 0.2, shape),
        vy_neg=rng.uniform(0, 0.2, shape),
        count_A=rng.uniform(0, 30, shape),
        count_B=rng.uniform(0, 30, shape),
        n_samples=rng.integers(0, 100, shape),
        min_samples=5,
        attrs={"input_hash": "abc", "preset": "smoke", "config": {"a": 1}},
    )


def test_round_trip_preserves_every_dataset_and_attribute(tmp_path, rng):
    table = _table(rng)
    back = read_table(write_table(tmp_path / "t.h5", table))
    for name in ("t", "x_edges", "y_edges", "vx_pos", "vx_neg", "vy_pos", "vy_neg", "count_A", "count_B", "n_samples"):
        np.testing.assert_array_equal(getattr(back, name), getattr(table, name), err_msg=name)
    assert back.window_s == 5.0 and back.min_samples == 5
    assert back.attrs["input_hash"] == "abc" and back.attrs["config"] == {"a": 1}
    np.testing.assert_array_equal(back.valid, table.n_samples >= 5)
    with h5py.File(tmp_path / "t.h5") as h5:
        assert h5["velocity_table"].attrs["schema_version"] == SCHEMA_VERSION


def test_window_index_switches_at_table_times(rng):
    table = _table(rng)
    assert [table.window_index(t) for t in (0, 4.99, 5.0, 12, 100)] == [0, 0, 1, 2, 2]
    assert table.t_end == 15.0


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(vx_pos=-1.0), "'vx_pos' must be >= 0"),
        (dict(vy_neg=np.nan), "'vy_neg' contains NaN"),
        (dict(count_A=np.zeros((3, 4, 4))), "'count_A' has shape (3, 4, 4)"),
        (dict(t=[0.0, 5.0, 5.0]), "'t' must be finite and strictly increasing"),
        (dict(window_s=0.0), "'window_s' must be > 0"),
    ],
)
def test_bad_values_are_refused_with_the_dataset_named(rng, change, message):
    table = _table(rng)
    if "vx_pos" in change or "vy_neg" in change:
        name, value = next(iter(change.items()))
        arr = getattr(table, name).copy()
        arr[1, 2, 3] = value
        change = {name: arr}
    with pytest.raises(TableError) as info:
        table.replace(**change)
    assert message in str(info.value)


def test_missing_dataset_and_unknown_schema_are_refused(tmp_path, rng):
    path = write_table(tmp_path / "t.h5", _table(rng))
    with h5py.File(path, "a") as h5:
        del h5["velocity_table/vy_pos"]
    sign_h5(path)  # an edit on purpose: signed again, so the check under test is reached
    with pytest.raises(TableError, match="dataset 'vy_pos' is missing"):
        read_table(path)
    path = write_table(tmp_path / "u.h5", _table(rng))
    with h5py.File(path, "a") as h5:
        h5["velocity_table"].attrs["schema_version"] = 99
    sign_h5(path)  # an edit on purpose: signed again, so the check under test is reached
    with pytest.raises(TableError, match="unknown velocity-table schema_version 99"):
        read_table(path)
    (tmp_path / "junk.h5").write_text("not hdf5")
    with pytest.raises(TableError, match="not a readable HDF5 file"):
        read_table(tmp_path / "junk.h5")


def test_failed_write_leaves_no_file(tmp_path, rng):
    class Boom(Exception):
        pass

    from coupling.tables import atomic_h5

    with pytest.raises(Boom):
        with atomic_h5(tmp_path / "x.h5") as h5:
            h5["a"] = 1
            raise Boom
    assert list(tmp_path.iterdir()) == []


def _rates(rng, k=3, nx=4, ny=5):
    rates = {name: rng.uniform(0, 2.0, (k, nx, ny)) for name in RATE_NAMES}
    rates["rate_x_neg"][:, 0, :] = 0.0  # walls: no transition crosses them
    rates["rate_y_neg"][:, :, 0] = 0.0
    rates["rate_y_pos"][:, :, -1] = 0.0
    rates["rate_x_pos"][1, 2, 3] = np.nan  # too few observations
    rates["rate_y_pos"][:, 0, 0] = np.nan
    return rates


def test_round_trip_with_measured_rates_keeps_their_nans(tmp_path, rng):
    table = _table(rng).replace(**_rates(rng))
    assert table.has_rates
    back = read_table(write_table(tmp_path / "t.h5", table))
    assert back.has_rates
    for name in RATE_NAMES:
        np.testing.assert_array_equal(getattr(back, name), getattr(table, name), err_msg=name)  # NaN == NaN here
    assert np.isnan(back.rate_x_pos[1, 2, 3]) and np.isnan(back.rate_y_pos[:, 0, 0]).all()
    with h5py.File(tmp_path / "t.h5") as h5:
        assert h5["velocity_table"].attrs["schema_version"] == SCHEMA_VERSION == 2
        assert all(name in h5["velocity_table"] for name in RATE_NAMES)


def test_a_table_without_rates_is_written_as_version_2_without_rate_datasets(tmp_path, rng):
    table = _table(rng)
    assert not table.has_rates and table.rate_x_pos is None
    path = write_table(tmp_path / "t.h5", table)
    with h5py.File(path) as h5:
        assert h5["velocity_table"].attrs["schema_version"] == 2
        assert not any(name in h5["velocity_table"] for name in RATE_NAMES)
    assert not read_table(path).has_rates


def test_version_1_files_still_read(tmp_path, rng):
    table = _table(rng)
    path = write_table(tmp_path / "v1.h5", table)
    with h5py.File(path, "a") as h5:  # exactly what version 1 wrote: no rates, schema_version 1
        h5["velocity_table"].attrs["schema_version"] = 1
    sign_h5(path)  # an edit on purpose: signed again, so the check under test is reached
    back = read_table(path)
    assert not back.has_rates
    np.testing.assert_array_equal(back.vx_pos, table.vx_pos)
    assert back.attrs["input_hash"] == "abc"


def test_rates_are_all_four_or_none(tmp_path, rng):
    rates = _rates(rng)
    with pytest.raises(TableError, match=r"dataset\(s\) \['rate_y_neg'\] missing"):
        _table(rng).replace(**{name: rates[name] for name in RATE_NAMES[:3]})
    path = write_table(tmp_path / "t.h5", _table(rng).replace(**rates))
    with h5py.File(path, "a") as h5:
        del h5["velocity_table/rate_x_neg"]
    sign_h5(path)  # an edit on purpose: signed again, so the check under test is reached
    with pytest.raises(TableError, match=r"\['rate_x_neg'\] missing.*all four.*t.h5"):
        read_table(path)


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("rate_y_pos", -0.5, "'rate_y_pos' must be >= 0 everywhere; window 1, compartment (2, 3) holds -0.5"),
        ("rate_x_neg", np.inf, "'rate_x_neg' contains infinite values; every entry must be finite or NaN"),
    ],
)
def test_bad_rates_are_refused_with_the_dataset_named(rng, name, value, message):
    rates = _rates(rng)
    rates[name][1, 2, 3] = value
    with pytest.raises(TableError) as info:
        _table(rng).replace(**rates)
    assert message in str(info.value)


def test_rates_of_the_wrong_shape_are_refused_by_name(rng):
    rates = _rates(rng)
    rates["rate_x_pos"] = rates["rate_x_pos"][:, :, :4]
    with pytest.raises(TableError, match=r"dataset 'rate_x_pos' has shape \(3, 4, 4\)"):
        _table(rng).replace(**rates)


def test_make_table_broadcasts_rates(rng):
    table = make_table(
        t=[0.0, 5.0],
        x_edges=[0, 0.1, 0.2],
        y_edges=[-0.05, 0.05],
        vx_pos=0.01,
        vx_neg=0,
        vy_pos=0,
        vy_neg=0,
        rate_x_pos=0.1,
        rate_x_neg=np.nan,
        rate_y_pos=0,
        rate_y_neg=0,
    )
    assert table.rate_x_pos.shape == (2, 2, 1) and np.isnan(table.rate_x_neg).all()
