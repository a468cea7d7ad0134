"""LIGGGHTS 3.8.0 input decks for the continuous blender, as pure text.

:func:`build_deck` turns a :class:`~dem.config.DemConfig` into a dict *relative file name →
text*; :func:`write_deck` is the only function here that touches the disk. Nothing is
written unless the geometry and the deck validate (:class:`~coupling.errors.GeometryError`,
:class:`~coupling.errors.DeckError`). :func:`build_drum_deck` builds the yardstick of the
deck's efficiency, from the same section builders as the blender deck: the same particles
tumbling in the blender's barrel spun as a drum (a stirred bed, like the blender's; a still
box of them, the earlier yardstick, hardly ever rebuilt its neighbour lists).

This module is longer than the others: the section builders are private to it, shared by
the two decks, and every line of the blender deck's text feeds the input hash of shipped
reference runs, so the text is built in one place.

File layout of a run directory (relative to the directory ``liggghts -in in.blender`` runs
in; every name is a module constant, the runner and the post-processor use them):

=====================================  ===================================================
``in.blender`` (:data:`MAIN_DECK`)      main input deck (fresh start)
``in.resume`` (:data:`RESUME_DECK`)     only from ``build_deck(config, resume_from=...)``:
                                        continues from a restart file to the same end step;
                                        run it with ``-log log.resume.liggghts``
                                        (:data:`RESUME_LOG_FILE`); it appends to the
                                        massflow files and rewrites later dumps
``meshes/impeller.stl`` etc.           ASCII STL of the impeller (shaft + paddles), the weir
                                        and the discharge counting face (:data:`MESH_FILES`)
``deck.json`` (:data:`DECK_INFO`)      machine-readable facts of the deck: timestep, step
                                        intervals, end step, thermo columns, file names
``dumps/dump.<step>.txt``              one plain-text LIGGGHTS custom dump per snapshot
  (:data:`DUMP_GLOB`)                   (``ITEM: ATOMS id type x y z vx vy vz radius``),
                                        every ``dump_every_steps``; time = step × timestep
``restart/restart.<step>.bin``         binary restart files every ``restart_every_steps``
  (:data:`RESTART_GLOB`)
``discharge_A.txt``, ``discharge_B.txt``  ``fix massflow/mesh`` output, one line per
  (:data:`MASSFLOW_FILES`, globs in      discharged particle of that component: header
  :data:`MASSFLOW_GLOBS`)               ``# ID time  diameter x y z u v w  (ex ey ez,
                                        color)``, then ``id t[s] d[m] x y z vx vy vz``
                                        where t is the simulated time of the crossing
                                        (measured continuous across a resume). A resume
                                        appends a second header line; records above it
                                        with t after the restart's time belong to the
                                        abandoned run and must be dropped.
                                        With ``mpirun -np N`` each rank writes its own file
                                        with suffix ``.0`` ... ``.N-1`` (measured); the
                                        union is the discharge record. Verified: every
                                        discharged ID appears once; totals equal the
                                        thermo ``outA``/``outB`` columns.
``log.liggghts`` (:data:`LOG_FILE`)    LIGGGHTS' log (``-log`` default name)
=====================================  ===================================================

Thermo lines carry :data:`THERMO_COLUMNS` (the header LIGGGHTS prints, in order). Simulated
time is ``v_simtime = step * dt``, not LIGGGHTS' ``time`` keyword, because ``time`` restarts
at 0 after ``read_restart`` while steps (and so dump names) continue.

Resuming (measured on LIGGGHTS 3.8.0 from a discharging smoke state): particles, steps,
the impeller's angle and the insertion counters ``insA``/``insB`` are restored exactly;
the massflow counters ``outA``/``outB`` restart at 0 (the appended massflow files keep the
whole record), and so does LIGGGHTS' ``time`` (hence ``simtime``).

Lost particles: ``thermo_modify lost ignore``, because with ``delete_atoms`` LIGGGHTS 3.8.0
printed a spurious "Lost atoms: original N current N" warning (measured). Check the balance
from the thermo columns instead: ``insA + insB - outA - outB - Atoms`` is 0 (or briefly
negative, between a count and the deletion); positive means particles were lost. (In a
resumed run add the discharges recorded before the restart.)

Discharge: ``fix massflow/mesh ... count once delete_atoms yes`` deletes a particle at the
re-neighbouring after its centre crosses ``x = L + discharge_offset_m``, so a dump can
still show a few particles with ``x > L``: they have left the blender (the post-processor
should bin only ``0 <= x <= L``).

Atom types: 1 = component A, 2 = component B, 3 = steel (barrel, inlet wall, weir,
impeller). Particle IDs are never renumbered (no ``reset_timestep``, no ``compress_tags``),
so an ID identifies one particle across dumps and the discharge files.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from pathlib import Path

import numpy as np
from scipy.optimize import brentq

from coupling.cache import stable_hash
from coupling.errors import DeckError, OutputError, os_reason
from dem.config import MAX_STABLE_RAYLEIGH_FRACTION, DemConfig
from dem.geometry import Box, build_geometry, simulation_box, stl_text

#: Largest step count LIGGGHTS takes: ``run N upto`` runs N minus the current step, and
#: every ``every`` of dump, thermo, restart and insertion, as a C int (LAMMPS' MAXSMALLINT,
#: "Invalid run command N value"); a deck beyond it is refused when written, not by the
#: solver on a cluster node.
MAX_STEPS = 2**31 - 1

MAIN_DECK = "in.blender"
RESUME_DECK = "in.resume"
DECK_INFO = "deck.json"
LOG_FILE = "log.liggghts"
#: Log of a resumed run: pass ``-log log.resume.liggghts`` (LIGGGHTS truncates its log file at
#: start-up, before reading the deck, so the resume must not reuse LOG_FILE).
RESUME_LOG_FILE = "log.resume.liggghts"
MESH_DIR = "meshes"
MESH_FILES = {name: f"{MESH_DIR}/{name}.stl" for name in ("impeller", "weir", "discharge")}
DUMP_DIR = "dumps"
DUMP_PATTERN = "dumps/dump.*.txt"  # as given to LIGGGHTS' dump command
DUMP_GLOB = "dumps/dump.*.txt"


def dump_step(path: Path) -> int:
    """The step of a dump file of :data:`DUMP_PATTERN`, from its name (LIGGGHTS puts the
    step where the pattern has its ``*``): what was written before a solver line is known
    without opening a file that may still be being written."""
    return int(Path(path).name.split(".")[1])


DUMP_COLUMNS = ("id", "type", "x", "y", "z", "vx", "vy", "vz", "radius")
RESTART_DIR = "restart"
RESTART_PATTERN = "restart/restart.*.bin"
RESTART_GLOB = "restart/restart.*.bin"
MASSFLOW_FILES = {"A": "discharge_A.txt", "B": "discharge_B.txt"}
#: Every discharge file of a component, relative to the run directory: the file, its per-rank
#: files (``.0``, ``.1``... under MPI) and the ``.upto<step>`` records kept by a resume.
MASSFLOW_GLOBS = {"A": "discharge_A.txt*", "B": "discharge_B.txt*"}
MASSFLOW_COLUMNS = ("id", "time", "diameter", "x", "y", "z", "vx", "vy", "vz")
#: directories LIGGGHTS needs to exist before it starts (it does not create them)
RUN_DIRS = (DUMP_DIR, RESTART_DIR)
ATOM_TYPES = {"A": 1, "B": 2, "steel": 3}

#: Columns of the thermo lines, exactly as LIGGGHTS prints the header (it drops the ``v_``
#: prefix and truncates long names, so every column is an equal-style variable with a short
#: name; the timestep check is read directly, ``f_ts[k]``, because a variable would demand it be
#: computed on every thermo step, including the run's last): step, simulated time [s], particles in the box, particles inserted so far by feeder
#: A and B, particles discharged so far (counted and deleted past the weir) of A and of B, and
#: the timestep as a fraction of the Rayleigh and of the Hertz time (check/timestep/gran).
THERMO_COLUMNS = ("Step", "simtime", "Atoms", "insA", "insB", "outA", "outB", "ts[1]", "ts[2]")
THERMO_MEANING = {
    "Step": "timestep number",
    "simtime": "simulated time [s] (= step * dt, continuous across restarts)",
    "Atoms": "particles in the simulation",
    "insA": "particles of A inserted so far",
    "insB": "particles of B inserted so far",
    "outA": "particles of A discharged over the weir so far (since the start of this run: a resumed run restarts it at 0)",
    "outB": "particles of B discharged over the weir so far (since the start of this run: a resumed run restarts it at 0)",
    "ts[1]": "timestep / Rayleigh time (fix check/timestep/gran 'ts')",
    "ts[2]": "timestep / Hertz time (fix check/timestep/gran 'ts')",
}
#: Thermo columns whose sum is the solver's own count of discharged / inserted particles.
THERMO_DISCHARGED = ("outA", "outB")
THERMO_INSERTED = ("insA", "insB")
#: LIGGGHTS expression behind each variable column.
_THERMO_VARIABLES = {
    "insA": "f_insA[1]",
    "insB": "f_insB[1]",
    "outA": "f_outA[2]",
    "outB": "f_outB[2]",
}
#: The fix of a feed step's second feeder of A (its count is added to the ``insA`` column).
STEP_FEEDER = "insA2"
#: Warn (check/timestep/gran) above this fraction of the Hertz time.
HERTZ_WARN_FRACTION = 0.2
FEED_VELOCITY_M_S = 0.5  # downward speed given to inserted particles
FEED_BATCH_S = 0.05  # the feeders insert a batch every this much simulated time
#: The rotating drum (:func:`build_drum_deck`): its deck, its log, how often it is topped up
#: while it fills, and its Froude number Fr = omega^2 R / g. 0.5 is the cascading regime: a
#: stirred bed that neither rests nor centrifuges (Fr >= 1; the impeller's tip speed would
#: centrifuge it).
DRUM_DECK = "in.drum"
DRUM_LOG_FILE = "log.drum.liggghts"
DRUM_FILL_BATCH_S = 0.1
DRUM_FROUDE = 0.5
GRAVITY_M_S2 = 9.81


# --------------------------------------------------------------------------------------
# particle size distribution
# --------------------------------------------------------------------------------------


def size_classes(mean_m: float, sd_m: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Discretise a normal diameter distribution into ``n`` classes.

    Returns ``(diameters_m, number_weights)`` whose number-weighted mean and SD equal
    ``mean_m`` and ``sd_m`` exactly (to rounding). For n <= 5 the classes are the
    Gauss-Hermite nodes (exact for all moments up to 2n-1, all within 3 SD); for more
    classes they are evenly spaced over +-3 SD with normal weights exponentially tilted so
    that the variance is exact. One class (diameter = mean) when ``sd_m == 0`` or n == 1.
    """
    if n < 1:
        raise DeckError(f"size_classes = {n}: must be >= 1")
    if sd_m == 0 or n == 1:
        return np.array([mean_m]), np.array([1.0])
    if n <= 5:
        z, w = np.polynomial.hermite_e.hermegauss(n)
        w = w / w.sum()
    else:
        z = np.linspace(-3.0, 3.0, n)

        def excess_var(beta: float) -> float:
            w = np.exp(-0.5 * z**2 + beta * z**2)
            w /= w.sum()
            return float(np.sum(w * z**2) - 1.0)

        beta = brentq(excess_var, -20.0, 0.5)
        w = np.exp(-0.5 * z**2 + beta * z**2)
        w = w / w.sum()
    return mean_m + sd_m * z, w


