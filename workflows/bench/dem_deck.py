"""DEM deck efficiency, per-fix profile and the paper's core-hours (``python -m workflows.bench.dem_deck``).

Writes ``results/bench/dem_deck.json`` (read by ``pbmdem dem slurm``:
``blender_particle_steps_per_s_serial``) and prints a table with the targets (issue):

* efficiency: the blender deck runs at >= 90 % of the particle-step rate of a rotating drum
  of the same particles, on 1 rank (``efficiency_serial``);
* 2-rank speed-up >= 1.7x at steady state (``speedup_np2_blender``) and >= 1.5x over the
  whole smoke run, filling included (``speedup_np2_whole_run``);
* dump overhead at the interval in use <= 5 % (``dump_overhead_serial``, ``_np2``).

Method
------
1. **Fill** (temporary directory): the preset's blender deck (``smoke`` by default) from
   empty for ``--fill-s`` simulated seconds (25 s: the smoke hold-up plateaus from ~26 s),
   with sparse dumps and one restart file written at the last step, once on every rank
   count of ``--nps``. The ratio of the two fills' ``Loop time`` is the whole-run speed-up
   (one fill each, not repeated); every later run starts from the restart of the
   ``--fill-np`` fill (default: the preset's ranks).
2. **Blender**: the deck's own resume variant (:func:`dem.deck.build_deck` with
   ``resume_from``) continues from that restart for ``--steps`` steps with everything users
   run (moving impeller mesh, massflow counting/deletion, insertion, dumps at their normal
   interval, thermo, timestep check).
3. **Per-fix profile**: variants of that resume deck, each a text edit of it
   (:data:`workflows.bench.deck_variants.VARIANTS`; an edit raises :class:`DeckError` when
   its line is missing, so a deck change cannot silently make a variant a no-op), measured
   from the same restart:

   ``nodump``            no ``dump`` command: the dump cost at the interval in use
   ``no_massflow``       no ``fix outA``/``outB`` (massflow/mesh counting and deletion at the
                         discharge face) and no ``outA``/``outB`` thermo variables; particles
                         past the weir stay in the box until they leave it
   ``no_insertion``      no feeders ``fix insA``/``insB`` (and their thermo variables): the
                         bed drains slowly during the run
   ``no_timestep_check`` no ``fix ts`` (check/timestep/gran) and its thermo columns
   ``no_weir``           the ``walls`` fix holds only the impeller mesh: the weir is no
                         contact wall, so the bed drains faster
   ``static_impeller``   no ``fix rotor``: the impeller stands still. Changes the physics
                         (a resting bed): read it as what the moving mesh costs, with the
                         stirring it causes
   ``skin_0.75d``        neighbour skin 0.75 d instead of the deck's 0.5 d

4. **Drum** (:func:`dem.deck.build_drum_deck`), the fair reference: the same particle
   templates, materials, pair style, timestep, neighbour settings, gravity, thermo interval
   and timestep check, in the blender's own box and barrel, spun about its axis at Froude
   number 0.5 (a cascading bed: stirred like the blender's, so it rebuilds its neighbour
   lists about as often; a still box hardly ever does), filled with the blender's particle
   count for 1 s, then the same number of steps. No impeller, meshes, feeders, discharge or
   dumps.

Every variant runs on 1 rank; the blender, ``nodump`` and the drum also on 2 ranks
(``mpirun -np 2``, the decks' ``processors * 1 1``). The runs are **interleaved and
repeated** (``--repeats``: blender, variant 1, variant 2, ..., drum, then again), because
on a shared 2-core machine single runs scatter by +-10 % and a slow spell should hit every
variant alike. Each figure is the median over the repeats with its spread
(max - min) / median. A variant's cost is (median blender time - median variant time) /
median blender time, with the spread max(range of blender times, range of variant times) /
median blender time; a cost smaller than its spread is reported "within scatter". Times:
LIGGGHTS' ``Loop time`` (wall time of the time-stepping loop, setup and restart reading
excluded) and the process CPU time (``resource.getrusage(RUSAGE_CHILDREN)`` around the run,
start-up included, so it dilutes a cost slightly): on 1 rank the CPU time is robust to other
load, on 2 ranks it also counts MPI's busy waiting, so 2-rank figures use the Loop time.
The drum's CPU time includes its fill: its efficiency is from the Loop time only. Variants
that change the particle count (``no_massflow``, ``no_insertion``, ``no_weir``) also give
the cost per particle-step, 1 - rate(blender) / rate(variant).

Throughput = mean of the thermo ``Atoms`` column over the measured run x steps / ``Loop
time``. The 1-minute load average is recorded before and after every run and printed
beside every figure.

Core-hours of the ``paper`` preset (2 mm particles): :func:`dem.cluster.estimate_cost`
with the measured serial blender throughput and the steady hold-up scaled by solid volume
from coupling.errors import ConfigError
from the measured smoke hold-up (x (6/2)^3), or, when ``pbmdem dem slurm`` finds a shipped
reference run, from that run's hold-up as that command does (both are recorded).
Assumption: particle-steps per second do not depend on the particle size (the skin and the
bins scale with the diameter, so neighbours and contacts per particle are the same;
measured on one core: 3-4.5e6 for 2 mm and 3.9e6 for 6 mm). The steady hold-up bounds the
run's mean from above (the blender fills first). Parallel efficiency: the measured 2-rank
one on 2 cores; ``estimate_cost``'s default (0.85) on 8 and 32 cores, which nothing here
measures (a 1-D split along x of a 330 mm barrel gives 10 mm slabs on 32 ranks and no load
balancing: expect less).
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from coupling.errors import ConfigError, SolverRunError
from coupling.jsonable import write_json
from dem import deck
from dem.cluster import estimate_cost
from dem.liggghts import SolverResult, liggghts_version, run_solver, solver_command, text_tail
from dem.liggghts_log import loop_details, parse_runs
from workflows.bench.deck_variants import COUNT_CHANGING, MULTI_RANK_VARIANTS, VARIANTS
from workflows.config import config_from_dict, load_preset, override

OUT = Path("results/bench/dem_deck.json")
#: the paper's cost: 6.5 days on 8 workers
PAPER_CORE_HOURS = 6.5 * 24 * 8
LOAD_WARN = 1.5
TARGETS = {"efficiency_min": 0.9, "speedup_np2_min": 1.7, "speedup_np2_whole_run_min": 1.5, "dump_overhead_max": 0.05}


# --------------------------------------------------------------------------------------
# running and measuring
# --------------------------------------------------------------------------------------


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
    load_after: float
    warnings: int
    run_dir: str
    details: dict = field(default_factory=dict)


def _solve(run_config, np: int, run_dir: Path, main_input: str, log: str, timeout_s: float) -> SolverResult:
    """Run ``main_input`` in ``run_dir`` (output in ``<log stem>.out``); SolverRunError if it failed."""
    command = [*solver_command(run_config, np, main_input), "-log", log]
    result = run_solver(command, run_dir, f"{Path(log).stem}.out", timeout_s=timeout_s)
    if result.failure:
        raise SolverRunError(
            f"{result.failure} (running {main_input} on {np} rank(s))",
            run_dir=run_dir,
            log_tail=text_tail(result.output_file, 20),
        )
    return result


def _measure(name: str, run_config, np: int, run_dir: Path, main_input: str, log: str, timeout_s: float) -> Measurement:
    load = os.getloadavg()[0]
    result = _solve(run_config, np, run_dir, main_input, log, timeout_s)
    load_after = os.getloadavg()[0]
    text = result.output
    runs = parse_runs(text)
    last = runs[-1] if runs else None
    if last is None or last.loop.seconds <= 0 or last.loop.steps <= 0:
        raise SolverRunError(
            f"no plausible 'Loop time' line in the output of {main_input} ({last.loop if last else 'none'})",
            run_dir=run_dir,
        )
    atoms = last.column("Atoms") or [float(last.loop.atoms)]
    mean_atoms = sum(atoms) / len(atoms)
    rate = mean_atoms * last.loop.steps / last.loop.seconds
    n_warn = sum(1 for line in text.splitlines() if line.lstrip().startswith("WARNING"))
    details = loop_details(text)
    sections = ", ".join(f"{k} {v / last.loop.seconds:.0%}" for k, v in details.get("sections_s", {}).items())
    print(
        f"  {name:<26} np={np}  {last.loop.steps} steps, {mean_atoms:.0f} particles, loop {last.loop.seconds:.2f} s "
        f"(wall {result.wall_s:.1f} s, CPU {result.cpu_s:.1f} s, load {load:.2f}->{load_after:.2f}): "
        f"{rate:.3g} particle-steps/s"
        + (
            f"\n{'':31}loop: {sections}; {details.get('neighbour_builds', 0):.0f} neighbour-list builds"
            if sections
            else ""
        ),
        flush=True,
    )
    return Measurement(
        name,
        np,
        last.loop.steps,
        last.loop.seconds,
        mean_atoms,
        last.loop.atoms,
        rate,
        result.cpu_s,
        result.wall_s,
        load,
        load_after,
        n_warn,
        str(run_dir),
        details,
    )


def _with_numerics(config, **numerics):
    data = config.to_dict()
    data["dem"]["numerics"].update({k: v for k, v in numerics.items() if k != "duration_s"})
    if "duration_s" in numerics:
        data["dem"]["operation"]["duration_s"] = numerics["duration_s"]
    return config_from_dict(data, source="benchmark configuration")


def _step_of(path: Path) -> int:
    return int(re.findall(r"\d+", path.name)[-1])


def fill(config, work: Path, fill_s: float, np: int, timeout_s: float) -> tuple[Path, int, float, Measurement]:
    """Run the blender from empty for ``fill_s`` s on ``np`` ranks; return (restart file, its
    step, Atoms at the end, the run's measurement)."""
    dem = config.dem
    fill_config = _with_numerics(
        config, duration_s=fill_s, restart_interval_s=fill_s, dump_interval_s=min(dem.tables.window_s, fill_s)
    )
    run_dir = work / f"fill_np{np}"
    deck.write_deck(deck.build_deck(fill_config.dem), run_dir)
    print(f"  fill: {fill_s:g} s simulated from empty on {np} rank(s) in {run_dir} ...", flush=True)
    m = _measure(f"fill {fill_s:g} s", dem.run, np, run_dir, deck.MAIN_DECK, "log.fill.liggghts", timeout_s)
    restarts = sorted(run_dir.glob(deck.RESTART_GLOB), key=_step_of)
    if not restarts:
        raise SolverRunError("the fill run wrote no restart file", run_dir=run_dir)
    step = _step_of(restarts[-1])
    print(f"  fill: done in {m.wall_s:.0f} s wall; {m.atoms_end} particles held at step {step}", flush=True)
    return restarts[-1], step, m.atoms_end, m


def _blender_dir(config, work: Path, name: str, restart: Path, restart_step: int, steps: int, variant) -> Path:
    """Run directory of the resume deck from ``restart`` for ``steps`` steps, its text edited
    by ``variant`` (None: as built)."""
    measure_config = _with_numerics(config, duration_s=(restart_step + steps) * config.dem.timestep_s)
    local = f"restart/{restart.name}"
    files = deck.build_deck(measure_config.dem, resume_from=local)
    if variant is not None:
        files[deck.RESUME_DECK] = variant(files[deck.RESUME_DECK])
    run_dir = work / name
    deck.write_deck(files, run_dir)
    shutil.copy2(restart, run_dir / local)
    return run_dir


# --------------------------------------------------------------------------------------
# statistics of the repeats
# --------------------------------------------------------------------------------------


def _spread(values: list[float]) -> float | None:
    """(max - min) / median; None for a single value (no scatter to tell)."""
    return (max(values) - min(values)) / statistics.median(values) if len(values) > 1 else None


def summarise(runs: list[Measurement]) -> dict:
    """Medians and spreads of one run's repeats, with the load range they ran under."""
    rates, loops, cpus = ([getattr(m, k) for m in runs] for k in ("particle_steps_per_s", "loop_s", "cpu_s"))
    loads = [x for m in runs for x in (m.load_before, m.load_after)]
    return {
        "repeats": len(runs),
        "particle_steps_per_s": statistics.median(rates),
        "rate_spread": _spread(rates),
        "loop_s": statistics.median(loops),
        "loop_spread": _spread(loops),
        "cpu_s": statistics.median(cpus),
        "cpu_spread": _spread(cpus),
        "atoms_mean": statistics.median([m.atoms_mean for m in runs]),
        "load_min": min(loads),
        "load_max": max(loads),
    }


def cost(base: list[float], variant: list[float]) -> dict:
    """What switching a thing off saves: (median base - median variant) / median base, with
    the spread max(range of base, range of variant) / median base (None with one repeat)
    and whether the cost is within it."""
    mb = statistics.median(base)
    value = (mb - statistics.median(variant)) / mb
    spread = max(max(base) - min(base), max(variant) - min(variant)) / mb if min(len(base), len(variant)) > 1 else None
    return {"cost": value, "spread": spread, "within_scatter": None if spread is None else abs(value) < spread}


def _liggghts_running() -> list[str]:
    try:
        out = subprocess.run(["pgrep", "-af", "liggghts"], capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.TimeoutExpired):
        return []
    return [line for line in out.splitlines() if line.strip()]


def paper_core_hours(
    rate_serial: float,
    speedup_np2: float | None,
    holdup_smoke: float,
    smoke_config,
    reference_rate_serial: float | None = None,
) -> dict:
    """Core-hours of the ``paper`` preset on 2, 8 and 32 cores from the measured rate.

    ``core_hours`` uses the blender's measured particle-steps per second as is (the cost
    per particle-step of the smoke deck, conservative). ``core_hours_overhead_amortised``
    (with ``reference_rate_serial``, the drum's) splits the smoke blender's step into the
    drum's cost per particle plus a per-step overhead (impeller mesh, insertion, discharge,
    dumps) taken as independent of the particle count, which a 27x larger bed amortises: a
    lower estimate."""
    from workflows.shipped import reference_holdup

    paper = load_preset("paper").dem
    scale = (smoke_config.dem.particles.diameter_m / paper.particles.diameter_m) ** 3
    scaled = holdup_smoke * scale
    holdup, source = (
        scaled,
        (
            f"measured smoke hold-up {holdup_smoke:.0f} x "
            f"({smoke_config.dem.particles.diameter_m * 1e3:g}/{paper.particles.diameter_m * 1e3:g})^3"
        ),
    )
    reference = None
    try:
        # the hold-up `pbmdem dem slurm` uses: a shipped reference run, scaled by solid volume
        reference = reference_holdup(paper)
        holdup, source = reference
    except LookupError:  # no shipped reference run: keep the scaled measurement
        pass
    eff2 = min(1.0, speedup_np2 / 2) if speedup_np2 else 0.85
    why2 = "measured 2-rank speed-up / 2" if speedup_np2 else "assumed (estimate_cost default)"
    amortised_rate = None
    if reference_rate_serial and reference_rate_serial > 0:
        overhead_s_per_step = max(0.0, holdup_smoke * (1 / rate_serial - 1 / reference_rate_serial))
        amortised_rate = holdup / (holdup / reference_rate_serial + overhead_s_per_step)
    out = {
        "holdup_particles": holdup,
        "holdup_source": source,
        "holdup_scaled_from_smoke": scaled,
        "holdup_from_reference": reference[0] if reference else None,
        "particle_steps_per_core_s": rate_serial,
        "throughput_assumption": "particle-steps/s independent of particle size (measured on the smoke deck, 6 mm)",
        "paper_reported_core_hours": PAPER_CORE_HOURS,
        "cores": {},
    }
    out["particle_steps_per_core_s_overhead_amortised"] = amortised_rate
    for cores, eff, why in (
        (2, eff2, why2),
        (8, 0.85, "assumed (estimate_cost default)"),
        (32, 0.85, "assumed (estimate_cost default)"),
    ):
        est = estimate_cost(paper, holdup, rate_serial, cores, eff)
        out["steps"] = est.steps
        out["cores"][str(cores)] = {
            "core_hours": est.core_hours,
            "wall_hours": est.wall_hours,
            "parallel_efficiency": eff,
            "efficiency_source": why,
            "vs_paper": est.core_hours / PAPER_CORE_HOURS,
        }
        if reference:
            out["cores"][str(cores)]["core_hours_smoke_scaled_holdup"] = estimate_cost(
                paper, scaled, rate_serial, cores, eff
            ).core_hours
        if amortised_rate:
            low = estimate_cost(paper, holdup, amortised_rate, cores, eff)
            out["cores"][str(cores)]["core_hours_overhead_amortised"] = low.core_hours
            out["cores"][str(cores)]["wall_hours_overhead_amortised"] = low.wall_hours
    return out


def _plan(nps: list[int], variants: list[str]) -> list[tuple[str, int, str | None]]:
    """One repeat's runs in order: (kind, ranks, variant name or None). Every variant on 1
    rank, the blender, the multi-rank variants and the drum on every rank count."""
    plan = []
    for np in nps:
        plan.append(("blender", np, None))
        plan += [("blender", np, v) for v in variants if np == 1 or v in MULTI_RANK_VARIANTS]
        plan.append(("drum", np, None))
    return plan


def _key(kind: str, np: int, variant: str | None) -> str:
    return f"{kind}{'' if variant is None else '_' + variant}_np{np}"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The command line's options of this benchmark."""
    parser.add_argument("--preset", default="smoke", help="blender preset to measure (default smoke)")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="PATH=VALUE",
        help="change one value of the preset, e.g. dem.geometry.inlet_margin_m=0.005 (repeatable)",
    )
    parser.add_argument("--steps", type=int, default=20000, help="measured steps per run (default 20000)")
    parser.add_argument(
        "--fill-s",
        type=float,
        default=25.0,
        help="simulated seconds of filling before measuring (default 25: smoke's hold-up is near steady)",
    )
    parser.add_argument(
        "--fill-np",
        type=int,
        default=None,
        help="ranks of the fill whose restart the measured runs start from (default: the preset's)",
    )
    parser.add_argument("--nps", default="1,2", help="rank counts to measure (default 1,2)")
    parser.add_argument("--repeats", type=int, default=3, help="interleaved repeats of every run (default 3)")
    parser.add_argument(
        "--variants",
        default=",".join(VARIANTS),
        help=f"per-fix variants to measure, comma-separated (default all: {','.join(VARIANTS)})",
    )
    parser.add_argument("--out-file", default=str(OUT))
    parser.add_argument("--work", default=None, help="keep the run directories here (default: a temporary directory)")
    parser.add_argument("--timeout", type=float, default=3600.0, help="per LIGGGHTS run [s]")


