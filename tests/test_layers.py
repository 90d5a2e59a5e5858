"""Imports run only downward: bench -> export -> service -> model. A module may import its own
package and any package below it, never one above (also inside functions)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ["model", "service", "export", "bench"]  # lowest first


def imported_packages(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
        elif isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
    return names & set(LAYERS)


def upward_imports(root: Path = ROOT) -> list[str]:
    found = []
    for rank, package in enumerate(LAYERS):
        assert (root / package).is_dir(), f"no {package}/ package: update LAYERS"
        for path in sorted((root / package).rglob("*.py")):
            above = {name for name in imported_packages(path) if LAYERS.index(name) > rank}
            found += [f"{path.relative_to(root)} imports {name}" for name in sorted(above)]
    return found


def test_no_module_imports_a_package_above_its_own():
    assert upward_imports() == []


def test_the_check_sees_an_upward_import(tmp_path):
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "bad.py").write_text("def f():\n    from service.engine import OnnxEngine\n")
    for package in LAYERS[1:]:
        (tmp_path / package).mkdir()
    assert upward_imports(tmp_path) == ["model/bad.py imports service"]