def _format_weights(w: np.ndarray) -> list[str]:
    """Weights as text summing to exactly 1 (LIGGGHTS checks the sum)."""
    text = [f"{x:.8f}" for x in w[:-1]]
    last = 1.0 - sum(float(t) for t in text)
    return text + [f"{last:.8f}"]


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _primes_from(seed: int, count: int) -> list[int]:
    """``count`` distinct primes >= seed (LIGGGHTS wants a prime > 10000 per random fix)."""
    out, n = [], seed
    while len(out) < count:
        if n > 10000 and all(n % k for k in range(2, math.isqrt(n) + 1)):
            out.append(n)
        n += 1
    return out


def _g(x: float) -> str:
    """Compact, reproducible number text."""
    return f"{x:.10g}"


def _steps(interval_s: float, dt: float, what: str) -> int:
    n = round(interval_s / dt)
    if n < 1:
        raise DeckError(f"{what} = {interval_s} s is shorter than the timestep {dt:.4g} s")
    return _within_steps(n, interval_s, dt, what)


def _within_steps(n: int, interval_s: float, dt: float, what: str) -> int:
    """``n`` steps (of ``interval_s`` at timestep ``dt``) if LIGGGHTS can take them."""
    if n > MAX_STEPS:
        raise DeckError(
            f"{what} = {interval_s:.6g} s is {n:.4g} steps of {dt:.4g} s; LIGGGHTS takes at most {MAX_STEPS} "
            f"steps ({MAX_STEPS * dt:.6g} s at this timestep)"
        )
    return n