def measure_all(config, args: argparse.Namespace, nps: list[int], variants: list[str], fill_np: int):
    """Fill the blender on every rank count, then every run of :func:`_plan`, interleaved
    and repeated. Returns the measurements per run key, the fills per rank count, the
    drum's particle count, and the restart step and hold-up the measured runs start from."""
    run_config = config.dem.run
    results: dict[str, list[Measurement]] = {}
    fills: dict[int, Measurement] = {}
    with tempfile.TemporaryDirectory(prefix="bench_dem_deck_") as tmp:
        work = Path(args.work) if args.work else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for np in dict.fromkeys([fill_np, *nps]):
            restart_np, step_np, held_np, fills[np] = fill(config, work, args.fill_s, np, args.timeout)
            if np == fill_np:
                restart, restart_step, held_fill = restart_np, step_np, held_np
        plan = _plan(nps, variants)
        dirs: dict[str, Path] = {}
        for kind, np, variant in plan:
            if kind == "blender":
                key = _key(kind, np, variant)
                dirs[key] = _blender_dir(
                    config, work, key, restart, restart_step, args.steps, None if variant is None else VARIANTS[variant]
                )
        particles = None
        for r in range(args.repeats):
            print(f" repeat {r + 1}/{args.repeats}", flush=True)
            for kind, np, variant in plan:
                key = _key(kind, np, variant)
                if kind == "blender":
                    m = _measure(key, run_config, np, dirs[key], deck.RESUME_DECK, deck.RESUME_LOG_FILE, args.timeout)
                    if particles is None:  # the first blender run sets the drum's particle count
                        particles = round(m.atoms_mean)
                else:
                    if key not in dirs:
                        dirs[key] = deck.write_deck(deck.build_drum_deck(config.dem, particles, args.steps), work / key)
                    m = _measure(key, run_config, np, dirs[key], deck.DRUM_DECK, deck.DRUM_LOG_FILE, args.timeout)
                    if m.atoms_end != particles:
                        raise SolverRunError(
                            f"the drum holds {m.atoms_end} particles, not {particles}: insertion fell "
                            "short or particles escaped",
                            run_dir=dirs[key],
                        )
                results.setdefault(key, []).append(m)
    return results, fills, particles, restart_step, held_fill


