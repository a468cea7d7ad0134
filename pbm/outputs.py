"""Files of one PBM run: ``timeseries.csv``, ``rtd.csv``, ``summary.json`` and figures."""

from __future__ import annotations

from pathlib import Path

from coupling.errors import OutputError, os_reason
from coupling.files import replace_file
from coupling.jsonable import write_json
from pbm.plots import save_figures
from pbm.simulate import PbmResult


def write_outputs(result: PbmResult, out_dir: str | Path, figures: bool = True) -> dict[str, Path]:
    """Write ``timeseries.csv``, ``rtd.csv``, ``summary.json`` and (if ``figures``) PNGs.

    CSVs: comma-separated, a header line, ``nan`` where a value is undefined (C_A before
    anything leaves, RSD with fewer than two occupied compartments). JSON: NaN -> null.
    Returns name -> path of every file written; raises OutputError naming the directory
    when the file system refuses.
    """
    out = Path(out_dir)
    paths = {"timeseries": out / "timeseries.csv", "rtd": out / "rtd.csv", "summary": out / "summary.json"}
    try:
        out.mkdir(parents=True, exist_ok=True)
        for name, frame in (("timeseries", result.timeseries()), ("rtd", result.rtd())):
            replace_file(paths[name], frame.to_csv(index=False, float_format="%.10g", na_rep="nan"), "PBM table")
        overrides = {"feed_overrides": [o.message for o in result.feed_overrides]} if result.feed_overrides else {}
        write_json(paths["summary"], {**result.summary.record(), **overrides})
        if figures:
            paths.update(save_figures(result, out))
    except OSError as exc:
        raise OutputError(f"cannot write the PBM outputs in {out}: {os_reason(exc)}") from exc
    return paths