def deck_parameters(config: DemConfig) -> dict:
    """Derived numbers of the deck (timestep, step intervals, end step...), JSON-ready."""
    n = config.numerics
    dt = config.timestep_s
    if dt / config.rayleigh_time_s > MAX_STABLE_RAYLEIGH_FRACTION * (1 + 1e-9):
        raise DeckError(
            f"timestep {dt:.4g} s is {dt / config.rayleigh_time_s:.3f} of the Rayleigh time; the measured stable "
            f"limit is {MAX_STABLE_RAYLEIGH_FRACTION}"
        )
    rpm = config.operation.impeller_rpm
    if not rpm > 0:
        raise DeckError(f"operation.impeller_rpm = {rpm}: must be > 0")
    for comp, rate in (("A", config.operation.feed_rate_a_per_s), ("B", config.operation.feed_rate_b_per_s)):
        if not rate > 0:
            raise DeckError(f"feed rate of {comp} = {rate} /s: must be > 0")
    c = config.contact
    if c.friction_particle_wall != c.friction_particle_blade:
        raise DeckError(
            f"contact.friction_particle_wall ({c.friction_particle_wall}) != friction_particle_blade "
            f"({c.friction_particle_blade}): the deck uses one steel atom type (3) for walls and blades, so they "
            "must be equal (Table 1: both 0.4)"
        )
    end_step = _within_steps(
        round(config.operation.duration_s / dt), config.operation.duration_s, dt, "operation.duration_s"
    )
    insert_every = max(1, round(FEED_BATCH_S / dt))
    step = {}
    if config.operation.step_time_s is not None:
        # half a batch after a batch of the first feeder, so that the two never insert on one step
        start = round(config.operation.step_time_s / dt) + insert_every // 2
        step = {
            "feed_step": {
                "start_step": start,
                "start_s": start * dt,
                "extra_rate_a_per_s": (config.operation.step_factor_a - 1) * config.operation.feed_rate_a_per_s,
            }
        }
    return {
        **step,
        "timestep_s": dt,
        "rayleigh_time_s": config.rayleigh_time_s,
        "timestep_rayleigh_fraction": dt / config.rayleigh_time_s,
        "dump_every_steps": _steps(n.dump_interval_s, dt, "numerics.dump_interval_s"),
        "thermo_every_steps": _steps(n.thermo_interval_s, dt, "numerics.thermo_interval_s"),
        "restart_every_steps": _steps(n.restart_interval_s, dt, "numerics.restart_interval_s"),
        "insert_every_steps": insert_every,
        "end_step": end_step,
        "impeller_period_s": 60.0 / rpm,
        "thermo_columns": list(THERMO_COLUMNS),
        "dump_columns": list(DUMP_COLUMNS),
        "dump_glob": DUMP_GLOB,
        "restart_glob": RESTART_GLOB,
        "massflow_files": dict(MASSFLOW_FILES),
        "massflow_globs": dict(MASSFLOW_GLOBS),
        "massflow_columns": list(MASSFLOW_COLUMNS),
        "length_m": config.geometry.length_m,
        "discharge_x_m": config.geometry.length_m + config.geometry.discharge_offset_m,
        "atom_types": dict(ATOM_TYPES),
    }


