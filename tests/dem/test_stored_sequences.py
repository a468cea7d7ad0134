"""The one reader of a results file's stored arrays (dem.tracking.checked_sequence_arrays,
dem.post.check_snapshot_counts): every array out of range, of the wrong shape, empty or
huge is refused in one line naming the file and the array, never an IndexError, a
MemoryError or a silently wrong fit. The command-line cases are the reproducers of issue
46, crafted with the project's own writer (so their digests are valid)."""

import dataclasses
import hashlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from coupling.errors import ResultsError
from dem.tracking import CompartmentSequences

PREFIX = "sequences_"
INTEGER_ARRAYS = ("ids", "component", "start", "run_offsets", "run_state", "run_length")


def small_arrays() -> dict[str, np.ndarray]:
    """Three particles on a 2 x 2 grid over 8 dumps: one discharged (its last run past the
    weir, state 4), one censored at the last dump, one seen once."""
    return CompartmentSequences(
        ids=np.array([5, 9, 11]),
        component=np.array([1, 2, 3], np.int8),
        start=np.array([0, 2, 7], np.int32),
        run_offsets=np.array([0, 3, 5, 6]),
        run_state=np.array([0, 1, 4, 2, 3, 0], np.int16),
        run_length=np.array([2, 3, 1, 4, 2, 1], np.int32),
        snapshot_t=np.arange(8) * 0.1,
        interval_s=0.1,
        nx=2,
        ny=2,
    ).to_arrays(PREFIX)


def changed(name: str, index, value) -> dict[str, np.ndarray]:
    arrays = small_arrays()
    array = arrays[PREFIX + name].astype(np.float64 if name in ("snapshot_t", "interval_s") else np.int64)
    array[index] = value
    arrays[PREFIX + name] = array
    return arrays


def test_valid_sequences_are_read_back():
    seq = CompartmentSequences.from_arrays(small_arrays(), PREFIX, "f.h5")
    assert seq.n_particles == 3 and (seq.nx, seq.ny) == (2, 2)
    np.testing.assert_array_equal(seq.lengths, [6, 6, 1])
    np.testing.assert_array_equal(seq.discharged, [True, False, False])
    assert CompartmentSequences.from_arrays({}, PREFIX, "f.h5") is None  # made before sequences were kept


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        # the reproducers
        (changed("run_length", 0, 2**31 - 1), r"'sequences_run_length' holds 2147483647; a run lasts 1 to 8 dumps"),
        (
            {**small_arrays(), PREFIX + "run_offsets": np.array([0, 3, 5])},
            r"'sequences_run_offsets' has 3 entries for 3 particles; 4 \(one more\) are valid",
        ),
        (changed("start", 1, 8), r"'sequences_start' holds dump 8; dumps 0 to 7 are recorded"),
        (
            {**small_arrays(), PREFIX + "grid": np.array([0, 0])},
            r"'sequences_grid' is \[0, 0\]; two integers NX, NY >= 1 are valid",
        ),
        (
            {**small_arrays(), PREFIX + "interval_s": np.array(0.0)},
            r"'sequences_interval_s' is 0.0; a dump interval > 0 s is valid",
        ),
        (changed("run_state", 1, 30000), r"'sequences_run_state' holds 30000; on the 2 x 2 grid states 0 to 3"),
        (changed("run_state", 1, -3), r"'sequences_run_state' holds -3; on the 2 x 2 grid"),
        (changed("run_length", 1, -2), r"'sequences_run_length' holds -2; a run lasts 1 to 8 dumps"),
        (changed("snapshot_t", 3, np.nan), r"'sequences_snapshot_t' of shape \(8,\) is not all finite"),
        (changed("ids", 1, 5), r"'sequences_ids' lists particle 5 twice; each particle once is valid"),
        # variants
        (changed("run_length", 0, 0), r"'sequences_run_length' holds 0; a run lasts 1 to 8"),
        (changed("run_length", 4, 3), r"gives particle 9 \(first seen at dump 2\) 7 dumps; only 8 are recorded"),
        (changed("start", 0, -1), r"'sequences_start' holds dump -1"),
        (changed("run_offsets", 1, 6), r"'sequences_run_offsets' runs 0 \.\.\. 6; valid offsets go from 0 to the 6"),
        (changed("run_offsets", 3, 5), r"'sequences_run_offsets' runs 0 \.\.\. 5"),
        (changed("run_offsets", 0, 1), r"'sequences_run_offsets' runs 1 \.\.\. 6"),
        (changed("run_state", 0, 4), r"absorbing state 4 \(past the weir\) in run 0 other than as a particle's last"),
        (changed("run_length", 2, 2), r"absorbing state 4 \(past the weir\) in run 2"),
        (changed("run_state", 2, 5), r"'sequences_run_state' holds 5"),
        (changed("component", 0, 7), r"'sequences_component' holds 7; 1 \(A\), 2 \(B\) or 3"),
        (changed("snapshot_t", 4, 0.2), r"goes from 0.3 s to 0.2 s at dump 4; strictly increasing times"),
        (changed("snapshot_t", 4, 0.3), r"goes from 0.3 s to 0.3 s"),
        (changed("snapshot_t", 0, np.inf), r"not all finite"),
        ({**small_arrays(), PREFIX + "interval_s": np.array(np.nan)}, r"'sequences_interval_s' is nan"),
        ({**small_arrays(), PREFIX + "interval_s": np.array(-0.1)}, r"'sequences_interval_s' is -0.1"),
        ({**small_arrays(), PREFIX + "interval_s": np.array([0.1, 0.1])}, r"'sequences_interval_s' is \[0.1, 0.1\]"),
        ({**small_arrays(), PREFIX + "grid": np.array([2])}, r"'sequences_grid' is \[2\]"),
        ({**small_arrays(), PREFIX + "grid": np.array([2.0, 2.0])}, r"'sequences_grid' is \[2.0, 2.0\]"),
        ({**small_arrays(), PREFIX + "grid": np.array([1000, 1000])}, r"is 1000 x 1000; at most 32766 compartments"),
        ({**small_arrays(), PREFIX + "start": np.array([0, 2])}, r"'sequences_start' has 2 entries for 3 particles"),
        (
            {**small_arrays(), PREFIX + "run_length": np.array([2.0, 3, 1, 4, 2, 1])},
            r"'sequences_run_length' is float64 of shape \(6,\); a 1-D integer array is valid",
        ),
        (
            {**small_arrays(), PREFIX + "run_state": np.zeros((2, 3), np.int16)},
            r"'sequences_run_state' is int16 of shape \(2, 3\)",
        ),
        ({**small_arrays(), PREFIX + "run_length": np.array([2, 3, 1, 4, 2])}, r"has 5 entries for 6 runs"),
        (
            {k: v for k, v in small_arrays().items() if k != PREFIX + "run_state"},
            r"the compartment sequences lack sequences_run_state",
        ),
    ],
)
def test_a_bad_stored_array_is_refused_in_one_line_naming_it(arrays, message):
    with pytest.raises(ResultsError, match=message) as info:
        CompartmentSequences.from_arrays(arrays, PREFIX, "f.h5")
    assert str(info.value).startswith("f.h5: ") and "\n" not in str(info.value)


