"""The data that ships with the repository, in one place: which files they are, and the
two numbers the product reads from them (a shipped run's hold-up to scale a cluster job
from, the paper-scale probe's measured throughput).

The folder ``workflows/reference/`` holds DEM results made with this code, so that a fresh
clone reproduces the comparison, the validation campaign and the design example without
running LIGGGHTS:

* :data:`REDUCED_RUN`: the ``reduced`` preset's run (NX = 10), the default input of every
  study run on DEM results, and the other ``dem-*.h5`` beside it (the same run binned at
  NX = 20, for the grid sensitivity);
* :data:`VALIDATION_DIR`: the validation campaign's runs, also runs of the library below;
* :data:`STEP_DIR`: the feed-step run of the dynamic check;
* :data:`UNSEEN_DIR`: runs at operating points outside the campaign, each with its
  20-slice twin and its configuration (``200rpm-x1.25.toml``: 200 rpm, the feed x1.25;
  ``300rpm-mono-a30.toml``: 300 rpm, particles of one size, feeder A 30 % of 60 /s), the
  runs ``pbmdem library suggest`` chose (``suggested-*.toml``) and campaign points run with
  another seed (``replicate-*.toml``): the phase model and the library's law judged on runs
  they were not built on, not part of the library;
* :data:`PAPER_SCALE_DIR`: the paper-scale probe's summary, thermo rows and throughput;
* :data:`LIBRARY_DIR`: DEM runs at further speeds, lengths and seeds, and in ``law/`` the
  law fitted to them and the campaign (:data:`LIBRARY_MODEL`, ``pbmdem predict``'s and
  ``pbmdem design``'s).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

from coupling.cache import try_load_entry
from coupling.errors import ConfigError, error_line
from dem.config import DemConfig
from dem.summary import DemSummary
from workflows.config import config_from_dict

REFERENCE_DIR = Path(__file__).resolve().parent / "reference"
REDUCED_RUN = REFERENCE_DIR / "dem-17ea4c9cc143cd3e.h5"
VALIDATION_DIR = REFERENCE_DIR / "validation"
STEP_DIR = REFERENCE_DIR / "step"
UNSEEN_DIR = REFERENCE_DIR / "unseen"
PAPER_SCALE_DIR = REFERENCE_DIR / "paper_scale"
#: DEM runs beyond the campaign, at more speeds, lengths and seeds
LIBRARY_DIR = REFERENCE_DIR / "library"
#: the law fitted to the campaign and the library together, with its laws left out and
#: its calibration (``pbmdem library fit``): what ``pbmdem predict`` runs on
LIBRARY_MODEL = LIBRARY_DIR / "law" / "library.json"
#: every folder of shipped DEM results, where the DEM stage looks for a run's results
SHIPPED_RESULTS_DIRS = (REFERENCE_DIR, VALIDATION_DIR, STEP_DIR, UNSEEN_DIR)
PAPER_SCALE_SUMMARY = PAPER_SCALE_DIR / "summary.json"
PAPER_SCALE_THERMO = PAPER_SCALE_DIR / "thermo.csv"


def library_runs() -> list[str]:
    """The results files of the shipped DEM library: the validation campaign's and the
    library's beside it."""
    return [str(p) for folder in (VALIDATION_DIR, LIBRARY_DIR) for p in sorted(folder.glob("dem-*.h5"))]


def _same_vessel(reference: DemConfig, other: DemConfig) -> bool:
    """Whether ``other`` is ``reference``'s vessel: neither the blade clearance nor the
    empty box upstream of the inlet changes it."""
    keep = {
        "blade_tip_clearance_m": reference.geometry.blade_tip_clearance_m,
        "inlet_margin_m": reference.geometry.inlet_margin_m,
    }
    return reference.geometry == other.geometry.model_copy(update=keep)


def reference_holdup(dem_config: DemConfig, directory: Path = REFERENCE_DIR) -> tuple[float, str]:
    """Steady hold-up for ``dem_config`` scaled by solid volume from a shipped DEM run of
    the same blender: the same vessel holds the same powder volume, so the number of
    particles goes as (d_ref / d)^3. Raises LookupError when no shipped run fits."""
    for path in sorted(directory.glob("dem-*.h5")):
        entry, _ = try_load_entry(path)
        if entry is None:
            continue
        ref = config_from_dict(tomllib.loads(entry.provenance["config_toml"])).dem
        if not _same_vessel(ref, dem_config):
            continue
        held = float(DemSummary.from_record(entry.summary).holdup_final)
        scale = (ref.particles.diameter_m / dem_config.particles.diameter_m) ** 3
        return (
            held * scale,
            f"{held:.0f} particles of {ref.particles.diameter_m * 1000:g} mm in {path.name}, x {scale:.3g}",
        )
    raise LookupError("no shipped reference run of the same blender to scale the hold-up from; pass --holdup")


def measured_throughput(
    dem_config: DemConfig, summary_file: Path = PAPER_SCALE_SUMMARY
) -> tuple[float, str, int] | None:
    """The paper-scale probe's per-core throughput when ``dem_config`` uses the probe's
    particles (same diameter and spread) in the same vessel, with a line naming its source
    and the number of ranks it was measured on; else None."""
    if not summary_file.is_file():
        return None
    try:
        summary = json.loads(summary_file.read_text())
        probe = config_from_dict(tomllib.loads(summary["config_toml"])).dem
        rate = float(summary["throughput"]["late_particle_steps_per_s_per_core"])
    except (OSError, ValueError, KeyError, TypeError, ConfigError) as exc:
        raise ConfigError(f"{summary_file}: unreadable paper-scale measurement ({error_line(exc)})") from None
    if probe.particles != dem_config.particles or not _same_vessel(probe, dem_config):
        return None
    t = summary["throughput"]
    return (
        rate,
        (
            f"measured at paper scale ({summary_file.name}: {summary['np']} ranks, "
            f"{t['late_particles_mean']:.0f} particles held, {summary['simulated_s']:.0f} s simulated)"
        ),
        int(summary["np"]),
    )
