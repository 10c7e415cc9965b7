"""The decoder's modules share only public names: each class's private state stays in its
own file (a module reaching into another object's `_x`, or importing another module's
`_x`, is a class smeared over files, which the decoder's modules are not)."""

from __future__ import annotations

import ast
from pathlib import Path

import calibration.decode

PACKAGE = Path(calibration.decode.__file__).parent


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _modules() -> list[Path]:
    return sorted(PACKAGE.glob("*.py"))


def test_no_module_imports_another_modules_private_names() -> None:
    found = []
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("calibration"):
                found += [f"{path.name}: {node.module}.{a.name}" for a in node.names
                          if _private(a.name)]
    assert not found, found


def test_no_module_reads_another_objects_private_attributes() -> None:
    found = []
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (isinstance(node, ast.Attribute) and _private(node.attr)
                    and isinstance(node.value, ast.Name)
                    and node.value.id not in ("self", "cls", "np")):
                found.append(f"{path.name}:{node.lineno} {node.value.id}.{node.attr}")
    assert not found, found