@st.composite
def valid_arrays(draw):
    """Sequences as the post-processing writes them: each particle first seen at some
    dump, then runs of compartments that fit in the dumps recorded, perhaps ending past
    the weir for one dump."""
    nx, ny = draw(st.integers(1, 3)), draw(st.integers(1, 3))
    cells = nx * ny
    n_dumps = draw(st.integers(1, 12))
    n_particles = draw(st.integers(0, 6))
    starts, states, lengths, offsets = [], [], [], [0]
    for _ in range(n_particles):
        start = draw(st.integers(0, n_dumps - 1))
        left = n_dumps - start
        absorbed = left >= 2 and draw(st.booleans())
        budget = left - int(absorbed)
        while budget > 0:
            length = draw(st.integers(1, budget))
            states.append(draw(st.integers(0, cells - 1)))
            lengths.append(length)
            budget -= length
            if draw(st.booleans()):
                break
        if absorbed or len(states) == offsets[-1]:
            states.append(cells)
            lengths.append(1)
        starts.append(start)
        offsets.append(len(states))
    return CompartmentSequences(
        ids=np.arange(n_particles, dtype=np.int64) * 3 + 1,
        component=np.array(
            draw(st.lists(st.sampled_from([1, 2, 3]), min_size=n_particles, max_size=n_particles)), np.int8
        ),
        start=np.array(starts, np.int32),
        run_offsets=np.array(offsets, np.int64),
        run_state=np.array(states, np.int16),
        run_length=np.array(lengths, np.int32),
        snapshot_t=np.cumsum(draw(st.lists(st.floats(0.01, 5.0), min_size=n_dumps, max_size=n_dumps))),
        interval_s=0.1,
        nx=nx,
        ny=ny,
    ).to_arrays(PREFIX)


BOUNDARY_INTS = st.one_of(
    st.integers(-5, 40),
    st.sampled_from([-(2**31), -(2**15), 2**15 - 1, 2**16, 2**31 - 1, 2**40, 2**62]),
)