def variant_costs(results: dict[str, list[Measurement]], summary: dict, nps: list[int], variants: list[str]) -> dict:
    """Per variant run: what switching the fix off saves against the blender, ± the spread."""

    def rate(key: str) -> float | None:
        return summary[key]["particle_steps_per_s"] if key in summary else None

    costs: dict = {}
    for kind, np, variant in _plan(nps, variants):
        if variant is None:
            continue
        base, var = results[_key("blender", np, None)], results[_key(kind, np, variant)]
        entry = {
            "np": np,
            "loop": cost([m.loop_s for m in base], [m.loop_s for m in var]),
            "cpu": cost([m.cpu_s for m in base], [m.cpu_s for m in var]),
            "atoms_mean": summary[_key(kind, np, variant)]["atoms_mean"],
            "atoms_mean_blender": summary[_key("blender", np, None)]["atoms_mean"],
            "load_min": min(summary[_key(k, np, v)]["load_min"] for k, v in ((kind, None), (kind, variant))),
            "load_max": max(summary[_key(k, np, v)]["load_max"] for k, v in ((kind, None), (kind, variant))),
        }
        if variant in COUNT_CHANGING:
            entry["cost_per_particle_step"] = 1 - rate(_key("blender", np, None)) / rate(_key(kind, np, variant))
        costs[_key(kind, np, variant)] = entry
    return costs


