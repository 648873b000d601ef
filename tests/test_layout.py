"""The layout rules, read from every module's imports (ast): every arrow points down.

    ipc_component (CLI)          may use everything below
    components                   may use component_container and baglib
    component_container          may use baglib only where a runtime needs it (today: the action topic names)
    baglib.tools                 may use baglib.read, baglib.write, baglib.format
    baglib.upload                may use baglib.read, baglib.format (uploading finished bags beside the tools)
    baglib.read | baglib.write   may use baglib.format, never each other nor the tools
    baglib.format                the bottom: no other layer of the project

The test harness (``ipc_testing``) sits beside the CLI: tests and benchmarks use it, no product code does. The
benchmarks (``benchmarks``) sit on top: no product code imports them, and like every package they hold no import
cycle.
"""
from __future__ import annotations

import ast
import pathlib
import subprocess
import sys

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]

#: For each layer, the project layers it must not import. Layers are module prefixes; the longest one wins.
FORBIDDEN: dict[str, set[str]] = {
    "baglib.format": {"baglib.read", "baglib.write", "baglib.tools", "baglib.upload", "components", "component_container",
                      "ipc_component", "ipc_testing", "benchmarks"},
    "baglib.read": {"baglib.write", "baglib.tools", "baglib.upload", "components", "component_container", "ipc_component",
                    "ipc_testing", "benchmarks"},
    "baglib.write": {"baglib.read", "baglib.tools", "baglib.upload", "components", "component_container", "ipc_component",
                     "ipc_testing", "benchmarks"},
    "baglib.tools": {"baglib.upload", "components", "component_container", "ipc_component", "ipc_testing", "benchmarks"},
    "baglib.upload": {"baglib.write", "baglib.tools", "components", "component_container", "ipc_component",
                      "ipc_testing", "benchmarks"},
    "component_container": {"components", "ipc_component", "ipc_testing", "benchmarks"},
    "components": {"ipc_component", "ipc_testing", "benchmarks"},
    "ipc_component": {"ipc_testing", "benchmarks"},
    "ipc_testing": {"benchmarks"},
}
SOURCE_PACKAGES = ("baglib", "component_container", "components", "ipc_component", "ipc_testing", "benchmarks")


def module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: pathlib.Path) -> set[str]:
    """The absolute module names ``path`` imports (relative imports resolved against its package)."""
    package = module_name(path) if path.name == "__init__.py" else module_name(path).rpartition(".")[0]
    return imports_in(path.read_text(), package)


def imports_in(source: str, package: str) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, *([base] if base else [])])
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
    return names


def layer_of(module: str) -> str | None:
    matches = [layer for layer in FORBIDDEN if module == layer or module.startswith(layer + ".")]
    return max(matches, key=len) if matches else None


def within(module: str, layer: str) -> bool:
    return module == layer or module.startswith(layer + ".")


def all_modules() -> dict[str, set[str]]:
    return {module_name(path): imports_of(path)
            for package in SOURCE_PACKAGES for path in sorted((REPO / package).rglob("*.py"))}


def upward_imports(modules: dict[str, set[str]]) -> dict[str, list[str]]:
    found = {}
    for module, imported in modules.items():
        layer = layer_of(module)
        bad = sorted(name for name in imported for other in FORBIDDEN.get(layer, ()) if within(name, other))
        if bad:
            found[module] = bad
    return found


def test_every_import_points_down() -> None:
    modules = all_modules()
    assert {"baglib.read.reader", "baglib.write.writer", "baglib.tools.repair", "ipc_component.cli",
            "component_container.component_manager"} <= set(modules)
    assert upward_imports(modules) == {}


@pytest.mark.parametrize(("module", "imported"), [
    ("baglib.read.reader", "baglib.tools.repair"),       # the read path once imported the repair tool
    ("baglib.read.sqlite_reader", "baglib.write.writer"),
    ("baglib.write.writer", "baglib.read.reader"),
    ("baglib.format.metadata", "baglib.read.metadata_read"),
    ("component_container.component_manager", "components.recorder.recorder"),
    ("components.player.player", "ipc_component.cli"),
])
def test_the_rule_catches_an_upward_import(module: str, imported: str) -> None:
    assert upward_imports({module: {imported}}) == {module: [imported]}


def test_relative_imports_are_resolved() -> None:
    source = "from ..tools import repair\nfrom .mcap_reader import McapReader\n"
    assert {"baglib.tools", "baglib.tools.repair", "baglib.read.mcap_reader"} <= imports_in(source, "baglib.read")


def test_the_cli_lives_outside_the_container_runtime() -> None:
    assert not list((REPO / "component_container").glob("cli*.py"))
    assert (REPO / "ipc_component" / "cli.py").is_file()


def test_component_node_is_importable_as_the_docs_say() -> None:
    from component_container import ComponentNode
    from component_container.component_node import ComponentNode as Defined

    assert ComponentNode is Defined


def import_cycles(modules: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles among ``modules`` within one top-level package (each as its modules, sorted), imports
    inside functions included: a function-level import only postpones the circle to the first call."""
    edges = {module: {target for name in imported for target in modules
                      if target != module and name == target and _package(target) == _package(module)}
             for module, imported in modules.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(module: str) -> None:  # Tarjan's strongly connected components
        index[module] = low[module] = len(index)
        stack.append(module)
        for target in edges[module]:
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == module:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for module in sorted(edges):
        if module not in index:
            visit(module)
    return sorted(cycles)


def _package(module: str) -> str:
    return module.split(".")[0]


def test_no_import_cycle_within_a_package() -> None:
    modules = all_modules()
    assert {"benchmarks.report", "benchmarks.result_folder", "benchmarks.record.main"} <= set(modules)
    assert import_cycles(modules) == []


def test_the_cycle_rule_catches_a_circle() -> None:
    modules = {"ipc_component.cli": {"ipc_component.top", "ipc_component.top.run_top"},
               "ipc_component.top": {"ipc_component.cli.RosSession", "ipc_component.cli"},
               "ipc_component.text_table": set(),
               "components.a": {"ipc_component.cli"}}
    assert import_cycles(modules) == [["ipc_component.cli", "ipc_component.top"]]


@pytest.mark.parametrize(("imported", "not_loaded"), [
    # the bag verbs (info, merge, convert, export, recover) need no ROS: rclpy and the interfaces cost ~0.1 CPU-s
    ("ipc_component.cli", ("rclpy", "composition_interfaces", "av")),
    # the components import the codec modules for their parameters; PyAV loads at the first frame (~50 ms)
    ("components.recorder.recorder", ("av",)),
    ("components.player.player", ("av",)),
    ("components.foxglove_bridge.bridge", ("av",)),
])
def test_heavy_modules_load_where_they_are_used(imported: str, not_loaded: tuple[str, ...]) -> None:
    """Importing ``imported`` in a fresh interpreter leaves ``not_loaded`` unimported (they load on first use)."""
    probe = f"import sys, {imported}; print(' '.join(m for m in {not_loaded!r} if m in sys.modules))"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [], f"importing {imported} loads {done.stdout.split()}"
