"""The layout rules: imports point down (container <- components; baglib below both), and what the README
tells users to import is importable as written."""
from __future__ import annotations

import ast
import pathlib

REPO = pathlib.Path(__file__).resolve().parents[1]


def imported_modules(package: str) -> dict[str, set[str]]:
    """Per source file of ``package``, the absolute module names it imports."""
    found: dict[str, set[str]] = {}
    for path in sorted((REPO / package).rglob("*.py")):
        names: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module)
        found[str(path.relative_to(REPO))] = names
    return found


def test_container_never_imports_components() -> None:
    offending = {f: sorted(n for n in names if n.split(".")[0] == "components")
                 for f, names in imported_modules("component_container").items()}
    assert not {f: n for f, n in offending.items() if n}


def test_baglib_imports_neither_components_nor_the_container() -> None:
    modules = imported_modules("baglib")
    assert "baglib/writer.py" in modules and "baglib/info.py" in modules
    offending = {f: sorted(n for n in names if n.split(".")[0] in ("components", "component_container"))
                 for f, names in modules.items()}
    assert not {f: n for f, n in offending.items() if n}


def test_component_node_is_importable_as_the_readme_says() -> None:
    from component_container import ComponentNode
    from component_container.component_node import ComponentNode as Defined

    assert ComponentNode is Defined
