"""``pbmdem bench predict`` runs the README's example in fresh interpreters and records
every measurement (timings are recorded, never asserted)."""

import json
from pathlib import Path

from workflows.bench.predict import EXAMPLE
from workflows.cli.main import main


def test_bench_predict_records_the_command_with_and_without_its_figure_and_its_imports(tmp_path, capsys):
    out = tmp_path / "predict.json"
    assert main(["bench", "predict", "--repeats", "1", "--out-file", str(out)]) == 0
    record = json.loads(out.read_text())
    for name in ("with its figure and page", "without them (--no-figures)", "its imports (workflows.products.predict)"):
        assert len(record[name]["wall_s"]) == 1 and record[name]["wall_s"][0] > 0
    assert record["target_s"] == 2.0 and "<= 2 s" in capsys.readouterr().out


def test_the_bench_times_the_readmes_example():
    readme = (Path(__file__).resolve().parents[3] / "README.md").read_text()
    assert f"pbmdem predict --config {EXAMPLE} --no-figures" in readme
