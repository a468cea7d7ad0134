"""The dependency direction: workflows -> {dem, pbm} -> coupling. DEM and PBM meet only in
coupling/, which imports neither; nothing below workflows/ imports it. Read from the source
(every import statement, at any depth), so a lazy import inside a function counts too."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("coupling", "dem", "pbm", "workflows")
FORBIDDEN = {
    "coupling": {"dem", "pbm", "workflows"},
    "dem": {"pbm", "workflows"},
    "pbm": {"dem", "workflows"},
    "workflows": set(),
}


def imported_packages(path: Path) -> set[tuple[int, str]]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update((node.lineno, alias.name.split(".")[0]) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add((node.lineno, node.module.split(".")[0]))
        elif isinstance(node, ast.ImportFrom) and node.level > 0:
            found.add((node.lineno, path.relative_to(ROOT).parts[0]))  # relative: its own package
    return found


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_run_one_way(package):
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"no sources under {package}/"
    wrong = [f"{path.relative_to(ROOT)}:{line} imports {target}"
             for path in files for line, target in sorted(imported_packages(path)) if target in FORBIDDEN[package]]
    assert not wrong, "imports against the direction workflows -> {dem, pbm} -> coupling:\n" + "\n".join(wrong)


def test_the_check_sees_a_lazy_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import numpy\n\ndef f():\n    from dem.post import DemResults\n")
    assert imported_packages(bad) == {(1, "numpy"), (4, "dem")}
