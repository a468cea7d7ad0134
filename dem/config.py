"""Typed, validated configuration of the DEM stage (geometry, materials, operation, numerics).

Every field carries its unit in its name. Models are frozen and refuse unknown keys, so a
typo in a TOML file is an error naming the key, not a silently ignored setting. Cross-field
checks that need geometry (blade clearance, feed zones clear of the blades) live in
:mod:`dem.geometry`, which refuses a bad blender before any file is written.
"""

from __future__ import annotations

import math
import shlex
import string

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator


def _is_prime(n: int) -> bool:
    if n < 2:
        return False
    return all(n % k for k in range(2, math.isqrt(n) + 1))


class _Section(BaseModel):
    # allow_inf_nan=False: an infinite feed rate or a NaN feed height would otherwise pass
    # every gt/ge bound (or none is given) and be written into the LIGGGHTS deck verbatim.
    # strict=True: no coercion. A boolean or a string where a number belongs (`np = true`,
    # `nx = "10"`, `duration_s = true`) and a float where an integer belongs (`nx = 1e9`)
    # are refused naming the key instead of being read as 1, 10 or 1000000000; an integer
    # is still a valid float.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)


class GeometryConfig(_Section):
    """A GCM250-style horizontal bladed blender. x axial from the inlet wall, z up.

    The impeller carries ``blade_stations`` stations evenly spaced from ``first_blade_x_m``
    to ``last_blade_x_m``; each station has ``blades_per_station`` flat paddles evenly spaced
    in azimuth, consecutive stations are turned by ``blade_azimuth_step_deg``, and the paddle
    faces are pitched by ``blade_pitch_deg`` from the axial direction, forward (F, conveying
    towards the outlet) or backward (B) following ``blade_pattern`` cyclically.

    Choices (Dubey et al.'s GCM250 drawing is not available, so these are stated, not copied):
    a 20 mm shaft; ten stations of two opposed 25 mm paddles pitched 45 deg, F/B alternating,
    turned 90 deg from station to station, from x = 45 mm (just downstream of the feed zones,
    which span x = 6-30 mm) to x = 300 mm; tips 5 mm from the wall (presets with coarser
    particles widen this to stay above the largest particle); a 20 mm weir at x = L. Powder
    is counted and removed at ``x = L + discharge_offset_m``; the simulation box extends
    ``outlet_length_m`` past the weir and ``box_margin_m`` around the barrel.
    See :mod:`dem.geometry` for how each surface is built and checked.
    """

    length_m: float = Field(
        0.330, gt=0, description="barrel length L from the inlet end wall (x = 0) to the weir plane (x = L)"
    )
    diameter_m: float = Field(
        0.100, gt=0, description="barrel inner diameter D; the impeller axis is the barrel's axis"
    )
    shaft_radius_m: float = Field(
        0.010, gt=0, description="impeller shaft radius; the paddles' roots sit inside it, at half this radius"
    )
    blade_stations: int = Field(
        10, ge=1, description="number of axial paddle stations, evenly spaced from first_blade_x_m to last_blade_x_m"
    )
    first_blade_x_m: float = Field(0.045, gt=0, description="axial position of the first paddle station's centre")
    last_blade_x_m: float = Field(
        0.300, gt=0, description="axial position of the last paddle station's centre; below length_m"
    )
    blades_per_station: int = Field(2, ge=1, le=8, description="flat paddles per station, evenly spaced in azimuth")
    blade_chord_m: float = Field(0.025, gt=0, description="paddle width along its pitched chord")
    blade_tip_clearance_m: float = Field(
        0.005,
        gt=0,
        description="gap between the paddles' outermost corners and the barrel wall; must exceed the largest "
        "particle (mean + 3 SD)",
    )
    blade_pitch_deg: float = Field(45.0, gt=0, lt=90, description="angle of the paddle faces from the axial direction")
    blade_azimuth_step_deg: float = Field(
        90.0, ge=0, lt=360, description="azimuthal turn of each station's paddles relative to the previous station"
    )
    blade_pattern: str = Field(
        "FB",
        pattern=r"^[FB]+$",
        description="paddle orientation per station, repeated cyclically from the inlet: F conveys towards the "
        "outlet, B back towards the inlet",
    )
    weir_height_m: float = Field(
        0.020, gt=0, description="weir crest height above the barrel bottom; powder leaves over it"
    )
    outlet_length_m: float = Field(0.020, gt=0, description="simulation box extent past the weir plane")
    discharge_offset_m: float = Field(
        0.002,
        gt=0,
        description="the discharge face (fix massflow/mesh: counts and deletes particles) this far past the "
        "weir plane; below outlet_length_m",
    )
    feed_x_min_m: float = Field(0.006, ge=0, description="upstream end of both feed zones along x")
    feed_x_max_m: float = Field(
        0.030, gt=0, description="downstream end of both feed zones along x; clear of the first paddles"
    )
    feed_y_inner_m: float = Field(
        0.005, ge=0, description="|y| of the feed zones' inner edge (A on +y, B mirrored on -y)"
    )
    feed_y_outer_m: float = Field(0.030, gt=0, description="|y| of the feed zones' outer edge; below the barrel radius")
    feed_height_m: float = Field(
        0.025, description="height z of the feed zones' centre above the impeller axis (z = 0)"
    )
    feed_depth_m: float = Field(0.012, gt=0, description="vertical extent of each feed zone")
    mesh_resolution_m: float = Field(
        0.04,
        gt=0,
        description="target triangle edge of curved and long surfaces (coarse: moving triangles cost time every step)",
    )
    box_margin_m: float = Field(
        0.005,
        gt=0,
        description="simulation box clearance around the barrel radius (and upstream, unless inlet_margin_m)",
    )
    inlet_margin_m: float | None = Field(
        None,
        gt=0,
        description="simulation box extent upstream of the inlet wall; None = box_margin_m. "
        "Under MPI the deck cuts the box along x into equal slabs: a longer margin moves the cut between 2 ranks "
        "toward the feed end, which holds most of the particles",
    )

    @model_validator(mode="after")
    def _check(self) -> GeometryConfig:
        radius = self.diameter_m / 2
        if self.shaft_radius_m + self.blade_tip_clearance_m >= radius:
            raise ValueError(
                f"shaft_radius_m ({self.shaft_radius_m}) + blade_tip_clearance_m ({self.blade_tip_clearance_m}) "
                f"must be below the vessel radius ({radius}) to leave room for blades"
            )
        if not self.first_blade_x_m <= self.last_blade_x_m < self.length_m:
            raise ValueError(
                f"blade stations must satisfy first_blade_x_m ({self.first_blade_x_m}) <= last_blade_x_m "
                f"({self.last_blade_x_m}) < length_m ({self.length_m})"
            )
        if self.blade_stations == 1 and self.first_blade_x_m != self.last_blade_x_m:
            raise ValueError("with blade_stations = 1, first_blade_x_m must equal last_blade_x_m")
        if self.weir_height_m >= self.diameter_m:
            raise ValueError(f"weir_height_m ({self.weir_height_m}) must be below diameter_m ({self.diameter_m})")
        if not self.feed_x_min_m < self.feed_x_max_m <= self.length_m:
            raise ValueError(
                f"feed zone must satisfy feed_x_min_m ({self.feed_x_min_m}) < feed_x_max_m ({self.feed_x_max_m}) "
                f"<= length_m ({self.length_m})"
            )
        if not self.feed_y_inner_m < self.feed_y_outer_m < radius:
            raise ValueError(
                f"feed zone must satisfy feed_y_inner_m ({self.feed_y_inner_m}) < feed_y_outer_m "
                f"({self.feed_y_outer_m}) < vessel radius ({radius})"
            )
        return self

    @property
    def radius_m(self) -> float:
        return self.diameter_m / 2

    @property
    def blade_tip_radius_m(self) -> float:
        return self.radius_m - self.blade_tip_clearance_m


