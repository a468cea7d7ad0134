"""Post-processing cost against DEM cost, from the DEM runs whose results are cached.

``python -m workflows.bench.reference [DIR ...]`` reads every ``dem-*.h5`` in the shipped
reference folder (and any cache folders given) and prints, per run, the LIGGGHTS wall time,
the post-processing time and their ratio (the issue's target: post-processing <= 5 % of
the DEM for ``reduced``). Both times are recorded by :func:`workflows.pipeline.stages.dem_stage`
when the run is made, so ``FRESH=1 make full-comparison`` measures them again.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from coupling.cache import try_load_entry
from coupling.jsonable import write_json
from dem.summary import DemSummary
from workflows.shipped import REFERENCE_DIR

OUT = Path("results/bench/reference.json")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The command line's options of this benchmark."""
    parser.add_argument(
        "folders",
        nargs="*",
        default=[str(REFERENCE_DIR)],
        help="folders of DEM results files (default: the shipped reference)",
    )
    parser.add_argument("--out-file", default=str(OUT))


def run(args: argparse.Namespace) -> int:
    folders = [Path(a) for a in args.folders]
    rows = []
    for folder in folders:
        for path in sorted(folder.glob("dem-*.h5")):
            entry, reason = try_load_entry(path)
            if entry is None:
                print(f"{path}: skipped ({reason})")
                continue
            prov = entry.provenance
            dem_s, post_s = prov.get("wall_time_s"), prov.get("postprocess_time_s")
            rows.append(
                {
                    "file": str(path),
                    "preset": prov.get("preset"),
                    "np": prov.get("np"),
                    "dem_wall_time_s": dem_s,
                    "postprocess_time_s": post_s,
                    "postprocess_fraction": post_s / dem_s if dem_s and post_s else None,
                    "holdup_final": DemSummary.from_record(entry.summary).holdup_final,
                    "made": prov.get("created"),
                }
            )
    print(f"{'preset':>8} {'ranks':>5} {'DEM [s]':>9} {'post [s]':>9} {'post/DEM':>9}  file")
    for r in rows:
        frac = f"{r['postprocess_fraction']:.2%}" if r["postprocess_fraction"] is not None else "-"
        print(
            f"{r['preset']:>8} {r['np']!s:>5} {r['dem_wall_time_s'] or 0:9.0f} {r['postprocess_time_s'] or 0:9.1f} {frac:>9}  {r['file']}"
        )
    print(f"wrote {write_json(args.out_file, rows)}")
    return 0
