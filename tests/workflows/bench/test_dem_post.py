"""``pbmdem bench dem-post`` end to end: on small synthetic dumps, and (marked
``liggghts``) on the real dumps of the session's smoke run; every snapshot is read and
post-processed, and the throughputs follow from the bytes and the times recorded."""

import json

import pytest

from dem.deck import DUMP_GLOB
from dem.run import prepare_run
from workflows.cli.main import main
from workflows.config import load_preset


def _check(record: dict, files: int) -> None:
    assert record["files"] == files and record["postprocess_snapshots"] == files
    for name in ("reader", "reader_1thread", "pandas"):
        assert record[f"{name}_MB_per_s"] == pytest.approx(record["bytes"] / record[f"{name}_best_s"] / 1e6)
    assert record["reader_over_pandas_speed"] == pytest.approx(record["pandas_best_s"] / record["reader_best_s"])
    assert record["postprocess_s"] > 0


def test_synthetic_dumps(tmp_path):
    out = tmp_path / "dem_post.json"
    argv = ["--particles", "2000", "--snapshots", "40", "--repeat", "1", "--out-file", str(out)]
    assert main(["bench", "dem-post", *argv]) == 0
    record = json.loads(out.read_text())
    _check(record, 40)
    # about 76 bytes per particle line, like LIGGGHTS' own dumps
    assert 60 < record["bytes"] / (2000 * 40) < 100


@pytest.mark.liggghts
def test_real_dumps_of_the_smoke_run(smoke_runs_root, tmp_path):
    run_dir = smoke_runs_root / prepare_run(load_preset("smoke").dem).key
    dumps = sorted(run_dir.glob(DUMP_GLOB))
    out = tmp_path / "dem_post.json"
    argv = ["--dumps", str(run_dir / DUMP_GLOB), "--preset", "smoke", "--repeat", "1", "--out-file", str(out)]
    assert main(["bench", "dem-post", *argv]) == 0
    record = json.loads(out.read_text())
    _check(record, len(dumps))
    assert record["bytes"] == sum(p.stat().st_size for p in dumps)
