"""The DEM deck benchmark: LIGGGHTS' timing lines are parsed right, the paper's core-hours
follow the cost estimate, the rotating drum it measures against is the blender's physics in
the blender's barrel, every per-fix variant edits exactly what it says (and refuses a deck
without its line), the repeat statistics, and (marked ``liggghts``) a tiny real run of the
whole benchmark."""

import difflib
import json
import math
import re

import pytest

from coupling.errors import DeckError
from dem.cluster import estimate_cost
from dem.deck import DRUM_DECK, MAIN_DECK, RESUME_DECK, build_deck, build_drum_deck
from dem.geometry import simulation_box
from dem.liggghts_log import loop_details, parse_loop_time, parse_runs
from workflows.bench import dem_deck as bench_dem_deck
from workflows.bench.dem_deck import VARIANTS, cost, paper_core_hours
from workflows.cli.main import main
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
    assert out["sections_s"] == {
        "Pair": 1.04285,
        "Neigh": 0.5,
        "Comm": 0.000195497,
        "Outpt": 4.4997e-05,
        "Other": 0.234003,
    }
    assert out["neighbours_per_particle"] == 5.33571 and out["neighbour_builds"] == 7
    assert loop_details("no timing here") == {}


# --------------------------------------------------------------------------------------
# the rotating drum
# --------------------------------------------------------------------------------------

#: lines the drum must share with the blender deck, word for word: the physics and numerics
_SHARED = re.compile(
    r"^(atom_style|atom_modify|boundary|newton|communicate|units|processors|region +domain|"
    r"create_box|neighbor|neigh_modify|hard_particles|pair_style|pair_coeff|timestep|thermo +\d|"
    r"fix +(m\d|gravi|pt[AB]\d+|integr|ts) ).*$",
    re.M,
)


def _lines(text: str, start: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith(start)]


@pytest.mark.parametrize("preset", ["smoke", "paper"])
def test_drum_deck_is_the_blender_barrel_spinning(preset):
    dem = load_preset(preset).dem
    g = dem.geometry
    blender = build_deck(dem)[MAIN_DECK]
    drum = build_drum_deck(dem, particles=1490, steps=30000)[DRUM_DECK]
    assert _SHARED.findall(drum) and sorted(m.group(0) for m in _SHARED.finditer(drum)) == sorted(
        m.group(0) for m in _SHARED.finditer(blender)
    )
    box = simulation_box(g)
    assert _lines(drum, "region          domain") == [
        "region          domain block "
        + " ".join(f"{v:.10g}" for v in (box.xmin, box.xmax, box.ymin, box.ymax, box.zmin, box.zmax))
        + " units box"
    ]
    # the blender's barrel primitive, spinning about x at V = sqrt(Fr g R), Fr = 0.5
    (barrel_blender,) = _lines(blender, "fix barrel ")
    (barrel,) = _lines(drum, "fix barrel ")
    prefix, shear, dim, speed = barrel.rsplit(" ", 3)
    assert prefix == barrel_blender and (shear, dim) == ("shear", "y")
    assert float(speed) == pytest.approx(math.sqrt(0.5 * 9.81 * g.radius_m), rel=1e-9)
    walls = [line.split()[-2:] for line in _lines(drum, "fix ") if "wall/gran" in line and "xplane" in line]
    assert walls == [["xplane", "0.0"], ["xplane", f"{g.length_m:.10g}"]]
    assert "mesh" not in drum and "insert/rate" not in drum and "massflow" not in drum and "dump" not in drum
    # the insertion region is the whole barrel; the count is the blender's bed; then unfix and measure
    assert _lines(drum, "region          fill") == [
        f"region          fill cylinder x 0 0 {g.radius_m:.10g} 0 {g.length_m:.10g} units box"
    ]
    (ins,) = _lines(drum, "fix ins ")
    assert "insert/pack" in ins and "particles_in_region 1490 region fill" in ins
    runs = [line.split()[1] for line in _lines(drum, "run ")]
    assert runs == [str(round(1.0 / dem.timestep_s)), "30000"]
    assert drum.index("unfix           ins") > drum.index(f"run             {runs[0]}")
    assert drum.index("unfix           ins") < drum.rindex("run ")
    for bad in ({"particles": 0, "steps": 10}, {"particles": 10, "steps": 0}):
        with pytest.raises(DeckError, match="drum deck"):
            build_drum_deck(dem, **bad)


# --------------------------------------------------------------------------------------
# the per-fix variants of the resume deck
# --------------------------------------------------------------------------------------


def _resume(dumps: bool = True) -> str:
    return build_deck(load_preset("smoke").dem, resume_from="restart/restart.1000.bin", dumps=dumps)[RESUME_DECK]


def _diff(before: str, after: str) -> tuple[list[str], list[str]]:
    """(removed lines, added lines)."""
    diff = list(difflib.ndiff(before.splitlines(), after.splitlines()))
    return [d[2:] for d in diff if d.startswith("- ")], [d[2:] for d in diff if d.startswith("+ ")]


_THERMO = "thermo_style    custom step v_simtime atoms v_insA v_insB v_outA v_outB f_ts[1] f_ts[2]"