# --------------------------------------------------------------------------------------
# deck sections: lists of lines, shared by the blender deck and the drum
# --------------------------------------------------------------------------------------

_CONTACT_MODEL = "model hertz tangential history rolling_friction cdt"


def _box_args(b: Box) -> str:
    return " ".join(_g(v) for v in (b.xmin, b.xmax, b.ymin, b.ymax, b.zmin, b.zmax))


def _seeds(seed: int, n_classes: int) -> dict:
    """Random seeds of every fix, all distinct primes: one particle template per size class
    and component, then the distributions and the insertions of A and B, then the drum's
    distribution and insertion (drawn last so the blender's seeds do not depend on it), then
    the second feeder of A of a feed step."""
    n = n_classes
    primes = _primes_from(seed, 2 * n + 7)
    return {
        "templates": {"A": primes[:n], "B": primes[n : 2 * n]},
        "distribution": {"A": primes[2 * n], "B": primes[2 * n + 1]},
        "insertion": {"A": primes[2 * n + 2], "B": primes[2 * n + 3]},
        "reference_distribution": primes[2 * n + 4],
        "reference_insertion": primes[2 * n + 5],
        "step_insertion": primes[2 * n + 6],
    }


def _resumed_step(resume_from: str | None) -> int:
    """The step of a restart file named ``.../restart.<step>.bin`` (0 for a fresh start)."""
    if resume_from is None:
        return 0
    digits = re.findall(r"\d+", Path(resume_from).name)
    if not digits:
        raise DeckError(f"resume_from = {resume_from!r}: a restart file name carries its step (restart.<step>.bin)")
    return int(digits[-1])