class ParticleConfig(_Section):
    """Particles of both components (Table 1). The size distribution is normal in diameter,
    truncated at +-3 SD and discretised into ``size_classes`` LIGGGHTS templates."""

    diameter_m: float = Field(0.002, gt=0, description="mean particle diameter, both components (Table 1: 2 mm)")
    # The paper's text says SD = 5 % of the mean radius, i.e. 0.05 mm on the
    # radius and 0.1 mm on the diameter; Table 1's "0.2" has no unit and is not used.
    diameter_sd_m: float = Field(
        0.0001, ge=0, description="standard deviation of the normal diameter distribution, truncated at +-3 SD"
    )
    size_classes: int = Field(
        5, ge=1, le=15, description="diameters the distribution is discretised into (one LIGGGHTS template each)"
    )
    shear_modulus_pa: float = Field(
        2.0e6, gt=0, description="particle shear modulus G; the deck uses E = 2 G (1 + nu) (Table 1)"
    )
    poisson_ratio: float = Field(0.33, gt=-1, lt=0.5, description="particle Poisson's ratio nu (Table 1)")
    density_kg_m3: float = Field(1500.0, gt=0, description="particle material density (Table 1)")

    @model_validator(mode="after")
    def _check(self) -> ParticleConfig:
        if self.diameter_m - 3 * self.diameter_sd_m <= 0:
            raise ValueError(
                f"diameter_sd_m ({self.diameter_sd_m}) is too wide for diameter_m ({self.diameter_m}): "
                "the distribution truncated at 3 SD would include sizes <= 0"
            )
        return self

    @property
    def youngs_modulus_pa(self) -> float:
        return 2 * self.shear_modulus_pa * (1 + self.poisson_ratio)

    @property
    def max_diameter_m(self) -> float:
        return self.diameter_m + 3 * self.diameter_sd_m

    @property
    def min_diameter_m(self) -> float:
        return self.diameter_m - 3 * self.diameter_sd_m


