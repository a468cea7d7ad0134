"""DEM results files and the PBM configuration they describe.

* :func:`load_results` -- a cache or shipped results file whole, with its configuration.
* :func:`load_table` -- only its velocity table, summary and configuration, checked
  against the file's head digest (:func:`coupling.cache.load_head`): a reader of the
  tables alone does not read the per-particle records.
* :func:`pbm_config_for` / :func:`rtd_pulse` -- the PBM configuration and tracer pulse of
  the process a DEM run describes.
* :func:`pbm_inputs` -- a results file's table and the PBM configuration of its own run,
  in the validated rate mode: a PBM from a DEM run without typing what the file holds.

Every table read here records its operating point (:class:`coupling.operating.OperatingPoint`):
as stored, or, for a file written before tables recorded it, from the configuration
stored with it (:func:`with_operating_point`).

Kept apart from :mod:`workflows.pipeline.stages` so that reading a results file does not
import the DEM run, the post-processing and the figures.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from coupling.cache import CacheEntry, CacheHead, load_entry, load_head
from coupling.operating import OperatingPoint
from coupling.tables import VelocityTable
from dem.operating import operating_point
from dem.summary import DemSummary
from pbm.config import PbmConfig
from pbm.feed import feed_at
from workflows.config import Config, config_from_dict, load_preset

if TYPE_CHECKING:
    from dem.post import DemResults


def load_results(path: str | Path) -> tuple[DemResults, Config]:
    """The DEM results in a cache or shipped results file, with the configuration they were
    made with (:func:`config_of`). A missing or corrupt file raises CacheError naming it."""
    from dem.post import DemResults  # the post-processing's imports: not needed for the table alone

    entry = with_operating_point(load_entry(path))
    return DemResults.from_cache_entry(entry), config_of(entry)


def load_table(path: str | Path) -> tuple[VelocityTable, DemSummary, Config]:
    """The velocity table, summary and configuration of a cache or shipped results file,
    without its per-particle records (:func:`coupling.cache.load_head`: checked against the
    file's head digest, the rest of the file not read): what a reader of the tables alone
    needs, at a fraction of :func:`load_results`' time. The summary is as stored;
    :func:`load_results` recomputes intervals an earlier version made."""
    head = with_operating_point(load_head(path))
    return head.table, DemSummary.from_record(head.summary), config_of(head)


Stored = TypeVar("Stored", CacheEntry, CacheHead)


def with_operating_point(entry: Stored) -> Stored:
    """``entry`` (a cache entry or head) whose table records its operating point: as
    stored, else (a file written before tables recorded it) the one of the configuration
    stored with it (:func:`config_of`)."""
    if entry.table.operating_point is not None:
        return entry
    point = operating_point(config_of(entry).dem)
    return dataclasses.replace(entry, table=entry.table.replace(operating_point=point))


def config_of(entry) -> Config:
    """The configuration a cached or shipped DEM results entry was made with (stored with
    it), else the reduced preset, from which the shipped reference was made."""
    text = entry.provenance.get("config_toml")
    if not text:
        return load_preset("reduced")
    return config_from_dict(tomllib.loads(text), "the configuration stored with the DEM results")


def table_with_operating_point(table: VelocityTable) -> VelocityTable:
    """``table`` recording its operating point: as stored, else from the configuration in
    its own provenance (``config_toml``, which DEM tables carry); unchanged when it has
    neither (a synthetic table)."""
    text = table.attrs.get("config_toml")
    if table.operating_point is not None or not isinstance(text, str) or not text:
        return table
    config = config_from_dict(tomllib.loads(text), "the configuration stored with the velocity table")
    return table.replace(operating_point=operating_point(config.dem))


def run_operating_point(table: VelocityTable, config: Config) -> OperatingPoint:
    """The operating point of the DEM run of ``config`` whose table is ``table``: as the
    table records it, else (a table made without it) the configuration's."""
    return table.operating_point if table.operating_point is not None else operating_point(config.dem)


def rtd_pulse(dem_summary: DemSummary) -> float | None:
    """The PBM's tracer pulse time: the DEM's RTD tagging time, None when it tagged none."""
    tag_time = dem_summary.rtd_tag_time_s
    return float(tag_time) if tag_time is not None and math.isfinite(tag_time) else None


def pbm_config_for(config: Config, table: VelocityTable, rtd_pulse_s: float | None) -> PbmConfig:
    """The PBM configuration that describes the process of the DEM run ``config`` on
    ``table``'s compartments: that run's operating point's feed rates (whatever
    ``config.pbm`` states), each feeder's zone mapped onto the compartments by overlap in x
    and y (:func:`pbm.feed.feed_at`). ``table`` may be another run's (a prediction of this
    one): the feed is this run's."""
    return config.pbm.model_copy(
        update={**feed_at(operating_point(config.dem), table.x_edges, table.y_edges), "rtd_pulse_s": rtd_pulse_s}
    )


#: The rate mode the validation campaign judges best (the hidden phases: inside the DEM's
#: intervals on the reduced run, ``workflows/reference/FINDINGS.md``), used by :func:`pbm_inputs`.
VALIDATED_RATES = "phases"


def pbm_inputs(path: str | Path, rates: str = VALIDATED_RATES) -> tuple[VelocityTable, PbmConfig]:
    """The velocity table of the DEM results file ``path`` and the PBM configuration of its
    own run in the rate mode ``rates`` (default the validated one): the feed from the
    table's operating point, the tracer pulse at the DEM's RTD tagging time, the rest from
    the configuration stored with the file. Raises CacheError naming an unreadable file."""
    table, summary, config = load_table(path)
    pbm = config.pbm.model_copy(
        update={
            "feed_rate_a_per_s": None,
            "feed_rate_b_per_s": None,
            "feed_weights_a": None,
            "feed_weights_b": None,
            "rtd_pulse_s": rtd_pulse(summary),
            "rates": rates,
        }
    )
    return table, pbm
