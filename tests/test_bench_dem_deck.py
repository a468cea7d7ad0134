"""The DEM deck benchmark's pure parts (no LIGGGHTS): the plain-box deck has the blender
deck's physics, and LIGGGHTS' timing lines are parsed right."""

import re

import pytest

from dem.cluster import estimate_cost
from dem.deck import MAIN_DECK, build_deck
from workflows.bench_dem_deck import (
    BenchError,
    box_deck_text,
    loop_details,
    paper_core_hours,
    parse_loop_time,
    parse_runs,
)
from workflows.config import load_preset


def _fixes(text: str) -> dict[str, list[str]]:
    """fix style -> the fixes' argument texts (after 'fix ID group style')."""
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        tokens = line.split()
        if len(tokens) >= 4 and tokens[0] == "fix":
            out.setdefault(tokens[3], []).append(" ".join(tokens[4:]))
    return out


def _commands(text: str, name: str) -> list[str]:
    return [" ".join(line.split()[1:]) for line in text.splitlines() if line.split()[:1] == [name]]


def _physics(text: str) -> dict:
    fixes = _fixes(text)
    walls = fixes.get("wall/gran", [])
    return {
        "pair_style": _commands(text, "pair_style"),
        "pair_coeff": _commands(text, "pair_coeff"),
        "timestep": [float(v) for v in _commands(text, "timestep")],
        "neighbor": _commands(text, "neighbor"),
        "neigh_modify": _commands(text, "neigh_modify"),
        "hard_particles": _commands(text, "hard_particles"),
        "newton": _commands(text, "newton"),
        "communicate": _commands(text, "communicate"),
        "materials": sorted(fixes["property/global"]),
        "templates": sorted(fixes["particletemplate/sphere"]),
        "gravity": fixes["gravity"],
        "integration": fixes["nve/sphere"],
        "timestep_check": fixes["check/timestep/gran"],
        # contact model and atom type of the primitive walls
        "wall_models": sorted({re.match(r"(.*?) primitive type (\d+)", w).groups() for w in walls if " primitive " in w}),
    }


@pytest.mark.parametrize("preset", ["smoke", "paper"])
def test_box_deck_has_the_blender_physics(preset):
    dem = load_preset(preset).dem
    blender = build_deck(dem)[MAIN_DECK]
    box = box_deck_text(dem, particles=1234, steps=5000)
    want, got = _physics(blender), _physics(box)
    assert got == want
    assert want["pair_style"] == ["gran model hertz tangential history rolling_friction cdt"]
    assert len(want["templates"]) == 2 * dem.particles.size_classes
    assert want["timestep"] == [pytest.approx(dem.timestep_s, rel=1e-9)]


def test_box_deck_is_a_plain_box_of_the_same_particles():
    dem = load_preset("smoke").dem
    box = box_deck_text(dem, particles=1234, steps=5000)
    fixes = _fixes(box)
    # no impeller, meshes, feeders, discharge or dumps
    for style in ("mesh/surface", "mesh/surface/planar", "move/mesh", "massflow/mesh", "insert/rate/region"):
        assert style not in fixes
    assert not _commands(box, "dump") and not _commands(box, "read_restart")
    # five steel primitive walls: floor and four sides
    prims = sorted(w.split()[-2] for w in fixes["wall/gran"])
    assert prims == ["xplane", "xplane", "yplane", "yplane", "zplane"]
    # one insertion topping the box up to the particle count, with every template of A and B
    (ins,) = fixes["insert/pack"]
    assert "particles_in_region 1234" in ins and "all_in yes" in ins
    (pdd,) = fixes["particledistribution/discrete/numberbased"]
    tokens = pdd.split()
    assert int(tokens[1]) == 2 * dem.particles.size_classes
    weights = [float(w) for w in tokens[3::2]]
    assert sum(weights) == pytest.approx(1.0, abs=1e-12)
    assert sorted(tokens[2::2]) == sorted(t.split()[0] for t in _commands(box, "fix") if "particletemplate/sphere" in t)
    # the measured run is the last one and the insertion is gone by then
    runs = _commands(box, "run")
    assert runs[-1] == "5000" and len(runs) == 3
    assert box.index("unfix           ins") < box.rindex("run ")
    with pytest.raises(BenchError):
        box_deck_text(dem, particles=0, steps=10)


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
    out = paper_core_hours(4.0e6, 1.8, 1500.0, smoke, box_rate_serial=6.0e6)
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
