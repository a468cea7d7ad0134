"""The README's Python example runs as printed (from a directory that holds the shipped
reference data, as the repository root does)."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_python_example_runs(tmp_path, monkeypatch, capsys):
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)
    assert blocks, "README.md has no python example"
    (tmp_path / "workflows").symlink_to(ROOT / "workflows")
    monkeypatch.chdir(tmp_path)
    exec(compile(blocks[0], "README.md", "exec"), {})
    assert re.search(r"mean residence time \d+\.\d s", capsys.readouterr().out)
    assert (tmp_path / "c_a.png").stat().st_size > 5_000
