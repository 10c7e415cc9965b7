"""Imports only point down the layers of docs/layout.md, inside functions too.

`acquisition` and `calibration` never import `api` or `hw_mocks`, `calibration` never imports
`acquisition`, and `hw_mocks` never imports `api`: the numerics stay usable without the
service or the simulator, and the simulator stays a plug-in of the hardware protocols.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("acquisition", "calibration", "api", "hw_mocks")
# (importing package, imported package) pairs that must never occur
FORBIDDEN = (("acquisition", "api"), ("acquisition", "hw_mocks"), ("calibration", "api"),
             ("calibration", "hw_mocks"), ("calibration", "acquisition"), ("hw_mocks", "api"))


def imported_modules(path: Path, package_parts: list[str]) -> set[str]:
    """Absolute names of every module a file imports (relative imports resolved)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package_parts[: len(package_parts) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            found.add(base)
    return found


def forbidden_imports(root: Path) -> list[str]:
    """`file: importer -> imported` for every import that points up a layer."""
    problems = []
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            package_parts = list(path.relative_to(root).parts[:-1])
            for name in imported_modules(path, package_parts):
                top = name.split(".")[0]
                if (pkg, top) in FORBIDDEN:
                    problems.append(f"{path.relative_to(root)}: {pkg} -> {name}")
    return problems


def test_product_imports_point_only_down() -> None:
    assert forbidden_imports(ROOT) == []


def test_an_upward_import_inside_a_function_is_found(tmp_path: Path) -> None:
    for pkg in PACKAGES:
        (tmp_path / pkg).mkdir()
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "calibration" / "ok.py").write_text("import numpy\nfrom . import maps\n")
    (tmp_path / "calibration" / "bad.py").write_text(
        "def f():\n    from ..acquisition import rig\n    return rig\n")
    (tmp_path / "hw_mocks" / "bad.py").write_text("import api.app\n")
    assert forbidden_imports(tmp_path) == [
        "calibration/bad.py: calibration -> acquisition",
        "hw_mocks/bad.py: hw_mocks -> api.app",
    ]