def _setup_lines(domain: Box) -> list[str]:
    return [
        "atom_style      granular",
        "atom_modify     map array",
        "boundary        f f f",
        "newton          off",
        "communicate     single vel yes",
        "units           si",
        "processors      * 1 1",
        "",
        f"region          domain block {_box_args(domain)} units box",
        "create_box      3 domain",
    ]


def _resume_setup_lines(resume_from: str) -> list[str]:
    return [
        f"# resume: state (particles, step, mesh positions, counters) from {resume_from}",
        "atom_modify     map array",
        "communicate     single vel yes",
        "processors      * 1 1",
        f"read_restart    {resume_from}",
        "newton          off",
    ]


def _neighbour_lines(config: DemConfig) -> list[str]:
    skin = 0.5 * config.particles.diameter_m
    return [f"neighbor        {_g(skin)} bin", "neigh_modify    delay 0", "hard_particles  yes"]


def _material_lines(config: DemConfig) -> list[str]:
    p, s, c = config.particles, config.steel, config.contact
    e_p, e_s = p.youngs_modulus_pa, s.youngs_modulus_pa
    mu = {
        (1, 1): c.friction_particle_particle,
        (1, 2): c.friction_particle_particle,
        (2, 2): c.friction_particle_particle,
        (1, 3): c.friction_particle_wall,
        (2, 3): c.friction_particle_wall,
        (3, 3): c.friction_particle_wall,
    }

    def pair_matrix(f) -> str:
        return " ".join(_g(f(min(i, j), max(i, j))) for i in (1, 2, 3) for j in (1, 2, 3))

    return [
        "# Table 1. E = 2 G (1 + nu): particles (types 1, 2) and steel (type 3)",
        f"fix m1 all property/global youngsModulus peratomtype {_g(e_p)} {_g(e_p)} {_g(e_s)}",
        f"fix m2 all property/global poissonsRatio peratomtype {_g(p.poisson_ratio)} {_g(p.poisson_ratio)} "
        f"{_g(s.poisson_ratio)}",
        f"fix m3 all property/global coefficientRestitution peratomtypepair 3 {pair_matrix(lambda i, j: c.restitution)}",
        f"fix m4 all property/global coefficientFriction peratomtypepair 3 {pair_matrix(lambda i, j: mu[(i, j)])}",
        f"fix m5 all property/global coefficientRollingFriction peratomtypepair 3 "
        f"{pair_matrix(lambda i, j: c.rolling_friction)}",
    ]


def _contact_lines(dt: float) -> list[str]:
    """Pair style, timestep and gravity."""
    return [
        f"pair_style      gran {_CONTACT_MODEL}",
        "pair_coeff      * *",
        f"timestep        {_g(dt)}",
        "fix gravi all gravity 9.81 vector 0.0 0.0 -1.0",
    ]


def _steel_wall(name: str, primitive: str) -> str:
    return f"fix {name} all wall/gran {_CONTACT_MODEL} primitive type {ATOM_TYPES['steel']} {primitive}"


def _template_lines(config: DemConfig, comp: str, diameters: np.ndarray, seeds: list[int]) -> list[str]:
    """One ``particletemplate/sphere`` per size class of component ``comp`` (``pt<comp><k>``)."""
    density = _g(config.particles.density_kg_m3)
    return [
        f"fix pt{comp}{k} all particletemplate/sphere {seeds[k]} atom_type {ATOM_TYPES[comp]} density constant "
        f"{density} radius constant {_g(d / 2)}"
        for k, d in enumerate(diameters)
    ]


def _distribution_line(name: str, seed: int, templates: list[str], weights: np.ndarray) -> str:
    parts = " ".join(f"{t} {w}" for t, w in zip(templates, _format_weights(weights)))
    return f"fix {name} all particledistribution/discrete/numberbased {seed} {len(templates)} {parts}"


def _integration_lines(thermo_every: int) -> list[str]:
    """Integration and the timestep check, run on every thermo step."""
    return [
        "fix integr all nve/sphere",
        f"fix ts all check/timestep/gran {thermo_every} {_g(MAX_STABLE_RAYLEIGH_FRACTION)} {_g(HERTZ_WARN_FRACTION)}",
    ]


