"""Dump reader: parsing by column name, streaming, truncated and malformed input."""

import numpy as np
import pytest

from coupling.errors import DumpFormatError
from dem.dumps import (
    TruncatedDumpWarning,
    dump_paths,
    format_snapshot,
    iter_snapshots,
    read_snapshot_file,
)

COLUMNS = ("id", "type", "x", "y", "z", "vx", "vy", "vz", "radius")


def _data(rng, n, first_id=1):
    values = rng.uniform(-0.05, 0.3, size=(n, len(COLUMNS)))
    values[:, 0] = np.arange(first_id, first_id + n)
    values[:, 1] = rng.integers(1, 3, n)
    return values


def test_per_snapshot_files_natural_order_and_values(tmp_path, rng):
    expected = {}
    for step in (0, 900, 1000, 10000):  # natural order: 900 before 1000
        data = _data(rng, 7)
        expected[step] = data
        (tmp_path / f"dump.{step}.txt").write_bytes(format_snapshot(step, COLUMNS, data))
    assert [p.name for p in dump_paths(str(tmp_path / "dump.*.txt"))] == [
        "dump.0.txt",
        "dump.900.txt",
        "dump.1000.txt",
        "dump.10000.txt",
    ]
    snaps = list(iter_snapshots(str(tmp_path / "dump.*.txt")))
    assert [s.step for s in snaps] == [0, 900, 1000, 10000]
    for snap in snaps:
        np.testing.assert_allclose(snap.data, expected[snap.step], rtol=1e-8)
        assert snap.columns == COLUMNS
        np.testing.assert_allclose(snap["vx"], expected[snap.step][:, 5], rtol=1e-8)


def test_columns_found_by_name_not_position(tmp_path, rng):
    data = _data(rng, 5)
    permuted = ("vx", "radius", "x", "id", "type", "y", "z", "vy", "vz")
    order = [COLUMNS.index(c) for c in permuted]
    path = tmp_path / "d.txt"
    path.write_bytes(format_snapshot(10, permuted, data[:, order]))
    (snap,) = read_snapshot_file(path)
    np.testing.assert_allclose(snap["x"], data[:, 2], rtol=1e-8)
    np.testing.assert_array_equal(snap["id"], data[:, 0])


def test_multi_snapshot_file_and_empty_snapshot(tmp_path, rng):
    path = tmp_path / "all.txt"
    blocks = [format_snapshot(0, COLUMNS, np.zeros((0, 9)))]
    blocks += [format_snapshot(100 * k, COLUMNS, _data(rng, 3 + k)) for k in (1, 2, 3)]
    path.write_bytes(b"".join(blocks))
    snaps = list(iter_snapshots(path))
    assert [s.n for s in snaps] == [0, 4, 5, 6]
    assert snaps[0]["x"].shape == (0,)


def test_lines_without_trailing_space_are_read(tmp_path):
    path = tmp_path / "d.txt"
    text = format_snapshot(5, ("id", "type", "x"), np.array([[1, 1, 0.5], [2, 2, 0.25]])).decode()
    path.write_text(text.replace(" \n", "\n"))
    (snap,) = read_snapshot_file(path)
    np.testing.assert_allclose(snap["x"], [0.5, 0.25])


