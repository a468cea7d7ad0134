"""``pbmdem bench reference`` end to end on the shipped runs: one row per results file,
the post-processing's share of the DEM's wall time computed from the two times recorded,
and a file that is not DEM results skipped with its reason, not a traceback."""

import json

import pytest

from workflows.cli.main import main
from workflows.shipped import REDUCED_RUN, REFERENCE_DIR


def test_shipped_runs(tmp_path, capsys):
    out = tmp_path / "reference.json"
    assert main(["bench", "reference", "--out-file", str(out)]) == 0
    rows = json.loads(out.read_text())
    assert [row["file"] for row in rows] == [str(p) for p in sorted(REFERENCE_DIR.glob("dem-*.h5"))]
    assert str(REDUCED_RUN) in {row["file"] for row in rows}
    for row in rows:
        assert row["preset"] == "reduced" and row["dem_wall_time_s"] > 0
        assert row["postprocess_fraction"] == pytest.approx(row["postprocess_time_s"] / row["dem_wall_time_s"])
        # the NX = 10 and NX = 20 binnings of one run: the same steady bed (about 2300 particles)
        assert 1000 < row["holdup_final"] < 5000
    assert len({row["holdup_final"] for row in rows}) == 1
    assert capsys.readouterr().out.splitlines()[-1] == f"wrote {out}"


def test_a_file_that_is_not_results_is_skipped(tmp_path, capsys):
    (tmp_path / "dem-0000000000000000.h5").write_bytes(b"not HDF5")
    out = tmp_path / "reference.json"
    assert main(["bench", "reference", str(tmp_path), "--out-file", str(out)]) == 0
    assert json.loads(out.read_text()) == []
    assert "dem-0000000000000000.h5: skipped" in capsys.readouterr().out