class SteelConfig(_Section):
    """Walls and blades (Table 1)."""

    shear_modulus_pa: float = Field(
        7.93e10, gt=0, description="shear modulus G of walls and blades; the deck uses E = 2 G (1 + nu) (Table 1)"
    )
    poisson_ratio: float = Field(0.33, gt=-1, lt=0.5, description="steel Poisson's ratio nu (Table 1)")
    density_kg_m3: float = Field(
        8000.0,
        gt=0,
        description="steel density (Table 1); not written to the deck: walls and blades move as prescribed, "
        "never by contact",
    )

    @property
    def youngs_modulus_pa(self) -> float:
        return 2 * self.shear_modulus_pa * (1 + self.poisson_ratio)


class ContactConfig(_Section):
    """Hertz contact coefficients (Table 1)."""

    restitution: float = Field(
        0.1, gt=0, le=1, description="coefficient of restitution, every pair of particle, wall and blade (Table 1)"
    )
    friction_particle_particle: float = Field(
        0.5, ge=0, description="coefficient of static (sliding) friction between particles (Table 1)"
    )
    friction_particle_wall: float = Field(
        0.4, ge=0, description="coefficient of static friction particle-steel (walls, weir, and blades) (Table 1)"
    )
    friction_particle_blade: float = Field(
        0.4,
        ge=0,
        description="coefficient of static friction particle-blade (Table 1); the deck has one steel type for walls "
        "and blades, so it must equal friction_particle_wall",
    )
    rolling_friction: float = Field(
        0.01,
        ge=0,
        description="coefficient of rolling friction (constant directional torque model, cdt), every pair (Table 1)",
    )


class OperationConfig(_Section):
    """Operating point (paper section 3.1)."""

    feed_rate_total_per_s: float = Field(1990.0, gt=0, description="particles fed per second by both feeders together")
    feed_fraction_a: float = Field(0.5, gt=0, lt=1, description="share of the feed that is component A")
    impeller_rpm: float = Field(250.0, gt=0, description="impeller speed, revolutions per minute")
    duration_s: float = Field(260.0, gt=0, description="simulated time of the DEM run, from an empty blender")
    step_time_s: float | None = Field(
        None, gt=0, description="feeder A's rate is multiplied by step_factor_a from this time on (None: steady feed)"
    )
    step_factor_a: float = Field(
        1.0,
        gt=0,
        description="feeder A's rate factor from step_time_s on (a second feeder of A); > 1 with a step, else 1",
    )

    @model_validator(mode="after")
    def _step(self) -> OperationConfig:
        if self.step_time_s is None:
            if self.step_factor_a != 1.0:
                raise ValueError(f"step_factor_a = {self.step_factor_a} needs step_time_s (when the step happens)")
            return self
        if not self.step_factor_a > 1.0:
            raise ValueError(
                f"step_factor_a = {self.step_factor_a}: a feed step raises feeder A's rate (a second feeder of A "
                "starts at step_time_s), so it must be > 1"
            )
        if not self.step_time_s < self.duration_s:
            raise ValueError(
                f"step_time_s = {self.step_time_s} s must lie before the end, duration_s = {self.duration_s} s"
            )
        return self

    @property
    def feed_rate_a_per_s(self) -> float:
        """Feeder A's rate before any step."""
        return self.feed_rate_total_per_s * self.feed_fraction_a

    @property
    def feed_rate_b_per_s(self) -> float:
        return self.feed_rate_total_per_s * (1 - self.feed_fraction_a)


