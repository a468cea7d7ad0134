"""The size study: classes read off the diameters, the diameters read off dumps, and on
the shipped validation baseline with sizes dealt at random (so they carry nothing about
the transport) chains per size class hold what the run holds, and without their dead
zones give what one chain for every size gives. The command runs end to end on the
shipped reduced run, whose sizes do carry transport; a missing file is one line."""

import dataclasses
import json

import numpy as np
import pytest

from coupling.cache import load_entry, save_entry
from coupling.errors import ConfigError
from dem import phases
from dem.dumps import format_snapshot
from dem.phases import MAX_CLASSES, QUANTILE_CLASSES, size_classes
from tests.dem.test_phases import exact_rtd_moments
from workflows.analysis.memory import MemoryCheck
from workflows.cli.main import main
from workflows.pipeline.results import load_results
from workflows.report.memory import _sizes_html
from workflows.shipped import REDUCED_RUN, VALIDATION_DIR
from workflows.studies.sizes import diameters_from_dumps, size_study

BASELINE = VALIDATION_DIR / "dem-aa093a229dfd2ce4.h5"
COLUMNS = ("id", "type", "x", "y", "z", "vx", "vy", "vz", "radius")


def test_many_distinct_diameters_are_grouped_by_quantiles():
    spread = np.random.default_rng(0).normal(0.006, 0.0003, 1000)
    labels, centres = size_classes(spread)
    assert np.unique(spread).size > MAX_CLASSES and centres.size == QUANTILE_CLASSES
    assert np.all(np.diff(centres) > 0)
    assert np.bincount(labels).min() >= 1000 // QUANTILE_CLASSES - 1
    with pytest.raises(ValueError, match="no particle has a known diameter"):
        size_classes(np.array([np.nan, 0.0]))


def _dumps_with_sizes(directory, ids, radius):
    rows = np.zeros((ids.size, len(COLUMNS)))
    rows[:, 0], rows[:, 1], rows[:, -1] = ids, 1, radius
    (directory / "dumps").mkdir(parents=True)
    (directory / "dumps" / "dump.0.txt").write_bytes(format_snapshot(0, COLUMNS, rows))
    later = rows[:3].copy()
    later[:, -1] = 0.01  # a particle keeps the size it was first seen with
    (directory / "dumps" / "dump.10.txt").write_bytes(format_snapshot(10, COLUMNS, later))


def _without_diameters(path, directory):
    """A copy of the results file ``path`` whose records lack the diameters, as files made
    before they were recorded do."""
    entry = load_entry(path)
    particles = entry.frames["particles"].drop(columns="diameter_m", errors="ignore")
    return save_entry(
        directory / path.name, dataclasses.replace(entry, frames={**entry.frames, "particles": particles})
    )


def test_sizes_that_carry_nothing_change_nothing(tmp_path):
    bare_file = _without_diameters(BASELINE, tmp_path)
    results, _config = load_results(bare_file)
    ids = results.particles["id"].to_numpy(np.int64)
    radius = np.where(ids % 2 == 0, 0.0027, 0.0033)
    _dumps_with_sizes(tmp_path, ids, radius)
    seen = diameters_from_dumps(tmp_path / "dumps" / "dump.*.txt")
    assert seen[int(ids[0])] == pytest.approx(2 * radius[0])
    with pytest.raises(ConfigError, match="holds no particle diameters.*--run-dir"):
        size_study(bare_file)
    study = size_study(bare_file, tmp_path)
    assert [round(c.diameter_m, 4) for c in study.classes] == [0.0054, 0.0066]
    assert sum(c.share for c in study.classes) == pytest.approx(1.0)
    small, large = study.classes
    # the two halves are one distribution: their means differ by less than the 95 % half
    # width of a difference of two independent estimates
    half = [(c.dem_mean_s.high - c.dem_mean_s.low) / 2 for c in (small, large)]
    assert abs(small.dem_mean_s.value - large.dem_mean_s.value) <= np.hypot(*half)
    # each class's chain has its dead zone, held to the class's Little's law: so the
    # population holds what the run holds
    assert study.n_phases == phases.PHASES + 1
    assert study.by_size["holdup"] == pytest.approx(study.dem["holdup"].value, rel=0.01)
    # without the zones, two classes of one distribution are that distribution's one chain
    seq, t_ss = results.sequences, float(results.summary.steady_time)
    diameters = np.where(seq.ids % 2 == 0, 0.0054, 0.0066)
    bare = results.table.replace(phases=None)
    no_zone = phases.PhaseSettings(zone_residences=None)
    plain, _fits = phases.table_with_phases(bare, seq, t_ss, phases.PHASES, no_zone, diameters=diameters)
    one_chain, _fit = phases.table_with_phases(bare, seq, t_ss, phases.PHASES)
    entering = phases.first_compartments(phases.prepare(seq, phases.steady_window(seq, t_ss)))
    for got, want in zip(exact_rtd_moments(plain.phases, entering), exact_rtd_moments(one_chain.phases, entering)):
        assert got == pytest.approx(want, rel=0.03)
    # the report's table of the classes
    page = _sizes_html(MemoryCheck((), (0.0, 1.0), 0, 0, by_size=study.classes))
    assert "By particle size" in page and page.count("<tr><td>5.40") == 1 and page.count("<tr><td>6.60") == 1


def test_the_zone_option_reads_residence_times_or_none():
    from workflows.studies.sizes import zone_argument

    assert zone_argument("2") == 2.0 and zone_argument("0.5") == 0.5 and zone_argument("None") is None
    for bad in ("0", "-1", "nan", "inf", "one"):
        with pytest.raises(ConfigError, match=f"--zone {bad}: expected a number of residence times > 0"):
            zone_argument(bad)


def test_the_command_on_the_shipped_run_finds_small_particles_stay_longer(tmp_path, capsys):
    """The shipped reduced run (three size classes, 4.6 / 5.0 / 5.4 mm) with two phases per
    class, the fast variant (16 s against 60 s at the run's own four): the DEM keeps the
    small particles longest (measured 21.2 / 17.0 / 13.7 s), each class's chain follows its
    class within 3 %, and the classes' chains together hold what the run holds."""
    assert main(["study", "sizes", "--results", str(REDUCED_RUN), "--k", "2", "--out", str(tmp_path)]) == 0
    study = json.loads((tmp_path / "sizes.json").read_text())
    classes = study["classes"]
    assert len(classes) == 3 and study["n_phases"] == 2 + 1  # two phases and the dead zone
    assert sum(c["share"] for c in classes) == pytest.approx(1.0)
    assert [c["diameter_m"] for c in classes] == sorted(c["diameter_m"] for c in classes)
    dem_means = [c["dem_mean_s"]["value"] for c in classes]
    assert dem_means == sorted(dem_means, reverse=True) and dem_means[0] > 1.3 * dem_means[-1]
    for c in classes:
        assert c["pbm_mean_s"] == pytest.approx(c["dem_mean_s"]["value"], rel=0.03)
    assert study["by_size"]["holdup"] == pytest.approx(study["dem"]["holdup"]["value"], rel=0.01)
    assert "| 4.64 |" in capsys.readouterr().out