def parse_plan(args: argparse.Namespace):
    """The preset with every ``--set`` applied, the rank counts, the variants and the fill's
    ranks; ConfigError naming a bad value and what would be valid."""
    config = load_preset(args.preset)
    for assignment in args.set:
        config = override(config, assignment)
    nps = [int(n) for n in args.nps.split(",") if n.strip()]
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ConfigError(f"--variants: unknown {unknown}; known: {', '.join(VARIANTS)}")
    if args.repeats < 1 or args.steps < 1 or not nps or min(nps) < 1:
        raise ConfigError(f"--repeats {args.repeats}, --steps {args.steps}, --nps {args.nps}: all must be >= 1")
    return config, nps, variants, args.fill_np or config.dem.run.np


def warn_if_loaded() -> tuple[tuple[float, float, float], list[str]]:
    """The load average before the runs and the LIGGGHTS processes already running; a
    warning on stderr when the load would slow the timings down."""
    load_before = os.getloadavg()
    others = _liggghts_running()
    if load_before[0] > LOAD_WARN:
        msg = (
            f"machine load {load_before[0]:.2f} > {LOAD_WARN} before starting: the timings will be slowed down "
            f"by other jobs" + (f" ({len(others)} LIGGGHTS processes running)" if others else "")
        )
        print(f"WARNING: {msg}", file=sys.stderr, flush=True)
    return load_before, others