def test_truncated_last_snapshot_dropped_with_warning(tmp_path, rng):
    for step in (0, 100, 200):
        (tmp_path / f"dump.{step}.txt").write_bytes(format_snapshot(step, COLUMNS, _data(rng, 50)))
    last = tmp_path / "dump.200.txt"
    last.write_bytes(last.read_bytes()[: len(last.read_bytes()) // 2])  # killed mid-write
    with pytest.warns(TruncatedDumpWarning, match="dump.200.txt"):
        steps = [s.step for s in iter_snapshots(str(tmp_path / "dump.*.txt"))]
    assert steps == [0, 100]


def test_truncated_at_line_boundary_is_detected(tmp_path, rng):
    path = tmp_path / "all.txt"
    good = format_snapshot(0, COLUMNS, _data(rng, 4))
    cut = format_snapshot(100, COLUMNS, _data(rng, 4))
    cut = cut[: cut.rfind(b"\n", 0, len(cut) - 1) + 1]  # one whole atom line missing
    path.write_bytes(good + cut)
    with pytest.warns(TruncatedDumpWarning):
        assert [s.step for s in iter_snapshots(path)] == [0]


def test_truncated_file_in_the_middle_is_an_error(tmp_path, rng):
    for step in (0, 100):
        (tmp_path / f"dump.{step}.txt").write_bytes(format_snapshot(step, COLUMNS, _data(rng, 20)))
    first = tmp_path / "dump.0.txt"
    first.write_bytes(first.read_bytes()[:-40])
    with pytest.raises(DumpFormatError, match=r"dump\.0\.txt: line \d+"):
        list(iter_snapshots(str(tmp_path / "dump.*.txt")))


def test_malformed_number_names_file_and_line(tmp_path, rng):
    path = tmp_path / "bad.txt"
    text = format_snapshot(0, COLUMNS, _data(rng, 5)).decode().splitlines(keepends=True)
    fields = text[11].split()
    fields[3] = "1.2.3"
    text[11] = " ".join(fields) + " \n"  # the third atom line is file line 12
    path.write_text("".join(text))
    with pytest.raises(DumpFormatError, match=r"bad\.txt: line 12"):
        read_snapshot_file(path)


def test_missing_field_names_the_line(tmp_path, rng):
    path = tmp_path / "bad.txt"
    lines = format_snapshot(0, COLUMNS, _data(rng, 5)).decode().splitlines(keepends=True)
    lines[10] = " ".join(lines[10].split()[:-1]) + "\n"
    path.write_text("".join(lines))
    with pytest.raises(DumpFormatError, match=r"bad\.txt: line 11"):
        read_snapshot_file(path)


def test_bad_header_and_extra_lines(tmp_path, rng):
    path = tmp_path / "bad.txt"
    path.write_text(
        format_snapshot(0, COLUMNS, _data(rng, 2)).decode().replace("NUMBER OF ATOMS", "NUMBER OF PARTICLES")
    )
    with pytest.raises(DumpFormatError, match=r"bad\.txt: line 3: expected 'ITEM: NUMBER OF ATOMS'"):
        read_snapshot_file(path)
    text = format_snapshot(0, COLUMNS, _data(rng, 2)).decode().replace("ATOMS\n2\n", "ATOMS\n1\n")
    path.write_text(text)
    with pytest.raises(DumpFormatError, match="announces 1 atoms but has 2 lines"):
        read_snapshot_file(path)


def test_required_column_missing(tmp_path, rng):
    path = tmp_path / "d.txt"
    path.write_bytes(format_snapshot(0, ("id", "type", "x"), _data(rng, 2)[:, :3]))
    with pytest.raises(DumpFormatError, match="no column 'vx'"):
        list(iter_snapshots(path, columns=("id", "vx")))


def test_steps_must_increase(tmp_path, rng):
    path = tmp_path / "d.txt"
    path.write_bytes(format_snapshot(100, COLUMNS, _data(rng, 2)) + format_snapshot(100, COLUMNS, _data(rng, 2)))
    with pytest.raises(DumpFormatError, match="does not follow"):
        list(iter_snapshots(path))


def test_no_files(tmp_path):
    with pytest.raises(DumpFormatError, match="no dump files match"):
        list(iter_snapshots(str(tmp_path / "dump.*.txt")))


STATIC = __import__("pathlib").Path(__file__).parent / "static" / "smoke_dumps"


def test_real_liggghts_dumps():
    """Dumps written by LIGGGHTS itself (tests/dem/static/smoke_dumps/README.md)."""
    snaps = list(iter_snapshots(str(STATIC / "dump.*.txt")))
    assert [s.step for s in snaps] == [21200, 23320, 25440]
    for snap in snaps:
        assert snap.columns == COLUMNS
        text = (STATIC / f"dump.{snap.step}.txt").read_text().splitlines()
        assert snap.n == int(text[3]) == len(text) - 9
        ids = snap["id"]
        assert np.unique(ids).size == ids.size and set(np.unique(snap["type"])) <= {1.0, 2.0}
        for axis, name in enumerate("xyz"):
            assert (snap[name] >= snap.box[axis, 0]).all() and (snap[name] <= snap.box[axis, 1]).all()
        assert (snap["radius"] > 0.0025).all() and (snap["radius"] < 0.0035).all()
        first = text[9].split()
        np.testing.assert_allclose(snap.data[0], [float(v) for v in first])
    # particles are only added early in a run: each snapshot holds the previous one's IDs
    assert set(snaps[0]["id"]) <= set(snaps[1]["id"]) <= set(snaps[2]["id"])


def test_real_dump_truncated_by_a_kill(tmp_path):
    for name in ("dump.21200.txt", "dump.23320.txt"):
        (tmp_path / name).write_bytes((STATIC / name).read_bytes())
    data = (STATIC / "dump.25440.txt").read_bytes()
    (tmp_path / "dump.25440.txt").write_bytes(data[: int(len(data) * 0.6)])
    with pytest.warns(TruncatedDumpWarning, match="dump.25440.txt"):
        assert [s.step for s in iter_snapshots(str(tmp_path / "dump.*.txt"))] == [21200, 23320]


def _one_snapshot(
    tmp_path,
    name="bad.txt",
    rows=((1, 1, 0.1, 0.0, 0.0, 0.1, 0.0, 0.0, 0.003), (2, 2, 0.2, 0.01, 0.0, 0.2, 0.0, 0.0, 0.003)),
):
    path = tmp_path / name
    path.write_bytes(format_snapshot(7, COLUMNS, np.array(rows, dtype=float)))
    return path


def _replace_line(path, index, text: bytes):
    lines = path.read_bytes().split(b"\n")
    lines[index] = text
    path.write_bytes(b"\n".join(lines))


def test_undecodable_header_bytes_name_file_and_line(tmp_path):
    path = _one_snapshot(tmp_path)
    _replace_line(path, 8, b"ITEM: ATOMS id type x \xff\xfe z vx vy vz radius ")
    with pytest.raises(DumpFormatError, match=r"bad\.txt: line 9: column names must be ASCII; byte 0xff"):
        read_snapshot_file(path)
    _replace_line(path, 8, b"ITEM: ATOMS id type x y z vx vy vz radius ")
    _replace_line(path, 9, b"1 1 0.\xc3 0 0 0.1 0 0 0.003 ")
    with pytest.raises(DumpFormatError, match=r"bad\.txt: line 10: column 'x': .* is not a number"):
        read_snapshot_file(path)


@pytest.mark.parametrize("column, value", [("x", "inf"), ("y", "-inf"), ("vx", "nan"), ("vy", "Infinity")])
def test_non_finite_value_names_line_and_column(tmp_path, column, value):
    path = _one_snapshot(tmp_path)
    fields = path.read_bytes().split(b"\n")[10].split(b" ")
    fields[COLUMNS.index(column)] = value.encode()
    _replace_line(path, 10, b" ".join(fields))
    with pytest.raises(DumpFormatError, match=rf"bad\.txt: line 11: column '{column}': '{value}' is not"):
        list(iter_snapshots(path, columns=("id", "type", "x", "y", "vx", "vy")))


def test_inf_in_a_column_nobody_uses_is_read(tmp_path):
    path = _one_snapshot(tmp_path)
    _replace_line(path, 10, b"2 2 0.2 0.01 0 0.2 0 0 inf ")
    (snap,) = iter_snapshots(path, columns=("id", "x"))
    assert np.isinf(snap["radius"][1])
    with pytest.raises(DumpFormatError, match=r"line 11: column 'radius': 'inf' is not finite"):
        read_snapshot_file(path)  # no columns named: every column must be finite


@pytest.mark.parametrize(
    "line", [b"-0.005", b"0.35 -0.005", b"0.1 0.1", b"-0.005 inf", b"nan 0.35", b"-0.005 0.35 0.0", b"a b", b""]
)
def test_box_bounds_need_two_finite_numbers_lo_below_hi(tmp_path, line):
    path = _one_snapshot(tmp_path)
    _replace_line(path, 6, line)
    with pytest.raises(DumpFormatError, match=r"bad\.txt: line 7: box bounds of axis y must be 'lo hi': 2 finite"):
        read_snapshot_file(path)


def test_triclinic_box_bounds_are_read(tmp_path):
    path = _one_snapshot(tmp_path)
    _replace_line(path, 4, b"ITEM: BOX BOUNDS xy xz yz ff ff ff")
    for index in (5, 6, 7):
        _replace_line(path, index, b"-1 1 0.0")
    (snap,) = read_snapshot_file(path)
    np.testing.assert_array_equal(snap.box, [[-1, 1]] * 3)
    _replace_line(path, 6, b"-1 1")
    with pytest.raises(DumpFormatError, match=r"line 7: box bounds of axis y must be 'lo hi tilt'"):
        read_snapshot_file(path)


@pytest.mark.parametrize(
    "column, value",
    [("id", b"-3"), ("id", b"0"), ("id", b"1.5"), ("id", b"1e20"), ("type", b"0"), ("type", b"2.5"), ("type", b"3e9")],
)
def test_ids_and_types_must_be_positive_integers(tmp_path, column, value):
    path = _one_snapshot(tmp_path)
    fields = path.read_bytes().split(b"\n")[9].split(b" ")
    fields[COLUMNS.index(column)] = value
    _replace_line(path, 9, b" ".join(fields))
    with pytest.raises(DumpFormatError, match=rf"line 10: column '{column}': .* an integer in \[1, "):
        read_snapshot_file(path)


def test_position_far_outside_the_box_is_refused(tmp_path):
    path = _one_snapshot(tmp_path)  # box [-1, 1]: positions in [-3, 3] are accepted
    _replace_line(path, 10, b"2 2 2.9 1e300 0 0.2 0 0 0.003 ")
    with pytest.raises(DumpFormatError, match=r"line 11: column 'y': '1e300' lies far outside the box"):
        read_snapshot_file(path)


@pytest.mark.parametrize("line, message", [(1, b"-5"), (1, b"99999999999999999999"), (3, b"-1")])
def test_header_numbers_out_of_range(tmp_path, line, message):
    path = _one_snapshot(tmp_path)
    _replace_line(path, line, message)
    with pytest.raises(DumpFormatError, match=rf"line {line + 1}: .* is out of range"):
        read_snapshot_file(path)
