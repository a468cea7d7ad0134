"""DEM results files and the PBM configuration they describe.

* :func:`load_results` -- a cache or shipped results file whole, with its configuration.
* :func:`load_table` -- only its velocity table, summary and configuration, checked
  against the file's head digest (:func:`coupling.cache.load_head`): a reader of the
  tables alone (the design inversion) does not read the per-particle records.
* :func:`pbm_config_for` / :func:`rtd_pulse` -- the PBM configuration and tracer pulse of
  the process a DEM run describes.

Kept apart from :mod:`workflows.pipeline.stages` so that reading a results file does not
import the DEM run, the post-processing and the figures.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING

from coupling.cache import load_entry, load_head
from coupling.compartments import feed_zone_weights
from coupling.tables import VelocityTable
from dem.geometry import feed_zones
from dem.summary import DemSummary
from pbm.config import PbmConfig
from workflows.config import Config, config_from_dict, load_preset

if TYPE_CHECKING:
    from dem.post import DemResults


def load_results(path: str | Path) -> tuple[DemResults, Config]:
    """The DEM results in a cache or shipped results file, with the configuration they were
    made with (:func:`config_of`). A missing or corrupt file raises CacheError naming it."""
    from dem.post import DemResults  # the post-processing's imports: not needed for the table alone

    entry = load_entry(path)
    return DemResults.from_cache_entry(entry), config_of(entry)


def load_table(path: str | Path) -> tuple[VelocityTable, DemSummary, Config]:
    """The velocity table, summary and configuration of a cache or shipped results file,
    without its per-particle records (:func:`coupling.cache.load_head`: checked against the
    file's head digest, the rest of the file not read): what a reader of the tables alone
    needs, at a fraction of :func:`load_results`' time. The summary is as stored;
    :func:`load_results` recomputes intervals an earlier version made."""
    head = load_head(path)
    return head.table, DemSummary.from_record(head.summary), config_of(head)


def config_of(entry) -> Config:
    """The configuration a cached or shipped DEM results entry was made with (stored with
    it), else the reduced preset, from which the shipped reference was made."""
    text = entry.provenance.get("config_toml")
    if not text:
        return load_preset("reduced")
    return config_from_dict(tomllib.loads(text), "the configuration stored with the DEM results")


def rtd_pulse(dem_summary: DemSummary) -> float | None:
    """The PBM's tracer pulse time: the DEM's RTD tagging time, None when it tagged none."""
    tag_time = dem_summary.rtd_tag_time_s
    return float(tag_time) if tag_time is not None and math.isfinite(tag_time) else None


def pbm_config_for(config: Config, table: VelocityTable, rtd_pulse_s: float | None) -> PbmConfig:
    """The PBM configuration that describes the same process as the DEM run: the DEM's
    feed rates, each feeder's zone mapped onto the compartments by overlap in x and y."""
    zones = feed_zones(config.dem.geometry)
    operation = config.dem.operation
    return config.pbm.model_copy(
        update={
            "feed_rate_a_per_s": operation.feed_rate_a_per_s,
            "feed_rate_b_per_s": operation.feed_rate_b_per_s,
            **{
                f"feed_weights_{name.lower()}": feed_zone_weights(
                    table.x_edges, table.y_edges, (zone.xmin, zone.xmax), (zone.ymin, zone.ymax)
                )
                for name, zone in zones.items()
            },
            "rtd_pulse_s": rtd_pulse_s,
        }
    )