def _rate(summary: dict, key: str) -> float | None:
    """The particle-steps per second of the runs ``key`` (:func:`summarise`), None when none ran."""
    return summary[key]["particle_steps_per_s"] if key in summary else None


def rank_rates(summary: dict, fills: dict[int, Measurement], nps: list[int]) -> dict:
    """Per rank count: the particle-steps per second of every kind of run, the blender's
    efficiency against the drum and the speed-ups over one rank (None where a run is
    missing)."""

    def rate(key: str) -> float | None:
        return _rate(summary, key)

    def ratio(a: float | None, b: float | None) -> float | None:
        return a / b if a and b else None

    record: dict = {}
    for np in nps:
        tag = "serial" if np == 1 else f"np{np}"
        for kind in ("blender", "blender_nodump", "drum"):
            record[f"{kind}_particle_steps_per_s_{tag}"] = rate(f"{kind}_np{np}")
        record[f"efficiency_{tag}"] = ratio(rate(f"blender_np{np}"), rate(f"drum_np{np}"))
        record[f"efficiency_nodump_{tag}"] = ratio(rate(f"blender_nodump_np{np}"), rate(f"drum_np{np}"))
        if np != 1:
            for kind in ("blender", "blender_nodump", "drum"):
                record[f"speedup_np{np}_{kind}"] = ratio(rate(f"{kind}_np{np}"), rate(f"{kind}_np1"))
            if 1 in fills and np in fills:
                record[f"speedup_np{np}_whole_run"] = fills[1].loop_s / fills[np].loop_s
                record[f"speedup_np{np}_whole_run_wall"] = fills[1].wall_s / fills[np].wall_s
    return record