def _thermo_lines(columns: str, every: int) -> list[str]:
    return [f"thermo_style    custom {columns}", f"thermo          {every}", "thermo_modify   lost ignore norm no"]


# --------------------------------------------------------------------------------------
# the blender deck
# --------------------------------------------------------------------------------------


def _deck_text(config: DemConfig, info: dict, resume_from: str | None, dumps: bool = True) -> str:
    geo = build_geometry(config)
    g, p, op = config.geometry, config.particles, config.operation
    dt = info["timestep_s"]
    diam, weights = size_classes(p.diameter_m, p.diameter_sd_m, p.size_classes)
    n_cls = len(diam)
    seeds = _seeds(config.numerics.seed, n_cls)

    L: list[str] = [
        "# pbmdem: LIGGGHTS 3.8.0 deck for a GCM250-style continuous blender (Sen et al. 2013).",
        "# Generated by dem.deck.build_deck; do not edit in place during a run.",
        f"# particles: d = {_g(p.diameter_m)} m (SD {_g(p.diameter_sd_m)} m, {n_cls} classes); feed "
        f"{_g(op.feed_rate_total_per_s)} /s (A share {_g(op.feed_fraction_a)}); {_g(op.impeller_rpm)} rpm; "
        f"{_g(op.duration_s)} s"
        + (f"; feeder A x{_g(op.step_factor_a)} from {_g(op.step_time_s)} s" if op.step_time_s is not None else ""),
        f"# atom types: 1 = A, 2 = B, 3 = steel. Thermo columns: {' '.join(THERMO_COLUMNS)}",
        "",
    ]
    add = L.append
    L += _setup_lines(geo.box) if resume_from is None else _resume_setup_lines(resume_from)
    L += ["", *_neighbour_lines(config), "", *_material_lines(config), "", *_contact_lines(dt), ""]
    add("# barrel and closed inlet end: primitives (faster than STL)")
    add(_steel_wall("barrel", f"xcylinder {_g(g.radius_m)} 0. 0."))
    add(_steel_wall("inletwall", "xplane 0.0"))
    add("# impeller (shaft + paddles) and weir: STL meshes; discharge face: counting only, no wall")
    add(f"fix impeller all mesh/surface file {MESH_FILES['impeller']} type 3")
    add(f"fix weir all mesh/surface file {MESH_FILES['weir']} type 3")
    add(f"fix walls all wall/gran {_CONTACT_MODEL} mesh n_meshes 2 meshes impeller weir")
    add(f"fix discharge all mesh/surface/planar file {MESH_FILES['discharge']} type 3")
    add(
        f"fix rotor all move/mesh mesh impeller rotate origin 0. 0. 0. axis 1. 0. 0. period {_g(info['impeller_period_s'])}"
    )
    add("")
    add(
        f"# size distribution: normal, d = {_g(p.diameter_m)} m, SD {_g(p.diameter_sd_m)} m, discretised into "
        f"{n_cls} number-weighted classes"
    )
    if resume_from is None:
        add("group           gA type 1")
        add("group           gB type 2")
    for comp in ("A", "B"):
        L += _template_lines(config, comp, diam, seeds["templates"][comp])
        add(
            _distribution_line(
                f"pdd{comp}", seeds["distribution"][comp], [f"pt{comp}{k}" for k in range(n_cls)], weights
            )
        )
    add("")
    add("# feeders: A on +y, B on -y, above the first compartment, upstream of the first blade")
    rates = {"A": op.feed_rate_a_per_s, "B": op.feed_rate_b_per_s}
    for comp in ("A", "B"):
        add(f"region          feed{comp} block {_box_args(geo.feed_zones[comp])} units box")
        add(
            f"fix ins{comp} g{comp} insert/rate/region seed {seeds['insertion'][comp]} distributiontemplate pdd{comp} "
            f"nparticles INF particlerate {_g(rates[comp])} insert_every {info['insert_every_steps']} "
            f"overlapcheck yes all_in yes vel constant 0. 0. {_g(-FEED_VELOCITY_M_S)} region feed{comp} ntry_mc 10000"
        )
    step = info.get("feed_step")
    if step:
        add(
            f"# feed step: a second feeder of A adds {_g(step['extra_rate_a_per_s'])} /s from step {step['start_step']}"
        )
        # 'start' must lie after the current step; a run resumed past it restores the fix's own state
        start = f" start {step['start_step']}" if _resumed_step(resume_from) < step["start_step"] else ""
        add(
            f"fix {STEP_FEEDER} gA insert/rate/region seed {seeds['step_insertion']} distributiontemplate pddA "
            f"nparticles INF particlerate {_g(step['extra_rate_a_per_s'])} insert_every {info['insert_every_steps']}"
            f"{start} overlapcheck yes all_in yes vel constant 0. 0. {_g(-FEED_VELOCITY_M_S)} region feedA "
            "ntry_mc 10000"
        )
    add("")
    add("# outlet: count and delete particles whose centre crosses the face past the weir, per component")
    for comp in ("A", "B"):
        # a resumed run appends: 'file' would truncate the discharges recorded before the restart
        mode = "file" if resume_from is None else "append"
        add(
            f"fix out{comp} g{comp} massflow/mesh mesh discharge vec_side 1. 0. 0. count once delete_atoms yes "
            f"{mode} {MASSFLOW_FILES[comp]} writeTime screen no"
        )
    L += ["", *_integration_lines(info["thermo_every_steps"]), ""]
    add("# output: simulated time from the step count (thermo 'time' restarts at 0 after read_restart)")
    add(f"variable        simtime equal step*{_g(dt)}")
    for name, expr in _THERMO_VARIABLES.items():
        if name == "insA" and step:
            expr = f"{expr}+f_{STEP_FEEDER}[1]"
        add(f"variable        {name} equal {expr}")
    cols = " ".join(
        c_.lower() if c_ in ("Step", "Atoms") else f"f_{c_}" if c_.startswith("ts[") else f"v_{c_}"
        for c_ in THERMO_COLUMNS
    )
    L += _thermo_lines(cols, info["thermo_every_steps"])
    if dumps:
        add(f"dump            dmp all custom {info['dump_every_steps']} {DUMP_PATTERN} {' '.join(DUMP_COLUMNS)}")
    add(f"restart         {info['restart_every_steps']} {RESTART_PATTERN}")
    add("")
    add(f"run             {info['end_step']} upto")
    return "\n".join(L) + "\n"


