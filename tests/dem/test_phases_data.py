"""The hidden-phase fit's data (dem/phases/data.py) against known answers: the sequences
extracted exactly (their moves are the measured rates' transition counts), decoded, cut,
subsampled at a lag with the discharge kept, joined by the residents of a window, and bad
selections refused by name."""

import numpy as np
import pytest

from dem import phases
from dem.post import postprocess
from tests.dem.phase_chains import fit_chain, inlet, two_phase_model
from tests.known_dumps import STEADY, write_synthetic
from tests.known_dumps import config as synthetic_config


def test_sequences_reproduce_the_measured_transition_counts(tmp_path):
    """The lag-1 moves of the stored sequences are exactly the moves the measured rates are
    fitted to (same binning, same discharge rule), including particles the solver deleted
    between dumps; and the sequences survive the results file."""
    cfg = synthetic_config()
    for name, unseen in (("seen", False), ("unseen", True)):
        write_synthetic(tmp_path / name, cfg, vanish_unseen=unseen)
        res = postprocess(str(tmp_path / name / "dump.*.txt"), cfg, STEADY)
        seq = res.sequences
        assert (seq.nx, seq.ny) == (4, 2) and seq.interval_s == pytest.approx(0.5, rel=1e-4)
        counts = phases.prepare(seq).counts()
        assert np.array_equal(counts, res.transitions.sum(axis=0))
        # A crosses in 4 s (2 dumps per slice), B in 6 s: sequences are exact
        a = seq.states(np.flatnonzero(seq.component == 1)[:1])[0]
        assert a.tolist() == [1, 1, 3, 3, 5, 5, 7, 7, 8]
        assert seq.discharged.sum() == int(np.isfinite(res.particles["exit_t_s"]).sum())
    entry = res.to_cache_entry({"input_hash": "test"})
    back = type(res).from_cache_entry(entry).sequences
    for name in seq.ARRAYS:
        assert np.array_equal(getattr(back, name), getattr(seq, name))


def test_padded_and_run_length_decoding_agree(synthetic_two_phase):
    _model, sequences, _data, _fit = synthetic_two_phase
    chosen = np.arange(0, sequences.n_particles, 37)
    padded = sequences.padded(chosen)
    for row, states in zip(padded, sequences.states(chosen)):
        assert np.array_equal(row[: states.size], states) and np.all(row[states.size :] == -1)


def test_a_lag_subsamples_and_keeps_the_discharge():
    obs = np.array([[0, 0, 1, 1, 2, 3], [0, 1, 1, 2, -1, -1]], np.int16)
    seq = phases.sequences_from_padded(obs, np.zeros(2, int), np.array([1, 2]), np.arange(6) * 0.1, 0.1, 3, 1)
    data = phases.prepare(seq, lag=2)
    assert data.interval_s == pytest.approx(0.2)
    # row 0: dumps 0, 2, 4 then discharged (3 = S) at the next kept column; row 1 censored
    assert data.obs.tolist() == [[0, 1, 2, 3], [0, 1, -1, -1]]
    with pytest.raises(ValueError, match="lag = 0"):
        phases.prepare(seq, lag=0)


def test_residents_join_from_the_window_on(synthetic_two_phase):
    """Particles inside when the window opens are followed from there, their first
    compartment their group; the window's entrants are unchanged."""
    _truth, sequences, _data, _fit = synthetic_two_phase
    t0 = 60.0
    only_new = phases.prepare(sequences, (t0, np.inf))
    both = phases.prepare(sequences, (t0, np.inf), residents=True)
    old = both.group >= 2
    assert (~old).sum() == only_new.n_particles and old.sum() > 100
    first_dump = int(np.searchsorted(sequences.snapshot_t, t0, side="right"))
    assert np.all(both.start[old] == first_dump)
    assert np.array_equal(both.obs[old, 0], both.group[old] - 2)
    fitted = fit_chain(both, 2, starts=1, max_iterations=30)
    assert np.isfinite(fitted.log_likelihood)


def test_sequences_until_a_time_are_the_record_of_a_shorter_run(synthetic_two_phase):
    _model, sequences, _data, _fit = synthetic_two_phase
    cut_t = float(sequences.snapshot_t[700])
    short = sequences.until(cut_t)
    assert short.snapshot_t[-1] == cut_t and short.n_particles == int((sequences.start <= 700).sum())
    full = sequences.padded(np.flatnonzero(sequences.start <= 700))
    rows = short.padded()
    for p in range(short.n_particles):  # each row: the full row up to dump 700, then nothing
        keep = 700 - short.start[p] + 1
        expected = full[p, :keep]
        expected = expected[expected >= 0]
        assert rows[p][rows[p] >= 0].tolist() == expected.tolist()
    ends = sequences.start + sequences.lengths - 1  # the dump of each full sequence's last state
    kept = sequences.start <= 700
    np.testing.assert_array_equal(short.discharged, sequences.discharged[kept] & (ends[kept] <= 700))


def test_a_subset_of_the_sequences_is_their_rows(synthetic_two_phase):
    _model, sequences, _data, _fit = synthetic_two_phase
    rows = np.array([17, 3, 400, 5999, 3])
    part = sequences.subset(rows)
    assert part.ids.tolist() == sequences.ids[rows].tolist()
    assert [s.tolist() for s in part.states()] == [s.tolist() for s in sequences.states(rows)]
    np.testing.assert_array_equal(part.discharged, sequences.discharged[rows])
    whole = sequences.subset(np.arange(sequences.n_particles))
    for name in sequences.ARRAYS:
        np.testing.assert_array_equal(getattr(whole, name), getattr(sequences, name))


def test_bad_selections_are_named():
    with pytest.raises(ValueError, match="no particle entered"):
        phases.prepare(
            phases.simulate_sequences(two_phase_model(), inlet(), 50, 100, np.random.default_rng(0)), (1e3, 2e3)
        )
    with pytest.raises(ValueError, match="does not divide"):
        phases.coarsen(np.zeros(3, np.int16), 10, 10, 3, 1)