# Measured on LIGGGHTS 3.8.0 from a settled bed of 2 mm particles: dt = 0.27 t_Rayleigh was
# stable, 0.32 gave spurious speed spikes, 0.38 lost particles.
MAX_STABLE_RAYLEIGH_FRACTION = 0.27


class NumericsConfig(_Section):
    """Timestep, output intervals and random seed of the DEM run."""

    timestep_rayleigh_fraction: float = Field(
        0.2, gt=0, description="DEM timestep as a fraction of the smallest particle's Rayleigh time; at most 0.27"
    )
    dump_interval_s: float = Field(
        0.1, gt=0, description="simulated time between particle dumps (the post-processing's samples)"
    )
    thermo_interval_s: float = Field(
        0.5, gt=0, description="simulated time between thermo lines (counters) and timestep checks in the log"
    )
    restart_interval_s: float = Field(
        10.0, gt=0, description="simulated time between restart files (what an interrupted run resumes from)"
    )
    seed: int = Field(
        15485863,
        gt=10000,
        description="random seed of the DEM run, a prime > 10000 (LIGGGHTS requirement); the particle templates, "
        "size distributions and insertions take the primes from it on",
    )

    @model_validator(mode="after")
    def _check(self) -> NumericsConfig:
        if self.timestep_rayleigh_fraction > MAX_STABLE_RAYLEIGH_FRACTION:
            raise ValueError(
                f"timestep_rayleigh_fraction {self.timestep_rayleigh_fraction} is above the stable limit "
                f"{MAX_STABLE_RAYLEIGH_FRACTION} measured for LIGGGHTS 3.8.0 (0.32 gave speed spikes); "
                "choose a value in (0, 0.27]"
            )
        if not _is_prime(self.seed):
            raise ValueError(f"seed {self.seed} is not prime; LIGGGHTS needs a prime > 10000, e.g. 15485863")
        return self


class RunConfig(_Section):
    """How the solver is launched. ``launcher`` is a command prefix such as
    ``"mpirun -np {np}"`` or ``"srun"``; empty runs ``liggghts`` directly when np == 1."""

    np: int = Field(1, ge=1, description="MPI ranks of the LIGGGHTS run (the command line's --np overrides it)")
    launcher: str = Field(
        "mpirun --allow-run-as-root -np {np}",
        description="command prefix that starts LIGGGHTS; its only field is {np} (the ranks); an {np} template is "
        'skipped at np = 1, "" runs LIGGGHTS directly',
    )
    liggghts: str = Field("liggghts", description="LIGGGHTS command (name on PATH or path, with options)")

    @field_validator("launcher")
    @classmethod
    def _launcher_template(cls, launcher: str) -> str:
        """Checked when the configuration is loaded, not when a run starts: the only field is
        ``{np}``, braces balanced, quotes closed."""
        return check_launcher(launcher)

    @field_validator("liggghts")
    @classmethod
    def _liggghts_command(cls, liggghts: str) -> str:
        try:
            words = shlex.split(liggghts)
        except ValueError as exc:
            raise ValueError(f'is not a valid command line ({exc}); e.g. "liggghts"') from None
        if not words:
            raise ValueError('is empty; the LIGGGHTS command is needed, e.g. "liggghts" or "/opt/bin/lmp_auto"')
        return liggghts


