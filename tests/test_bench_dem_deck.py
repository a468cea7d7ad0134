"""The DEM deck benchmark's pure parts (no LIGGGHTS): LIGGGHTS' timing lines are parsed
right, and the paper's core-hours follow the cost estimate. (The plain-box deck it measures
against is tested with the deck writer, tests/test_deck.py.)"""

import pytest

from dem.cluster import estimate_cost
from dem.liggghts_log import loop_details, parse_loop_time, parse_runs
from workflows.bench_dem_deck import paper_core_hours
from workflows.config import load_preset


def test_loop_time_parser():
    line = "Loop time of 8.43217 on 2 procs for 20000 steps with 1537 atoms, finish time Sun Nov 22 04:46:22 2026"
    loop = parse_loop_time(line)
    assert (loop.seconds, loop.procs, loop.steps, loop.atoms) == (8.43217, 2, 20000, 1537)
    plain = parse_loop_time("Loop time of 1.5e-01 on 1 procs for 100 steps with 20 atoms")
    assert (plain.seconds, plain.procs, plain.steps, plain.atoms) == (0.15, 1, 100, 20)
    assert parse_loop_time("Step Atoms KinEng") is None


def test_runs_are_split_at_loop_times_with_their_thermo():
    log = """LIGGGHTS (Version LIGGGHTS-PUBLIC 3.8.0)
    Step    Atoms         KinEng
       0        0              0
    1000      300      1.5e-05
Loop time of 0.5 on 1 procs for 1000 steps with 300 atoms, finish time x

Pair  time (%) = 0.1 (20)
Step simtime Atoms insA insB outA outB ts[1] ts[2]
  424092 25 1530 1 1 0 0 0.25 0.01
  432574 25.5 1540 1 1 0 0 0.25 0.01
  444092 26.179 1550 1 1 0 0 0.25 0.01
Loop time of 4 on 2 procs for 20000 steps with 1550 atoms, finish time x
"""
    runs = parse_runs(log)
    assert len(runs) == 2
    assert runs[0].column("Atoms") == [0.0, 300.0] and runs[0].loop.steps == 1000
    assert runs[1].column("Atoms") == [1530.0, 1540.0, 1550.0]
    assert runs[1].loop.procs == 2 and runs[1].loop.seconds == 4.0


def test_paper_core_hours_follow_estimate_cost():
    smoke = load_preset("smoke")
    out = paper_core_hours(4.0e6, 1.8, 1500.0, smoke, reference_rate_serial=6.0e6)
    paper = load_preset("paper").dem
    assert set(out["cores"]) == {"2", "8", "32"}
    for cores, est in out["cores"].items():
        ref = estimate_cost(paper, out["holdup_particles"], 4.0e6, int(cores), est["parallel_efficiency"])
        assert est["core_hours"] == pytest.approx(ref.core_hours)
        assert est["core_hours_overhead_amortised"] < est["core_hours"]
    assert out["cores"]["2"]["parallel_efficiency"] == pytest.approx(0.9)
    if out["holdup_source"].startswith("measured smoke"):
        assert out["holdup_particles"] == pytest.approx(1500.0 * 27)


def test_loop_details_after_the_last_loop_time():
    log = """Loop time of 1.2771 on 1 procs for 2000 steps with 1540 atoms, finish time x


Pair  time (%) = 1.04285 (81.6573)
Neigh time (%) = 0.5 (0)
Comm  time (%) = 0.000195497 (0.0153079)
Outpt time (%) = 4.4997e-05 (0.00352337)
Other time (%) = 0.234003 (18.3229)

Nlocal:    1540 ave 1540 max 1540 min
Total # of neighbors = 8217
Ave neighs/atom = 5.33571
Neighbor list builds = 7
Dangerous builds = 0
"""
    out = loop_details("Loop time of 9 on 1 procs for 1 steps with 1 atoms\nPair  time (%) = 9 (100)\n" + log)
    assert out["sections_s"] == {"Pair": 1.04285, "Neigh": 0.5, "Comm": 0.000195497, "Outpt": 4.4997e-05,
                                 "Other": 0.234003}
    assert out["neighbours_per_particle"] == 5.33571 and out["neighbour_builds"] == 7
    assert loop_details("no timing here") == {}