def test_variant_edits_change_exactly_what_they_say():
    text = _resume()
    assert _THERMO in text.splitlines()

    def fix_line(name):
        (line,) = _lines(text, f"fix {name} ")
        return line

    def variable(name):
        (line,) = _lines(text, f"variable        {name} ")
        return line

    expected = {
        "nodump": ([_lines(text, "dump ")[0]], []),
        "no_massflow": (
            [fix_line("outA"), fix_line("outB"), variable("outA"), variable("outB"), _THERMO],
            [_THERMO.replace(" v_outA v_outB", "")],
        ),
        "no_insertion": (
            [fix_line("insA"), fix_line("insB"), variable("insA"), variable("insB"), _THERMO],
            [_THERMO.replace(" v_insA v_insB", "")],
        ),
        "no_timestep_check": ([fix_line("ts"), _THERMO], [_THERMO.replace(" f_ts[1] f_ts[2]", "")]),
        "no_weir": (
            [fix_line("walls")],
            [fix_line("walls").replace("n_meshes 2 meshes impeller weir", "n_meshes 1 meshes impeller")],
        ),
        "static_impeller": ([fix_line("rotor")], []),
        "skin_0.75d": (["neighbor        0.003 bin"], ["neighbor        0.0045 bin"]),  # smoke: d = 6 mm
    }
    assert set(expected) == set(VARIANTS)
    for name, edit in VARIANTS.items():
        removed, added = _diff(text, edit(text))
        assert (sorted(removed), sorted(added)) == (sorted(expected[name][0]), sorted(expected[name][1])), name
    # the nodump edit is the deck writer's own deck without dumps
    assert VARIANTS["nodump"](text) == _resume(dumps=False)


@pytest.mark.parametrize("name", list(VARIANTS))
def test_a_variant_refuses_a_deck_without_its_line(name):
    text = _resume()
    # a deck that already lacks the line: the variant's own output (the skin edit keeps its
    # line, so its deck is one without a neighbor line)
    without = text.replace("neighbor        0.003 bin\n", "") if name == "skin_0.75d" else VARIANTS[name](text)
    with pytest.raises(DeckError, match=re.escape(f"variant {name}")):
        VARIANTS[name](without)


def test_cost_and_its_scatter():
    out = cost([10.0, 11.0, 9.0], [9.0, 9.5, 8.0])
    assert out["cost"] == pytest.approx((10.0 - 9.0) / 10.0)
    assert out["spread"] == pytest.approx(2.0 / 10.0)  # the base's range is the larger
    assert out["within_scatter"] is True
    assert cost([10.0, 10.1], [8.0, 8.1])["within_scatter"] is False
    single = cost([10.0], [9.0])
    assert single["spread"] is None and single["within_scatter"] is None


def test_every_variant_runs_on_one_rank_and_nodump_on_all():
    plan = bench_dem_deck._plan([1, 2], list(VARIANTS))
    assert plan[0] == ("blender", 1, None) and plan[len(VARIANTS) + 1] == ("drum", 1, None)
    assert [v for kind, np_, v in plan if np_ == 1 and v] == list(VARIANTS)
    assert [(kind, v) for kind, np_, v in plan if np_ == 2] == [
        ("blender", None),
        ("blender", "nodump"),
        ("drum", None),
    ]


# --------------------------------------------------------------------------------------
# a tiny real run of the whole benchmark
# --------------------------------------------------------------------------------------


@pytest.mark.liggghts
def test_tiny_benchmark_run_writes_every_key(tmp_path):
    out = tmp_path / "dem_deck.json"
    assert (
        main(
            [
                "bench",
                "dem-deck",
                "--steps",
                "200",
                "--fill-s",
                "0.3",
                "--repeats",
                "1",
                "--work",
                str(tmp_path / "work"),
                "--out-file",
                str(out),
            ]
        )
        == 0
    )
    record = json.loads(out.read_text())
    for key in (
        "blender_particle_steps_per_s_serial",
        "blender_particle_steps_per_s_np2",
        "blender_nodump_particle_steps_per_s_serial",
        "drum_particle_steps_per_s_serial",
        "drum_particle_steps_per_s_np2",
        "efficiency_serial",
        "efficiency_np2",
        "speedup_np2_blender",
        "speedup_np2_whole_run",
        "dump_overhead_serial",
        "dump_overhead_np2",
    ):
        assert record[key] > 0 or key.startswith("dump_overhead"), key
    assert set(record["variant_costs"]) == {f"blender_{v}_np1" for v in VARIANTS} | {"blender_nodump_np2"}
    for entry in record["variant_costs"].values():
        assert entry["loop"]["spread"] is None and entry["cpu"]["within_scatter"] is None  # one repeat
    assert set(record["fills"]) == {"np1", "np2"}
    for runs in record["runs"].values():
        (run,) = runs
        assert run["load_before"] >= 0 and run["load_after"] >= 0 and run["steps"] == 200
    assert record["targets"] == {
        "efficiency_min": 0.9,
        "speedup_np2_min": 1.7,
        "speedup_np2_whole_run_min": 1.5,
        "dump_overhead_max": 0.05,
    }
    assert record["particles"] == record["runs"]["drum_np1"][0]["atoms_end"]
