"""DEM deck efficiency and the paper's core-hours (``python -m workflows.bench_dem_deck``).

Writes ``results/bench/dem_deck.json`` (read by ``pbmdem dem slurm``:
``blender_particle_steps_per_s_serial``) and prints a table. Targets (issue): the blender
deck runs at >= 60 % of the particle-step rate of a plain box of the same particles, and
2 ranks are >= 1.7x faster than one.

Method
------
1. **Fill** (temporary directory): the preset's blender deck (``smoke`` by default) from
   empty for ``--fill-s`` simulated seconds (25 s: the smoke hold-up plateaus from ~26 s),
   with sparse dumps and one restart file written at the last step.
2. **Blender**: the deck's own resume variant (:func:`dem.deck.build_deck` with
   ``resume_from``) continues from that restart for ``--steps`` steps, on 1 rank and on
   2 ranks (``mpirun -np 2``, the deck's ``processors * 1 1``). Measured with the deck's
   dumps at their normal interval (what users run: moving impeller mesh, massflow
   counting/deletion, insertion, dumps, thermo, timestep check) and again with the
   ``dump`` line removed (``*_nodump``), which isolates the dump cost.
3. **Plain box** (:func:`box_deck_text`): the same particle templates and size classes,
   materials, pair style (Hertz + history + rolling friction cdt), timestep, neighbour
   settings, gravity, thermo interval and timestep check, in a rectangular box of steel
   ``wall/gran`` primitives of the blender's length and a width of the barrel's radius
   (about the blender's bed depth). ``fix insert/pack`` tops the box up to the blender's
   particle count, the bed settles, and the same number of steps is measured, on 1 and
   2 ranks. No impeller, no meshes, no insertion, no discharge, no dumps.

Throughput = mean of the thermo ``Atoms`` column over the measured run x steps / the
``Loop time`` LIGGGHTS prints for that run (wall time of the time-stepping loop; setup and
restart reading excluded). The process CPU time of every run is recorded too: on a shared
machine the wall time is the victim of other jobs.

Core-hours of the ``paper`` preset (2 mm particles): :func:`dem.cluster.estimate_cost`
with the measured serial blender throughput and the steady hold-up scaled by solid volume
from the measured smoke hold-up (x (6/2)^3), or, when ``pbmdem dem slurm`` finds a shipped
reference run (``workflows/reference/dem-*.h5``), from that run's hold-up as that command
does (both are recorded). Assumption: particle-steps per second do not depend on the
particle size (the skin and the bins scale with the diameter, so neighbours and contacts
per particle are the same; DESIGN.md measured 3-4.5e6 for 2 mm and 3.9e6 for 6 mm on one
core). The steady hold-up bounds the run's mean from above (the blender fills first).
Parallel efficiency: the measured 2-rank one on 2 cores; ``estimate_cost``'s default
(0.85) on 8 and 32 cores, which nothing here measures (a 1-D split along x of a 330 mm
barrel gives 10 mm slabs on 32 ranks and no load balancing: expect less).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

OUT = Path("results/bench/dem_deck.json")
#: the paper's cost: 6.5 days on 8 workers
PAPER_CORE_HOURS = 6.5 * 24 * 8
LOAD_WARN = 1.5
BOX_LOG = "log.box.liggghts"
BOX_DECK = "in.box"

_LOOP_RE = re.compile(
    r"Loop time of\s+(?P<time>[-+0-9.eE]+)\s+on\s+(?P<procs>\d+)\s+procs\s+"
    r"(?:\(\d+\s+MPI\s+x\s+\d+\s+OpenMP\)\s+)?for\s+(?P<steps>\d+)\s+steps\s+with\s+(?P<atoms>\d+)\s+atoms"
)


class BenchError(RuntimeError):
    """LIGGGHTS failed (ERROR line, non-zero exit, no timing line) or the setup is wrong."""


# ----------------------------------------------------------------------------- log parsing
@dataclass
class LoopTime:
    """One ``Loop time of ...`` line."""

    seconds: float
    procs: int
    steps: int
    atoms: int


def parse_loop_time(line: str) -> LoopTime | None:
    """``Loop time of X on P procs for S steps with N atoms`` -> LoopTime, else None."""
    match = _LOOP_RE.search(line)
    if match is None:
        return None
    return LoopTime(float(match["time"]), int(match["procs"]), int(match["steps"]), int(match["atoms"]))


@dataclass
class RunSegment:
    """One ``run`` command of a LIGGGHTS log: its thermo rows and its loop time."""

    header: list[str] = field(default_factory=list)
    rows: list[list[float]] = field(default_factory=list)
    loop: LoopTime | None = None

    def column(self, name: str) -> list[float]:
        if name not in self.header:
            return []
        k = self.header.index(name)
        return [row[k] for row in self.rows]


def parse_runs(text: str) -> list[RunSegment]:
    """Split a LIGGGHTS log into its runs (one per ``Loop time`` line), with thermo rows."""
    runs: list[RunSegment] = []
    current = RunSegment()
    for line in text.splitlines():
        loop = parse_loop_time(line)
        if loop is not None:
            current.loop = loop
            runs.append(current)
            current = RunSegment()
            continue
        tokens = line.split()
        if not tokens:
            continue
        if tokens[0] == "Step":
            current.header, current.rows = tokens, []
            continue
        if current.header and len(tokens) == len(current.header):
            try:
                current.rows.append([float(t) for t in tokens])
            except ValueError:
                pass
    return runs


_SECTION_RE = re.compile(r"^\s*(\w+)\s+time\s+\(%\)\s+=\s+([-+0-9.eE]+)")


def loop_details(text: str) -> dict:
    """What LIGGGHTS prints after the last ``Loop time`` line: seconds per section (Pair,
    Neigh, Comm, Outpt, Other -- fixes such as walls, meshes and insertion count as Other),
    neighbours per particle and neighbour-list builds."""
    starts = [m.start() for m in re.finditer(r"Loop time of", text)]
    if not starts:
        return {}
    tail = text[starts[-1]:].splitlines()[1:]
    out: dict = {"sections_s": {}}
    for line in tail:
        if line.startswith("Loop time of") or line.split()[:1] == ["Step"]:
            break
        section = _SECTION_RE.match(line)
        if section:
            out["sections_s"][section.group(1)] = float(section.group(2))
        for key, label in (("neighbours_per_particle", "Ave neighs/atom ="), ("neighbour_builds", "Neighbor list builds ="),
                           ("dangerous_builds", "Dangerous builds =")):
            if line.startswith(label):
                out[key] = float(line.split("=")[1])
    return out


def error_lines(text: str) -> list[str]:
    return [line.strip() for line in text.splitlines() if line.lstrip().startswith("ERROR")]


# ----------------------------------------------------------------------------- the plain box
_COPIED = (
    # (what, regex on a line of the blender deck); every match is copied verbatim
    ("setup", r"^(atom_style|atom_modify|boundary|newton|communicate|units|processors)\s"),
    ("neighbour", r"^(neighbor|neigh_modify|hard_particles)\s"),
    ("materials", r"^fix\s+m\d\s+all\s+property/global\s"),
    ("pair", r"^(pair_style|pair_coeff|timestep)\s"),
    ("gravity", r"^fix\s+\S+\s+all\s+gravity\s"),
    ("templates", r"^fix\s+\S+\s+all\s+particletemplate/sphere\s"),
    ("integration", r"^fix\s+\S+\s+all\s+(nve/sphere|check/timestep/gran)(\s|$)"),
    ("thermo", r"^thermo\s"),
)


def _deck_lines(text: str, pattern: str) -> list[str]:
    rx = re.compile(pattern)
    return [line.strip() for line in text.splitlines() if rx.search(line.strip())]


def box_geometry(dem_config, particles: int) -> dict:
    """Box of the blender's length and of width = barrel radius; insertion height so that
    random packing at ~25 % solids holds every particle; expected settled depth at 60 %."""
    from dem.deck import size_classes

    p, g = dem_config.particles, dem_config.geometry
    diam, weights = size_classes(p.diameter_m, p.diameter_sd_m, p.size_classes)
    mean_volume = float((weights * math.pi / 6 * diam**3).sum())
    length, width = g.length_m, g.radius_m
    solid = particles * mean_volume
    bed_depth = solid / (0.6 * length * width)
    height = max(solid / (0.25 * length * width), 4 * float(diam.max()))
    return {"length_m": length, "width_m": width, "fill_height_m": height, "bed_depth_m": bed_depth,
            "margin_m": float(diam.max())}


def box_deck_text(dem_config, particles: int, steps: int, fill_s: float = 1.0, settle_s: float = 0.5) -> str:
    """LIGGGHTS deck of a settled bed of ``particles`` particles in a plain box, then
    ``steps`` measured steps (the log's last ``Loop time``). Pure: returns text.

    Everything physical is copied line for line from the blender deck of ``dem_config``
    (:func:`dem.deck.build_deck`); the box walls use the barrel's ``wall/gran`` model with
    the steel atom type. A and B templates are inserted through one number-weighted
    distribution, each weight half its own component's, so the mix is the blender's feed
    at 50/50 (the material of A and B is the same)."""
    from dem.deck import MAIN_DECK, _primes_from, build_deck

    if particles < 1 or steps < 1:
        raise BenchError(f"particles ({particles}) and steps ({steps}) must be >= 1")
    blender = build_deck(dem_config)[MAIN_DECK]
    copied: dict[str, list[str]] = {}
    for what, pattern in _COPIED:
        lines = _deck_lines(blender, pattern)
        if not lines:
            raise BenchError(f"the blender deck has no {what} line (pattern {pattern!r}): update box_deck_text")
        copied[what] = lines
    barrel = _deck_lines(blender, r"^fix\s+\S+\s+all\s+wall/gran\s.*\sprimitive\s")
    if not barrel:
        raise BenchError("the blender deck has no wall/gran primitive line to take the wall model from")
    wall_model = re.match(r"^fix\s+\S+\s+all\s+wall/gran\s+(.*?)\s+primitive\s", barrel[0]).group(1)
    steel = re.search(r"\sprimitive\s+type\s+(\d+)\s", barrel[0]).group(1)

    # number-weighted templates of both components, each component's weights halved
    pdd = _deck_lines(blender, r"^fix\s+\S+\s+all\s+particledistribution/discrete/numberbased\s")
    if not pdd:
        raise BenchError("the blender deck has no particledistribution line")
    names, weights = [], []
    for line in pdd:
        tokens = line.split()
        for name, w in zip(tokens[6::2], tokens[7::2]):
            names.append(name)
            weights.append(float(w) / len(pdd))
    text_w = [f"{w:.8f}" for w in weights[:-1]]
    text_w.append(f"{1.0 - sum(float(t) for t in text_w):.8f}")

    dt = float(copied["pair"][[l.split()[0] for l in copied["pair"]].index("timestep")].split()[1])
    thermo_every = int(copied["thermo"][0].split()[1])
    num = dem_config.numerics
    n_cls = dem_config.particles.size_classes
    seed_pdd, seed_ins = _primes_from(num.seed, 2 * n_cls + 6)[-2:]  # beyond the blender's own seeds

    geo = box_geometry(dem_config, particles)
    L_, W, H, m = geo["length_m"], geo["width_m"], geo["fill_height_m"], geo["margin_m"]
    g = lambda x: f"{x:.10g}"  # noqa: E731
    fill_steps = max(1, round(fill_s / dt))
    settle_steps = max(1, round(settle_s / dt))
    insert_every = max(1, round(0.1 / dt))

    out: list[str] = [
        "# pbmdem bench: plain box of the blender deck's particles (workflows.bench_dem_deck.box_deck_text).",
        f"# {particles} particles settled in a {g(L_)} x {g(W)} m box of steel wall/gran primitives, "
        f"then {steps} measured steps (the last Loop time).",
        "",
        *copied["setup"][: [l.split()[0] for l in copied["setup"]].index("processors") + 1],
        "",
        f"region          domain block {g(-m)} {g(L_ + m)} {g(-W / 2 - m)} {g(W / 2 + m)} {g(-m)} {g(H + m)} units box",
        "create_box      3 domain",
        "",
        *copied["neighbour"],
        "",
        *copied["materials"],
        "",
        *copied["pair"],
        *copied["gravity"],
        "",
        "# the box: five steel primitives with the blender barrel's contact model",
        f"fix boxfloor all wall/gran {wall_model} primitive type {steel} zplane 0.0",
        f"fix boxxlo all wall/gran {wall_model} primitive type {steel} xplane 0.0",
        f"fix boxxhi all wall/gran {wall_model} primitive type {steel} xplane {g(L_)}",
        f"fix boxylo all wall/gran {wall_model} primitive type {steel} yplane {g(-W / 2)}",
        f"fix boxyhi all wall/gran {wall_model} primitive type {steel} yplane {g(W / 2)}",
        "",
        *copied["templates"],
        f"fix pddbox all particledistribution/discrete/numberbased {seed_pdd} {len(names)} "
        + " ".join(f"{n} {w}" for n, w in zip(names, text_w)),
        f"region          fill block 0 {g(L_)} {g(-W / 2)} {g(W / 2)} 0 {g(H)} units box",
        f"fix ins all insert/pack seed {seed_ins} distributiontemplate pddbox insert_every {insert_every} "
        f"overlapcheck yes all_in yes particles_in_region {particles} region fill ntry_mc 10000",
        "",
        *copied["integration"],
        "",
        "thermo_style    custom step atoms ke",
        f"thermo          {thermo_every}",
        "thermo_modify   lost ignore norm no",
        "",
        f"# fill: top the box up to {particles} particles every 0.1 s, then settle without insertion",
        f"run             {fill_steps}",
        "unfix           ins",
        f"run             {settle_steps}",
        "# measured",
        f"run             {steps}",
    ]
    return "\n".join(out) + "\n"


def deck_physics(text: str) -> dict:
    """The physics lines of a deck (pair style, materials, templates, timestep, neighbour
    settings, gravity, wall contact model), for comparing two decks."""
    out = {}
    for what, pattern in _COPIED:
        if what in ("setup", "thermo"):
            continue
        out[what] = sorted(_deck_lines(text, pattern))
    walls = _deck_lines(text, r"^fix\s+\S+\s+all\s+wall/gran\s.*\sprimitive\s")
    out["wall_model"] = sorted({re.match(r"^fix\s+\S+\s+all\s+wall/gran\s+(.*?)\s+primitive\s+type\s+(\d+)", w).groups()
                                for w in walls})
    return out


# ----------------------------------------------------------------------------- running
@dataclass
class Measurement:
    name: str
    np: int
    steps: int
    loop_s: float
    atoms_mean: float
    atoms_end: int
    particle_steps_per_s: float
    cpu_s: float
    wall_s: float
    load_before: float
    warnings: int
    run_dir: str
    details: dict = field(default_factory=dict)


def _run_liggghts(run_config, np: int, run_dir: Path, deck: str, log: str, timeout_s: float) -> tuple[str, float, float]:
    """Run ``deck`` in ``run_dir``; return (stdout text, wall s, CPU s of all ranks)."""
    from dem.run import _terminate_group, solver_command

    command = [*solver_command(run_config, np, deck), "-log", log]
    out_path = run_dir / f"{Path(log).stem}.out"
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    with open(out_path, "w") as out:
        proc = subprocess.Popen(command, cwd=run_dir, stdout=out, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
        error_seen = None
        try:
            while (rc := proc.poll()) is None:
                time.sleep(0.5)
                now = time.monotonic()
                if now - t0 > timeout_s:
                    raise BenchError(f"LIGGGHTS ran longer than {timeout_s:.0f} s on {deck} in {run_dir}: stopped")
                # an MPI rank can hang after another printed ERROR: stop it after a grace period
                if error_seen is None and error_lines(out_path.read_text(errors="replace")):
                    error_seen = now
                if error_seen is not None and now - error_seen > 30:
                    _terminate_group(proc)
                    rc = proc.wait()
                    break
        except BaseException:  # timeout, Ctrl-C: stop every rank we started
            _terminate_group(proc)
            raise
    wall = time.monotonic() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    text = out_path.read_text(errors="replace")
    errors = error_lines(text)
    if errors or rc != 0:
        tail = "\n".join(text.rstrip().splitlines()[-20:])
        what = f"reported {errors[0]!r}" if errors else f"exited with status {rc}"
        raise BenchError(f"LIGGGHTS {what} running {deck} with {np} rank(s) in {run_dir}:\n{tail}")
    return text, wall, cpu


def _measure(name: str, run_config, np: int, run_dir: Path, deck: str, log: str, timeout_s: float) -> Measurement:
    load = os.getloadavg()[0]
    text, wall, cpu = _run_liggghts(run_config, np, run_dir, deck, log, timeout_s)
    runs = parse_runs(text)
    if not runs or runs[-1].loop is None:
        raise BenchError(f"no 'Loop time' line in the output of {deck} ({run_dir})")
    last = runs[-1]
    atoms = last.column("Atoms") or [float(last.loop.atoms)]
    mean_atoms = sum(atoms) / len(atoms)
    if last.loop.seconds <= 0 or last.loop.steps <= 0:
        raise BenchError(f"{deck}: implausible loop time {last.loop}")
    rate = mean_atoms * last.loop.steps / last.loop.seconds
    n_warn = sum(1 for line in text.splitlines() if line.lstrip().startswith("WARNING"))
    details = loop_details(text)
    sections = ", ".join(f"{k} {v / last.loop.seconds:.0%}" for k, v in details.get("sections_s", {}).items())
    print(f"  {name:<16} np={np}  {last.loop.steps} steps, {mean_atoms:.0f} particles, loop {last.loop.seconds:.2f} s "
          f"(wall {wall:.1f} s, CPU {cpu:.1f} s, load {load:.2f}): {rate:.3g} particle-steps/s"
          + (f"\n{'':21}loop: {sections}; {details.get('neighbour_builds', 0):.0f} neighbour-list builds" if sections else ""),
          flush=True)
    return Measurement(name, np, last.loop.steps, last.loop.seconds, mean_atoms, last.loop.atoms, rate, cpu, wall, load,
                       n_warn, str(run_dir), details)


def _with_numerics(config, **numerics):
    from workflows.config import config_from_dict

    data = config.to_dict()
    data["dem"]["numerics"].update({k: v for k, v in numerics.items() if k != "duration_s"})
    if "duration_s" in numerics:
        data["dem"]["operation"]["duration_s"] = numerics["duration_s"]
    return config_from_dict(data, source="benchmark configuration")


def fill(config, work: Path, fill_s: float, np: int, timeout_s: float) -> tuple[Path, int, float]:
    """Run the blender from empty for ``fill_s`` s; return (restart file, its step, Atoms at the end)."""
    from dem.deck import MAIN_DECK, build_deck, write_deck

    dem = config.dem
    fill_config = _with_numerics(config, duration_s=fill_s, restart_interval_s=fill_s,
                                 dump_interval_s=min(dem.tables.window_s, fill_s))
    run_dir = work / "fill"
    write_deck(build_deck(fill_config.dem), run_dir)
    print(f"  fill: {fill_s:g} s simulated from empty on {np} rank(s) in {run_dir} ...", flush=True)
    t0 = time.monotonic()
    text, wall, _ = _run_liggghts(dem.run, np, run_dir, MAIN_DECK, "log.fill.liggghts", timeout_s)
    runs = parse_runs(text)
    atoms = runs[-1].column("Atoms") if runs else []
    restarts = sorted(run_dir.glob("restart/restart.*.bin"), key=lambda p: int(re.findall(r"\d+", p.name)[-1]))
    if not restarts or not atoms:
        raise BenchError(f"the fill run wrote no restart file or no thermo ({run_dir})")
    step = int(re.findall(r"\d+", restarts[-1].name)[-1])
    print(f"  fill: done in {time.monotonic() - t0:.0f} s wall; {atoms[-1]:.0f} particles held at step {step}", flush=True)
    return restarts[-1], step, atoms[-1]


def _blender_dir(config, work: Path, name: str, restart: Path, restart_step: int, steps: int, dumps: bool) -> Path:
    from dem.deck import RESUME_DECK, build_deck, write_deck

    dt = config.dem.timestep_s
    measure_config = _with_numerics(config, duration_s=(restart_step + steps) * dt)
    local = f"restart/{restart.name}"
    files = build_deck(measure_config.dem, resume_from=local)
    if not dumps:
        files[RESUME_DECK] = "".join(line for line in files[RESUME_DECK].splitlines(keepends=True)
                                     if not line.startswith("dump "))
    run_dir = work / name
    write_deck(files, run_dir)
    shutil.copy2(restart, run_dir / local)
    return run_dir


def paper_core_hours(rate_serial: float, speedup_np2: float | None, holdup_smoke: float, smoke_config,
                     box_rate_serial: float | None = None) -> dict:
    """Core-hours of the ``paper`` preset on 2, 8 and 32 cores from the measured rate.

    ``core_hours`` uses the blender's measured particle-steps per second as is (the cost
    per particle-step of the smoke deck, conservative). ``core_hours_overhead_amortised``
    (with ``box_rate_serial``) splits the smoke blender's step into the plain box's cost per
    particle plus a per-step overhead (impeller mesh, insertion, discharge, dumps) taken as
    independent of the particle count, which a 27x larger bed amortises: a lower estimate."""
    from dem.cluster import estimate_cost
    from workflows.config import load_preset

    paper = load_preset("paper").dem
    scale = (smoke_config.dem.particles.diameter_m / paper.particles.diameter_m) ** 3
    scaled = holdup_smoke * scale
    holdup, source = scaled, (f"measured smoke hold-up {holdup_smoke:.0f} x "
                              f"({smoke_config.dem.particles.diameter_m * 1e3:g}/{paper.particles.diameter_m * 1e3:g})^3")
    reference = None
    try:
        from workflows.cli_dem_cluster import reference_holdup

        # the hold-up `pbmdem dem slurm` uses: a shipped reference run, scaled by solid volume
        reference = reference_holdup(paper)
        holdup, source = reference
    except (LookupError, ImportError):  # no shipped reference (optional): keep the scaled measurement
        pass
    eff2 = min(1.0, speedup_np2 / 2) if speedup_np2 else 0.85
    why2 = "measured 2-rank speed-up / 2" if speedup_np2 else "assumed (estimate_cost default)"
    amortised_rate = None
    if box_rate_serial and box_rate_serial > 0:
        overhead_s_per_step = max(0.0, holdup_smoke * (1 / rate_serial - 1 / box_rate_serial))
        amortised_rate = holdup / (holdup / box_rate_serial + overhead_s_per_step)
    out = {"holdup_particles": holdup, "holdup_source": source, "holdup_scaled_from_smoke": scaled,
           "holdup_from_reference": reference[0] if reference else None, "particle_steps_per_core_s": rate_serial,
           "throughput_assumption": "particle-steps/s independent of particle size (measured on the smoke deck, 6 mm)",
           "paper_reported_core_hours": PAPER_CORE_HOURS, "cores": {}}
    out["particle_steps_per_core_s_overhead_amortised"] = amortised_rate
    for cores, eff, why in ((2, eff2, why2), (8, 0.85, "assumed (estimate_cost default)"),
                            (32, 0.85, "assumed (estimate_cost default)")):
        est = estimate_cost(paper, holdup, rate_serial, cores, eff)
        out["steps"] = est.steps
        out["cores"][str(cores)] = {"core_hours": est.core_hours, "wall_hours": est.wall_hours,
                                    "parallel_efficiency": eff, "efficiency_source": why,
                                    "vs_paper": est.core_hours / PAPER_CORE_HOURS}
        if reference:
            out["cores"][str(cores)]["core_hours_smoke_scaled_holdup"] = estimate_cost(
                paper, scaled, rate_serial, cores, eff).core_hours
        if amortised_rate:
            low = estimate_cost(paper, holdup, amortised_rate, cores, eff)
            out["cores"][str(cores)]["core_hours_overhead_amortised"] = low.core_hours
            out["cores"][str(cores)]["wall_hours_overhead_amortised"] = low.wall_hours
    return out


def _liggghts_running() -> list[str]:
    try:
        out = subprocess.run(["pgrep", "-af", "liggghts"], capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.TimeoutExpired):
        return []
    return [line for line in out.splitlines() if line.strip()]


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m workflows.bench_dem_deck", description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="smoke", help="blender preset to measure (default smoke)")
    parser.add_argument("--steps", type=int, default=20000, help="measured steps per run (default 20000)")
    parser.add_argument("--fill-s", type=float, default=25.0,
                        help="simulated seconds of filling before measuring (default 25: smoke's hold-up is near steady)")
    parser.add_argument("--fill-np", type=int, default=None, help="ranks for the fill (default: the preset's dem.run.np)")
    parser.add_argument("--nps", default="1,2", help="rank counts to measure (default 1,2)")
    parser.add_argument("--no-nodump", action="store_true", help="skip the blender runs without dumps")
    parser.add_argument("--out", default=str(OUT))
    parser.add_argument("--work", default=None, help="keep the run directories here (default: a temporary directory)")
    parser.add_argument("--timeout", type=float, default=3600.0, help="per LIGGGHTS run [s]")
    args = parser.parse_args(argv if argv is not None else [])

    from dem.run import liggghts_version
    from workflows.config import load_preset

    config = load_preset(args.preset)
    nps = [int(n) for n in args.nps.split(",") if n.strip()]
    version = liggghts_version(config.dem.run.liggghts)
    load_before = os.getloadavg()
    others = _liggghts_running()
    if load_before[0] > LOAD_WARN:
        msg = (f"machine load {load_before[0]:.2f} > {LOAD_WARN} before starting: the timings will be slowed down "
               f"by other jobs" + (f" ({len(others)} LIGGGHTS processes running)" if others else ""))
        print(f"WARNING: {msg}", file=sys.stderr, flush=True)
    print(f"DEM deck benchmark: preset {args.preset}, {args.steps} steps, ranks {nps}, LIGGGHTS {version}", flush=True)

    t_start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="bench_dem_deck_") as tmp:
        work = Path(args.work) if args.work else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        restart, restart_step, held_fill = fill(config, work, args.fill_s, args.fill_np or config.dem.run.np,
                                                args.timeout)
        results: dict[str, Measurement] = {}
        particles = None
        for np in nps:
            # blender first: its particle count sets the box's
            run_dir = _blender_dir(config, work, f"blender_np{np}", restart, restart_step, args.steps, dumps=True)
            from dem.deck import RESUME_DECK, RESUME_LOG_FILE

            m = _measure("blender", config.dem.run, np, run_dir, RESUME_DECK, RESUME_LOG_FILE, args.timeout)
            results[f"blender_np{np}"] = m
            if particles is None:
                particles = round(m.atoms_mean)
            box_dir = work / f"box_np{np}"
            box_dir.mkdir(parents=True, exist_ok=True)
            (box_dir / BOX_DECK).write_text(box_deck_text(config.dem, particles, args.steps))
            mb = _measure("box", config.dem.run, np, box_dir, BOX_DECK, BOX_LOG, args.timeout)
            if mb.atoms_end != particles:
                raise BenchError(f"the box holds {mb.atoms_end} particles, not {particles}: insertion fell short "
                                 f"({box_dir})")
            results[f"box_np{np}"] = mb
            if not args.no_nodump:
                run_dir = _blender_dir(config, work, f"blender_nodump_np{np}", restart, restart_step, args.steps,
                                       dumps=False)
                results[f"blender_nodump_np{np}"] = _measure("blender (no dump)", config.dem.run, np, run_dir,
                                                             RESUME_DECK, RESUME_LOG_FILE, args.timeout)
    load_after = os.getloadavg()

    def rate(key: str) -> float | None:
        return results[key].particle_steps_per_s if key in results else None

    def ratio(a: float | None, b: float | None) -> float | None:
        return a / b if a and b else None

    record: dict = {
        "preset": args.preset,
        "liggghts_version": version,
        "steps": args.steps,
        "particles": particles,
        "fill_s": args.fill_s,
        "fill_particles_held": held_fill,
        "restart_step": restart_step,
        "timestep_s": config.dem.timestep_s,
        "dumps": "blender_* runs: the deck's dumps at their normal interval "
                 f"({config.dem.numerics.dump_interval_s} s); blender_nodump_*: dump line removed; box: no dumps",
        "box": box_geometry(config.dem, particles),
    }
    for np in nps:
        for kind in ("blender", "box", "blender_nodump"):
            record[f"{kind}_particle_steps_per_s_{'serial' if np == 1 else f'np{np}'}"] = rate(f"{kind}_np{np}")
    for np in nps:
        tag = "serial" if np == 1 else f"np{np}"
        record[f"efficiency_{tag}"] = ratio(rate(f"blender_np{np}"), rate(f"box_np{np}"))
        record[f"efficiency_nodump_{tag}"] = ratio(rate(f"blender_nodump_np{np}"), rate(f"box_np{np}"))
        if np != 1:
            record[f"speedup_np{np}_blender"] = ratio(rate(f"blender_np{np}"), rate("blender_np1"))
            record[f"speedup_np{np}_box"] = ratio(rate(f"box_np{np}"), rate("box_np1"))
            record[f"speedup_np{np}_blender_nodump"] = ratio(rate(f"blender_nodump_np{np}"), rate("blender_nodump_np1"))
    record["targets"] = {"efficiency_min": 0.6, "speedup_np2_min": 1.7}
    if rate("blender_np1"):
        record["paper_core_hours"] = paper_core_hours(rate("blender_np1"), record.get("speedup_np2_blender"),
                                                      results["blender_np1"].atoms_mean, config, rate("box_np1"))
    record["runs"] = {k: asdict(v) for k, v in results.items()}
    record["machine_load"] = {"before": list(load_before), "after": list(load_after), "cpus": os.cpu_count(),
                              "other_liggghts_before": others}
    record["machine"] = {"node": platform.node(), "python": platform.python_version(), "processor": platform.processor()}
    record["wall_s"] = time.monotonic() - t_start

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=2, default=str) + "\n")
    print_table(record, nps)
    print(f"wrote {out}")
    return record


def _fmt(x, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def print_table(record: dict, nps: list[int]) -> None:
    print(f"\n{record['particles']} particles, {record['steps']} steps; particle-steps per second (Loop time):")
    print(f"{'ranks':>6} {'blender':>10} {'no dump':>10} {'box':>10} {'eff.':>6} {'eff. nodump':>12}")
    for np in nps:
        tag = "serial" if np == 1 else f"np{np}"
        print(f"{np:>6} {_fmt(record.get(f'blender_particle_steps_per_s_{tag}'), '10.3g')} "
              f"{_fmt(record.get(f'blender_nodump_particle_steps_per_s_{tag}'), '10.3g')} "
              f"{_fmt(record.get(f'box_particle_steps_per_s_{tag}'), '10.3g')} "
              f"{_fmt(record.get(f'efficiency_{tag}'), '6.0%')} {_fmt(record.get(f'efficiency_nodump_{tag}'), '12.0%')}")
    for np in nps:
        if np != 1:
            print(f"speed-up {np} ranks: blender {_fmt(record.get(f'speedup_np{np}_blender'), '.2f')}x, "
                  f"no dump {_fmt(record.get(f'speedup_np{np}_blender_nodump'), '.2f')}x, "
                  f"box {_fmt(record.get(f'speedup_np{np}_box'), '.2f')}x (target >= 1.7x)")
    cost = record.get("paper_core_hours")
    if cost:
        print(f"paper preset: {cost['steps']} steps x {cost['holdup_particles']:.0f} particles ({cost['holdup_source']})")
        for cores, est in cost["cores"].items():
            low = est.get("core_hours_overhead_amortised")
            print(f"  {cores:>3} cores: {est['core_hours']:7.0f} core-hours ({est['wall_hours']:.1f} h wall"
                  + (f"; {low:.0f} if the blender's per-step overhead is amortised" if low else "")
                  + f"), parallel efficiency {est['parallel_efficiency']:.2f} {est['efficiency_source']}")
        print(f"  the paper: {cost['paper_reported_core_hours']:.0f} core-hours (6.5 days on 8 workers)")
    load = record["machine_load"]
    print(f"load average before {load['before'][0]:.2f}, after {load['after'][0]:.2f} on {load['cpus']} CPUs")


if __name__ == "__main__":
    main(sys.argv[1:])