#: The fields a launcher template may use.
LAUNCHER_FIELDS = ("np",)


def check_launcher(launcher: str) -> str:
    """``launcher`` if it is a valid template (e.g. ``"mpirun -np {np}"``, ``"srun"``, ``""``):
    only the field ``{np}`` (no conversion or format spec), balanced braces (``{{``/``}}`` for
    literal ones), and a command line that shlex can split once filled in. Raises
    ValueError saying what is wrong and what is valid."""
    valid = 'the only field is {np} (the number of MPI ranks), e.g. "mpirun -np {np}" or "srun"'
    try:
        parts = list(string.Formatter().parse(launcher))
    except ValueError as exc:
        raise ValueError(f"is not a valid template ({exc}); {valid}; write literal braces as {{{{ }}}}") from None
    for _, name, spec, conversion in parts:
        if name is None:
            continue
        if name not in LAUNCHER_FIELDS:
            raise ValueError(f"uses the unknown field {{{name}}}; {valid}")
        if spec or conversion:
            raise ValueError(
                f"field {{{name}{'!' + conversion if conversion else ''}{':' + spec if spec else ''}}} "
                f"has a conversion or format spec; write it as plain {{{name}}}"
            )
    try:
        shlex.split(launcher.format(np=1))
    except ValueError as exc:
        raise ValueError(f"is not a valid command line ({exc}); close every quote") from None
    return launcher


class TablesConfig(_Section):
    """Binning of the dumps into velocity tables and CQA sampling (``coupling/DEFINITIONS.md``)."""

    nx: int = Field(10, ge=1, description="axial compartments (slices of L/NX) of the velocity tables and the PBM")
    ny: int = Field(10, ge=1, description="compartments along y per slice (strips of D/NY, full height)")
    window_s: float = Field(
        5.0, gt=0, description="length of each velocity-table window (the paper updates velocities every 5 s)"
    )
    sample_interval_s: float = Field(
        1.0, gt=0, description="interval of the DEM's CQA time series (outflow, C_A, RSD, hold-up)"
    )
    min_samples: int = Field(
        5,
        ge=1,
        description="fewer particle-snapshots (or observed moves) than this leave a compartment-window without "
        "a velocity (or rate): marked missing, not read as zero",
    )
    rtd_tag_window_s: float = Field(
        1.0,
        gt=0,
        description="the particles fed during this window from the steady state on are tagged for the DEM's RTD",
    )


class DemConfig(_Section):
    """The DEM stage: blender, materials, operating point, numerics, launch and binning."""

    geometry: GeometryConfig = GeometryConfig()
    particles: ParticleConfig = ParticleConfig()
    steel: SteelConfig = SteelConfig()
    contact: ContactConfig = ContactConfig()
    operation: OperationConfig = OperationConfig()
    numerics: NumericsConfig = NumericsConfig()
    run: RunConfig = RunConfig()
    tables: TablesConfig = TablesConfig()

    @model_validator(mode="after")
    def _check(self) -> DemConfig:
        g, p = self.geometry, self.particles
        if g.blade_tip_clearance_m <= p.max_diameter_m:
            raise ValueError(
                f"geometry.blade_tip_clearance_m ({g.blade_tip_clearance_m}) must exceed the largest particle "
                f"diameter ({p.max_diameter_m:.4g} m = mean + 3 SD), or particles get pinched between blade and wall"
            )
        if self.numerics.dump_interval_s > self.tables.window_s:
            raise ValueError(
                f"numerics.dump_interval_s ({self.numerics.dump_interval_s}) must not exceed tables.window_s "
                f"({self.tables.window_s}): every velocity window needs dumps"
            )
        return self

    @property
    def rayleigh_time_s(self) -> float:
        """Rayleigh time of the smallest particle [s] (the stability scale of the timestep)."""
        p = self.particles
        radius = p.min_diameter_m / 2
        return math.pi * radius * math.sqrt(p.density_kg_m3 / p.shear_modulus_pa) / (0.1631 * p.poisson_ratio + 0.8766)

    @property
    def timestep_s(self) -> float:
        return self.numerics.timestep_rayleigh_fraction * self.rayleigh_time_s
