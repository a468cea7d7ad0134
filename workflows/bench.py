"""``make bench``: every benchmark the issues ask for, each a module with ``main()``.

Results go to ``results/bench/*.json`` and a table on stdout. Timings are measured here,
never asserted in tests: the machines are shared and noisy.
"""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path
from typing import Any

BENCHMARKS = (
    ("PBM solver and ensembles", "workflows.bench_pbm"),
    ("DEM dump reader and post-processing", "workflows.bench_dem_post"),
    ("Transfer-rate estimators on a known chain", "workflows.bench_rates"),
    ("DEM deck efficiency and core-hours", "workflows.bench_dem_deck"),
    ("What two ranks can gain on this machine at all", "workflows.bench_machine"),
    ("A deck change against the seed-to-seed scatter", "workflows.bench_scatter"),
    ("Post-processing vs DEM wall time of the shipped runs", "workflows.bench_reference"),
)


def write_json(path: str | Path, record: Any) -> Path:
    """Write one benchmark's record as indented JSON (values JSON cannot hold as text),
    creating the folder; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=2, default=str) + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    wanted = set(argv if argv is not None else sys.argv[1:])
    failed = []
    for title, module_name in BENCHMARKS:
        if wanted and not any(w in module_name for w in wanted):
            continue
        print(f"\n=== {title} ({module_name}) ===", flush=True)
        try:
            importlib.import_module(module_name).main([])
        except Exception as exc:  # one broken benchmark must not hide the others' numbers
            print(f"FAILED: {type(exc).__name__}: {exc}", flush=True)
            failed.append(module_name)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