def run(args: argparse.Namespace) -> int:
    config, nps, variants, fill_np = parse_plan(args)
    version = liggghts_version(config.dem.run.liggghts)
    load_before, others = warn_if_loaded()
    print(
        f"DEM deck benchmark: preset {args.preset}, {args.steps} steps, ranks {nps}, {args.repeats} repeats, "
        f"variants {variants}, LIGGGHTS {version}",
        flush=True,
    )

    t_start = time.monotonic()
    results, fills, particles, restart_step, held_fill = measure_all(config, args, nps, variants, fill_np)
    load_after = os.getloadavg()

    summary = {key: summarise(runs) for key, runs in results.items()}
    record: dict = {
        "preset": args.preset,
        "liggghts_version": version,
        "steps": args.steps,
        "repeats": args.repeats,
        "particles": particles,
        "fill_s": args.fill_s,
        "fill_np": fill_np,
        "fill_particles_held": held_fill,
        "restart_step": restart_step,
        "timestep_s": config.dem.timestep_s,
        "dumps": "blender_* runs: the deck's dumps at their normal interval "
        f"({config.dem.numerics.dump_interval_s} s); blender_nodump_*: no dump command; drum: no dumps",
        "efficiency_reference": "drum",
        "drum": {
            "froude": deck.DRUM_FROUDE,
            "wall_speed_m_s": deck.drum_wall_speed_m_s(config.dem),
            "radius_m": config.dem.geometry.radius_m,
            "length_m": config.dem.geometry.length_m,
        },
        "rates": "medians over the repeats of mean Atoms x steps / Loop time",
    }
    record.update(rank_rates(summary, fills, nps))
    costs = variant_costs(results, summary, nps, variants)
    record["variant_costs"] = costs
    for np in nps:
        nodump = costs.get(_key("blender", np, "nodump"))
        record[f"dump_overhead_{'serial' if np == 1 else f'np{np}'}"] = nodump["loop"]["cost"] if nodump else None
    record["targets"] = dict(TARGETS)
    if _rate(summary, "blender_np1"):
        record["paper_core_hours"] = paper_core_hours(
            _rate(summary, "blender_np1"),
            record.get("speedup_np2_blender"),
            summary["blender_np1"]["atoms_mean"],
            config,
            _rate(summary, "drum_np1"),
        )
    record["summary"] = summary
    record["fills"] = {f"np{np}": asdict(m) for np, m in fills.items()}
    record["runs"] = {k: [asdict(m) for m in v] for k, v in results.items()}
    record["machine_load"] = {
        "before": list(load_before),
        "after": list(load_after),
        "cpus": os.cpu_count(),
        "other_liggghts_before": others,
    }
    record["machine"] = {
        "node": platform.node(),
        "python": platform.python_version(),
        "processor": platform.processor(),
    }
    record["wall_s"] = time.monotonic() - t_start

    out = write_json(args.out_file, record)
    print_table(record, nps)
    print(f"wrote {out}")
    return 0


