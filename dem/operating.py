"""The operating point of a DEM configuration (:class:`coupling.operating.OperatingPoint`):
what every velocity table and results file made from it records."""

from __future__ import annotations

from coupling.operating import FeedZone, OperatingPoint
from dem.config import DemConfig
from dem.deck import size_classes
from dem.geometry import blade_stations, feed_zones


def operating_point(config: DemConfig) -> OperatingPoint:
    """The speed, feed rates (before any step), barrel, blade stations, particle size
    classes and feed zones that ``config`` runs LIGGGHTS at."""
    g, p, op = config.geometry, config.particles, config.operation
    diameters, weights = size_classes(p.diameter_m, p.diameter_sd_m, p.size_classes)
    return OperatingPoint(
        impeller_rpm=op.impeller_rpm,
        feed_rate_a_per_s=op.feed_rate_a_per_s,
        feed_rate_b_per_s=op.feed_rate_b_per_s,
        length_m=g.length_m,
        diameter_m=g.diameter_m,
        blade_x_m=tuple(station.x_m for station in blade_stations(g)),
        particle_diameter_m=p.diameter_m,
        particle_diameter_sd_m=p.diameter_sd_m,
        size_class_diameters_m=tuple(float(d) for d in diameters),
        size_class_weights=tuple(float(w) for w in weights),
        feed_zones={name: FeedZone(zone.xmin, zone.xmax, zone.ymin, zone.ymax) for name, zone in feed_zones(g).items()},
    )
