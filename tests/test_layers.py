"""The dependency direction, read from the source (every import statement, at any depth,
so a lazy import inside a function counts too).

Between the top packages: workflows -> {dem, pbm} -> coupling. DEM and PBM meet only in
coupling/, which imports neither; nothing below workflows/ imports it.

Inside workflows/, by floor: cli -> products -> report -> analysis, prediction -> pipeline
-> shipped -> config. A room imports its own floor or lower ones. The studies and benchmarks import
the product; only the command line imports them, so nothing the product runs depends on a
study or a benchmark.
"""

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
#: workflows' rooms by floor; a room may import rooms on its floor or below.
FLOORS = {
    "config": 0,
    "config_reference": 0,
    "shipped": 1,
    "pipeline": 2,
    "analysis": 3,
    "prediction": 3,
    "report": 4,
    "products": 5,
    "studies": 6,
    "bench": 6,
    "cli": 7,
}
#: rooms nobody but the command line may import
LEAVES = {"studies", "bench"}


def imports(path: Path) -> set[tuple[int, str]]:
    """(line, dotted module) of every absolute import; relative ones resolved."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add((node.lineno, node.module))
            found.update((node.lineno, f"{node.module}.{alias.name}") for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level > 0:
            parts = path.relative_to(ROOT).with_suffix("").parts[: -node.level]
            found.add((node.lineno, ".".join((*parts, node.module or ""))))
    return found


def imported_packages(path: Path) -> set[tuple[int, str]]:
    return {(line, module.split(".")[0]) for line, module in imports(path)}


def room(module: str) -> str | None:
    """The workflows room a dotted module belongs to, or None outside workflows/."""
    parts = module.split(".")
    if parts[0] != "workflows" or len(parts) < 2:
        return None
    return parts[1] if parts[1] in FLOORS else None


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_run_one_way(package):
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"no sources under {package}/"
    wrong = [
        f"{path.relative_to(ROOT)}:{line} imports {target}"
        for path in files
        for line, target in sorted(imported_packages(path))
        if target in FORBIDDEN[package]
    ]
    assert not wrong, "imports against the direction workflows -> {dem, pbm} -> coupling:\n" + "\n".join(wrong)


def test_every_workflows_module_has_a_floor():
    loose = [
        str(p.relative_to(ROOT))
        for p in (ROOT / "workflows").rglob("*.py")
        if p.name != "__init__.py" and room(".".join(p.relative_to(ROOT).with_suffix("").parts)) is None
    ]
    assert not loose, f"modules of workflows/ in no room of {sorted(FLOORS)}: {loose}"


def test_workflows_floors_run_one_way():
    wrong = []
    for path in sorted((ROOT / "workflows").rglob("*.py")):
        here = room(".".join(path.relative_to(ROOT).with_suffix("").parts))
        if here is None:
            continue
        for line, module in sorted(imports(path)):
            there = room(module)
            if there is None or there == here:
                continue
            if there in LEAVES and here != "cli":
                wrong.append(f"{path.relative_to(ROOT)}:{line} ({here}) imports {module}: only the CLI may")
            elif FLOORS[there] > FLOORS[here]:
                wrong.append(
                    f"{path.relative_to(ROOT)}:{line} ({here}, floor {FLOORS[here]}) imports {module} "
                    f"({there}, floor {FLOORS[there]})"
                )
    assert not wrong, "imports up the floors of workflows/:\n" + "\n".join(wrong)


def test_only_the_cli_runs_as_a_program():
    mains = [
        str(p.relative_to(ROOT))
        for p in (ROOT / "workflows").rglob("*.py")
        if "__main__" in p.read_text() and p.parent.name != "cli"
    ]
    assert not mains, f"__main__ outside workflows/cli/: {mains}"


def test_the_check_sees_a_lazy_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import numpy\n\ndef f():\n    from dem.post import DemResults\n")
    assert imported_packages(bad) == {(1, "numpy"), (4, "dem"), (4, "dem")}


def test_the_floor_check_sees_a_product_importing_a_study():
    assert room("workflows.studies.lag") == "studies" and room("workflows.products.compare") == "products"
    assert room("workflows.config") == "config" and room("numpy") is None