def _fmt(x, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _spread_text(spread: float | None) -> str:
    return "" if spread is None else f" ({spread:.0%})"


def _load(lo: float, hi: float) -> str:
    return f"load {lo:.1f}-{hi:.1f}"


def _cost_text(c: dict) -> str:
    if c["spread"] is None:
        return f"{c['cost']:+.1%} (1 repeat: scatter unknown)"
    return f"{c['cost']:+.1%} ± {c['spread']:.1%}" + (" within scatter" if c["within_scatter"] else "")


def print_table(record: dict, nps: list[int]) -> None:
    summary, targets = record["summary"], record["targets"]
    print(
        f"\n{record['particles']} particles, {record['steps']} steps, median of {record['repeats']} repeat(s) "
        "(spread (max - min) / median); particle-steps per second (Loop time):"
    )
    print(f"{'ranks':>6} {'blender':>16} {'drum':>16} {'eff.':>6}  target")
    for np in nps:
        tag = "serial" if np == 1 else f"np{np}"
        b, d = summary[f"blender_np{np}"], summary[f"drum_np{np}"]
        print(
            f"{np:>6} {_fmt(b['particle_steps_per_s'], '9.3g')}{_spread_text(b['rate_spread']):>7} "
            f"{_fmt(d['particle_steps_per_s'], '9.3g')}{_spread_text(d['rate_spread']):>7} "
            f"{_fmt(record.get(f'efficiency_{tag}'), '6.0%')}  "
            + (f">= {targets['efficiency_min']:.0%}" if np == 1 else "(none)  ")
            + f"  {_load(min(b['load_min'], d['load_min']), max(b['load_max'], d['load_max']))}"
        )
    for np in nps:
        if np == 1 or "blender_np1" not in summary:
            continue
        lo = min(summary[k]["load_min"] for k in ("blender_np1", f"blender_np{np}"))
        hi = max(summary[k]["load_max"] for k in ("blender_np1", f"blender_np{np}"))
        print(
            f"speed-up {np} ranks at steady state: blender {_fmt(record.get(f'speedup_np{np}_blender'), '.2f')}x "
            f"(target >= {targets['speedup_np2_min']}x), drum {_fmt(record.get(f'speedup_np{np}_drum'), '.2f')}x  "
            f"{_load(lo, hi)}"
        )
        whole = record.get(f"speedup_np{np}_whole_run")
        if whole:
            f1, fn = record["fills"]["np1"], record["fills"][f"np{np}"]
            print(
                f"speed-up {np} ranks, whole smoke run, filling included ({record['fill_s']:g} s from empty, one run "
                f"each): {whole:.2f}x (target >= {targets['speedup_np2_whole_run_min']}x; loop {f1['loop_s']:.4g} s "
                f"vs {fn['loop_s']:.4g} s)  "
                f"{_load(min(f1['load_before'], fn['load_before']), max(f1['load_after'], fn['load_after']))}"
            )
    costs = record["variant_costs"]
    for np in nps:
        c = costs.get(f"blender_nodump_np{np}")
        if c:
            print(
                f"dump overhead, {np} rank(s): {_cost_text(c['loop'])} of the Loop time, {_cost_text(c['cpu'])} of "
                f"the CPU time (target <= {targets['dump_overhead_max']:.0%})  {_load(c['load_min'], c['load_max'])}"
            )
    if costs:
        print("\nper-fix profile: time saved by switching it off, (blender - variant) / blender, ± the spread:")
        print(f"{'variant':<30} {'particles':>9} {'Loop time':>30} {'CPU time':>30}")
        for key, c in costs.items():
            per = c.get("cost_per_particle_step")
            print(
                f"{key:<30} {c['atoms_mean']:>9.0f} {_cost_text(c['loop']):>30} {_cost_text(c['cpu']):>30}  "
                f"{_load(c['load_min'], c['load_max'])}"
                + (
                    f"\n{'':31}(blender {c['atoms_mean_blender']:.0f} particles; per particle-step {per:+.1%})"
                    if per is not None
                    else ""
                )
            )
    cost_hours = record.get("paper_core_hours")
    if cost_hours:
        print(
            f"\npaper preset: {cost_hours['steps']} steps x {cost_hours['holdup_particles']:.0f} particles "
            f"({cost_hours['holdup_source']})"
        )
        for cores, est in cost_hours["cores"].items():
            low = est.get("core_hours_overhead_amortised")
            print(
                f"  {cores:>3} cores: {est['core_hours']:7.0f} core-hours ({est['wall_hours']:.1f} h wall"
                + (f"; {low:.0f} if the blender's per-step overhead is amortised" if low else "")
                + f"), parallel efficiency {est['parallel_efficiency']:.2f} {est['efficiency_source']}"
            )
        print(f"  the paper: {cost_hours['paper_reported_core_hours']:.0f} core-hours (6.5 days on 8 workers)")
    load = record["machine_load"]
    print(f"load average before {load['before'][0]:.2f}, after {load['after'][0]:.2f} on {load['cpus']} CPUs")