def build_deck(config: DemConfig, resume_from: str | None = None, dumps: bool = True) -> dict[str, str]:
    """All files of a run directory as ``{relative path: text}``; nothing is written.

    ``resume_from`` (a restart file path relative to the run directory, e.g.
    ``"restart/restart.250000.bin"``) adds :data:`RESUME_DECK`, which reads it, declares
    every fix again and runs on to the same end step (steps, and so dump names, continue).
    ``dumps=False`` leaves out the ``dump`` command: a run to measure what the dumps cost,
    from which nothing can be post-processed.
    Raises :class:`GeometryError` / :class:`DeckError` before anything exists.
    """
    info = deck_parameters(config)
    files = {MAIN_DECK: _deck_text(config, info, None, dumps)}
    if resume_from is not None:
        if not str(resume_from).strip() or any(ch.isspace() for ch in str(resume_from)):
            raise DeckError(f"resume_from = {resume_from!r}: must be a restart file path without spaces")
        files[RESUME_DECK] = _deck_text(config, info, str(resume_from), dumps)
    geo = build_geometry(config)
    for name, path in MESH_FILES.items():
        files[path] = stl_text(geo.meshes[name])
    files[DECK_INFO] = json.dumps(info, indent=2, sort_keys=True) + "\n"
    return files


# --------------------------------------------------------------------------------------
# the rotating drum: the blender's particles and contact physics, stirred, without the blender
# --------------------------------------------------------------------------------------


def drum_wall_speed_m_s(config: DemConfig) -> float:
    """Tangential speed of the drum's wall: V = sqrt(Fr g R) at Froude number :data:`DRUM_FROUDE`."""
    return math.sqrt(DRUM_FROUDE * GRAVITY_M_S2 * config.geometry.radius_m)