@settings(max_examples=300, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(arrays=valid_arrays())
def test_sequences_the_post_processing_writes_are_accepted_and_decode(arrays):
    seq = CompartmentSequences.from_arrays(arrays, PREFIX, "f.h5")
    n_dumps = seq.snapshot_t.size
    assert ((seq.start + seq.lengths) <= n_dumps).all()
    counts = seq.counts((1, 2, 3))
    assert counts.shape == (n_dumps, seq.nx, seq.ny) and counts.min() >= 0


@settings(max_examples=500, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(arrays=valid_arrays(), name=st.sampled_from(INTEGER_ARRAYS), where=st.integers(0, 10**6), value=BOUNDARY_INTS)
def test_any_one_stored_integer_changed_is_refused_or_still_decodes(arrays, name, where, value):
    """The attack: one entry of any integer array set to anything. Either the reader
    refuses it by name, or what it accepts decodes within the grid and the dumps."""
    array = arrays[PREFIX + name].astype(np.int64)
    if array.size == 0:
        return
    array[where % array.size] = value
    arrays = {**arrays, PREFIX + name: array}
    try:
        seq = CompartmentSequences.from_arrays(arrays, PREFIX, "f.h5")
    except ResultsError as exc:
        assert str(exc).startswith("f.h5: ") and "\n" not in str(exc)
        return
    n_dumps = seq.snapshot_t.size
    padded = seq.padded()
    assert padded.shape[1] <= n_dumps and padded.max(initial=0) <= seq.n_cells
    assert ((seq.start + seq.lengths) <= n_dumps).all()
    assert seq.counts((1, 2, 3)).min(initial=0) >= 0


# ------------------------------------------------------------------ the command line, end to end
REFERENCE = "workflows/reference/validation/dem-dccc770e3c39f48c.h5"


@pytest.fixture(scope="module")
def entry():
    from pathlib import Path

    from coupling.cache import load_entry

    return load_entry(Path(__file__).resolve().parents[2] / REFERENCE)


def _crafted(entry, path, **changes):
    from coupling.cache import save_entry

    arrays = dict(entry.arrays)
    for name, change in changes.items():
        arrays[name] = change(np.array(arrays[name]))
    save_entry(path, dataclasses.replace(entry, arrays=arrays))
    return path


def _set(index, value):
    def change(array):
        array = array.astype(np.int64)
        array[index] = value
        return array

    return change


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"sequences_run_length": _set(0, 2**31 - 1)}, "stored array 'sequences_run_length' holds 2147483647"),
        ({"sequences_run_offsets": lambda a: a[:-5]}, "stored array 'sequences_run_offsets' has 11755 entries"),
        ({"sequences_start": _set(3, 10**6)}, "stored array 'sequences_start' holds dump 1000000"),
        ({"sequences_grid": lambda a: np.array([0, 0])}, "stored array 'sequences_grid' is [0, 0]"),
        ({"sequences_interval_s": lambda a: np.array(0.0)}, "stored array 'sequences_interval_s' is 0.0"),
        ({"sequences_run_state": _set(1, 30000)}, "stored array 'sequences_run_state' holds 30000"),
        ({"sequences_run_state": _set(1, -3)}, "stored array 'sequences_run_state' holds -3"),
        ({"sequences_run_length": _set(1, -2)}, "stored array 'sequences_run_length' holds -2"),
        ({"sequences_snapshot_t": lambda a: np.where(np.arange(a.size) == 7, np.nan, a)}, "is not all finite"),
        ({"sequences_ids": lambda a: np.where(np.arange(a.size) == 1, a[0], a)}, "lists particle 1 twice"),
        (
            {"snapshot_counts": lambda a: a[:, :, :5, :]},
            "stored array 'snapshot_counts' has shape (3201, 2, 5, 10); (dumps, A and B, NX, NY) = (3201, 2, 10, 10)",
        ),
        ({"snapshot_counts": lambda a: a[:-1]}, "stored array 'snapshot_counts' has shape (3200, 2, 10, 10)"),
        ({"snapshot_counts": lambda a: a.astype(np.float64) * 0.5}, "holds float64 values down to 0.0"),
        ({"snapshot_counts": _set((0, 0, 0, 0), -1)}, "holds int64 values down to -1; particle counts"),
    ],
)
@pytest.mark.parametrize("command", ["recompute-steady", "refit-phases"])
def test_commands_refuse_a_crafted_results_file_and_leave_it_unchanged(
    entry, tmp_path, capsys, changes, message, command
):
    from workflows.cli.main import main

    path = _crafted(entry, tmp_path / "crafted.h5", **changes)
    before = hashlib.sha256(path.read_bytes()).hexdigest()
    assert main(["dem", command, str(path)]) == 2
    err = capsys.readouterr().err
    assert err == f"pbmdem: error: {path}: {err.split(': ', 3)[-1]}" and err.count("\n") == 1
    assert message in err
    assert hashlib.sha256(path.read_bytes()).hexdigest() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["crafted.h5"]  # no temporary left


def test_load_results_refuses_counts_on_another_grid(entry, tmp_path):
    from workflows.pipeline.results import load_results

    path = _crafted(entry, tmp_path / "grid.h5", snapshot_counts=lambda a: a[:, :, :5, :])
    with pytest.raises(ResultsError, match=rf"^{tmp_path}/grid.h5: stored array 'snapshot_counts' has shape"):
        load_results(path)
