"""The notebook API (``workflows``' top-level names): the README's first Python example runs
as printed, from any directory; ``import workflows`` loads nothing until a name is used; ``predict``
is ``pbmdem predict``'s prediction."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

import workflows
from coupling.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]

#: the README's Python example, as printed there
README_EXAMPLE = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)[0]

NUMBER = r"(\d+\.\d)"


def test_the_readme_example_runs_from_any_directory(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # the shipped files are found by the package, not by the working directory
    exec(compile(README_EXAMPLE, "README_EXAMPLE", "exec"), {})
    out = capsys.readouterr().out
    dem = re.search(rf"DEM mean residence time {NUMBER} s \[{NUMBER}, {NUMBER}\]", out)
    pbm = re.search(rf"PBM mean residence time {NUMBER} s", out)
    new = re.search(rf"225 rpm, never run: {NUMBER} s \[{NUMBER}, {NUMBER}\]", out)
    assert dem and pbm and new, out
    value, low, high = map(float, dem.groups())
    assert low < value < high
    value, low, high = map(float, new.groups())
    assert low < value < high
    # the PBM of the validated mode sits within a few seconds of the DEM it was built from
    assert abs(float(pbm.group(1)) - float(dem.group(1))) < 3.0
    assert (tmp_path / "c_a.png").stat().st_size > 5_000


def test_the_example_uses_only_top_level_names():
    imports = re.findall(r"^(?:from|import) .*$", README_EXAMPLE, flags=re.M)
    assert imports == [line for line in imports if line.startswith("from workflows import ")]
    named = {name.strip() for line in imports for name in line.split(" import ")[1].split(",")}
    assert named <= set(workflows.__all__)


IMPORT_ALONE = """
import sys
import workflows
assert "predict" in dir(workflows) and "simulate" in dir(workflows)
heavy = sorted(m for m in ("numpy", "pbm", "dem", "workflows.config", "matplotlib") if m in sys.modules)
assert not heavy, heavy
"""


def test_importing_the_package_imports_nothing_heavy():
    # a fresh interpreter: the command line imports ``workflows`` and must not pay for the API
    proc = subprocess.run([sys.executable, "-c", IMPORT_ALONE], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_every_exported_name_resolves():
    for name in workflows.__all__:
        assert getattr(workflows, name) is not None, name
    with pytest.raises(AttributeError, match="'workflows' has no attribute 'simulte'"):
        workflows.simulte  # noqa: B018


def test_predict_is_what_the_command_prints(tmp_path):
    from workflows.cli.main import main

    config = ROOT / "workflows" / "reference" / "library" / "rpm200.toml"
    assert main(["predict", "--config", str(config), "--out", str(tmp_path), "--no-figures"]) == 0
    written = {q["key"]: q for q in json.loads((tmp_path / "prediction.json").read_text())["quantities"]}
    prediction = workflows.predict(config)
    assert {q.key for q in prediction.quantities} == set(written)
    for q in prediction.quantities:
        assert [q.value, q.low, q.high] == pytest.approx([written[q.key][k] for k in ("value", "low", "high")])
    again = workflows.predict(workflows.load_config(config))
    assert [q.record() for q in again.quantities] == [q.record() for q in prediction.quantities]


def test_predict_outside_the_domain_is_refused_unless_asked():
    reduced = workflows.load_preset("reduced")  # 5 mm particles; the library's are 6 mm
    with pytest.raises(ConfigError, match="outside the library's domain.*particle_diameter_m = 0.005"):
        workflows.predict(reduced)
    prediction = workflows.predict(reduced, extrapolate=True)
    assert prediction.extrapolated
    assert any("particle_diameter_m" in issue for issue in prediction.outside)