def build_drum_deck(config: DemConfig, particles: int, steps: int, fill_s: float = 1.0) -> dict[str, str]:
    """``{DRUM_DECK: text}``: ``particles`` particles in the blender's barrel spinning as a
    drum, then ``steps`` measured steps (the log's last ``Loop time``); nothing is written.

    The fair reference for the blender deck's efficiency: a stirred bed rebuilds its
    neighbour lists about as often as the blender's, a still one almost never. The same setup, neighbour settings, materials, pair style, timestep,
    gravity, particle templates, integration, timestep check and thermo interval as
    :func:`build_deck` (the same section builders), in the blender's own simulation box;
    the barrel is the blender's ``xcylinder`` primitive spinning about x (``shear y V``,
    V = :func:`drum_wall_speed_m_s`), closed by ``xplane`` primitives at 0 and L. No
    impeller, meshes, feeders, discharge or dumps. A and B are inserted through one
    number-weighted distribution, each class at half its own component's weight (the blender's feed at 50/50; A and B are the same material). ``fix insert/pack`` fills the whole barrel
    (so particles carried up by the wall stay counted) to ``particles`` for ``fill_s`` of
    tumbling, then ``unfix`` and the measured run. Raises :class:`DeckError`.
    """
    if particles < 1 or steps < 1:
        raise DeckError(f"drum deck: particles = {particles} and steps = {steps}; both must be >= 1")
    if not fill_s > 0:
        raise DeckError(f"drum deck: fill_s = {fill_s}: must be > 0")
    info = deck_parameters(config)
    dt, thermo_every = info["timestep_s"], info["thermo_every_steps"]
    p, g = config.particles, config.geometry
    diam, weights = size_classes(p.diameter_m, p.diameter_sd_m, p.size_classes)
    n_cls = len(diam)
    seeds = _seeds(config.numerics.seed, n_cls)
    speed = drum_wall_speed_m_s(config)
    templates = [f"pt{comp}{k}" for comp in ("A", "B") for k in range(n_cls)]
    fill_steps = max(1, round(fill_s / dt))

    L: list[str] = [
        "# pbmdem: rotating drum of the blender deck's particles (dem.deck.build_drum_deck).",
        f"# {particles} particles in the blender's barrel (R = {_g(g.radius_m)} m, L = {_g(g.length_m)} m) spinning "
        f"at Froude number {_g(DRUM_FROUDE)} (wall speed {_g(speed)} m/s), then {steps} measured steps "
        "(the last Loop time).",
        "",
        *_setup_lines(simulation_box(g)),
        "",
        *_neighbour_lines(config),
        "",
        *_material_lines(config),
        "",
        *_contact_lines(dt),
        "",
        "# the drum: the blender's barrel spinning about x (shear y = tangential wall speed), closed at both ends",
        _steel_wall("barrel", f"xcylinder {_g(g.radius_m)} 0. 0. shear y {_g(speed)}"),
        _steel_wall("inletwall", "xplane 0.0"),
        _steel_wall("outletwall", f"xplane {_g(g.length_m)}"),
        "",
        *_template_lines(config, "A", diam, seeds["templates"]["A"]),
        *_template_lines(config, "B", diam, seeds["templates"]["B"]),
        _distribution_line(
            "pdddrum", seeds["reference_distribution"], templates, np.concatenate([weights, weights]) / 2
        ),
        f"region          fill cylinder x 0 0 {_g(g.radius_m)} 0 {_g(g.length_m)} units box",
        f"fix ins all insert/pack seed {seeds['reference_insertion']} distributiontemplate pdddrum insert_every "
        f"{max(1, round(DRUM_FILL_BATCH_S / dt))} overlapcheck yes all_in yes particles_in_region {particles} "
        "region fill ntry_mc 10000",
        "",
        *_integration_lines(thermo_every),
        "",
        *_thermo_lines("step atoms ke", thermo_every),
        "",
        f"# fill: top the drum up to {particles} particles every {_g(DRUM_FILL_BATCH_S)} s while it turns, then stop inserting",
        f"run             {fill_steps}",
        "unfix           ins",
        "# measured",
        f"run             {steps}",
    ]
    return {DRUM_DECK: "\n".join(L) + "\n"}


def deck_hash(files: dict[str, str | bytes], liggghts_version: str = "") -> str:
    """Hash of every deck file's content (texts and meshes): the deck alone, or with
    ``liggghts_version`` the key of a run of it (:func:`dem.run.run_key`). Changes with any
    input that matters."""
    digests = {}
    for name, content in files.items():
        data = content.encode() if isinstance(content, str) else bytes(content)
        digests[name] = hashlib.sha256(data).hexdigest()
    return stable_hash({"files": digests, "liggghts_version": liggghts_version, "layout": 1}, length=16)


def write_deck(files: dict[str, str], out_dir: str | Path) -> Path:
    """Write the files (creating ``meshes/``, ``dumps/``, ``restart/``) under ``out_dir``.
    Raises OutputError naming the directory when the file system refuses."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        for d in RUN_DIRS:
            (out / d).mkdir(exist_ok=True)
        for name, text in files.items():
            path = out / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
    except OSError as exc:
        raise OutputError(f"cannot write the run directory {out}: {os_reason(exc)}") from exc
    return out
