"""Post-processing cost against DEM cost, from the DEM runs whose results are cached.

``python -m workflows.bench_reference [DIR ...]`` reads every ``dem-*.h5`` in the shipped
reference folder (and any cache folders given) and prints, per run, the LIGGGHTS wall time,
the post-processing time and their ratio (the issue's target: post-processing <= 5 % of
the DEM for ``reduced``). Both times are recorded by :func:`workflows.pipeline.dem_stage`
when the run is made, so ``FRESH=1 make full-comparison`` measures them again.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from coupling.cache import try_load_entry
from workflows.pipeline import REFERENCE_DIR

OUT = Path("results/bench/reference.json")


def main(argv: list[str] | None = None) -> int:
    folders = [Path(a) for a in (argv if argv is not None else sys.argv[1:])] or [REFERENCE_DIR]
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
                    "holdup_final": entry.summary.get("holdup_final"),
                    "made": prov.get("created"),
                }
            )
    print(f"{'preset':>8} {'ranks':>5} {'DEM [s]':>9} {'post [s]':>9} {'post/DEM':>9}  file")
    for r in rows:
        frac = f"{r['postprocess_fraction']:.2%}" if r["postprocess_fraction"] is not None else "-"
        print(f"{r['preset']:>8} {r['np']!s:>5} {r['dem_wall_time_s'] or 0:9.0f} {r['postprocess_time_s'] or 0:9.1f} {frac:>9}  {r['file']}")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
