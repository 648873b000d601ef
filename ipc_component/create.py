"""``ipc-component create PACKAGE``: a new package of rclpy components, what ``ros2 pkg create`` is for ROS.

It writes, into ``--destination`` (default: the current directory), a folder ``PACKAGE`` holding

* ``pyproject.toml``: the distribution, depending on ``rclpy-ipc-container``, with the component registered
  as an entry point in group ``rclpy_components`` (``"PACKAGE::Class" = "PACKAGE.module:Class"``);
* ``PACKAGE/__init__.py`` and ``PACKAGE/<module>.py``: one component class, a ``ComponentNode`` that publishes
  a fresh ``std_msgs/String`` per tick on ``~/out`` at a bounded ``rate`` that can be changed at run time,
  reports its health and stops its timer when it is unloaded;
* ``README.md``: how to install, list and load it.

``pip install <folder>`` then makes ``ipc-component types`` list it and a container load it by plugin name.
The package name must be a Python package name in the ROS style (lowercase letters, digits and underscores,
starting with a letter), because the container takes the package of a plugin from the top-level module of its
entry point; a name that an installed module already has is refused too, since the two would be confused.
An existing folder is never touched. Errors go to stderr with exit code 1.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import keyword
import re
import sys
from collections.abc import Sequence
from pathlib import Path

#: ROS package names (REP 144) that are Python package names as well.
PACKAGE_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
CLASS_NAME = re.compile(r"^[A-Z][A-Za-z0-9]*$")


class CreateError(Exception):
    """The package cannot be created; the message says why."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("package_name", help="Name of the new package (also its Python package name)")
    parser.add_argument("--destination", "--destination-directory", dest="destination", default=".",
                        help="Directory to create the package folder in (default: the current directory)")
    parser.add_argument("--component-name", default=None,
                        help="Class name of the component (default: the package name in CamelCase)")
    parser.add_argument("--description", default=None, help="One-line description of the package")


def run_create(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    """Write the package; print each file created. Errors: stderr, exit code 1."""
    try:
        files = create_package(args.package_name, Path(args.destination), args.component_name,
                               args.description)
    except CreateError as exc:
        print(exc, file=sys.stderr, flush=True)
        return 1
    root = str(files[0].parent)
    lines = [f"creating {path}" for path in files]
    lines += ["", f"Install it:     pip install {root if Path(root).is_absolute() else './' + root}",
              f"List it:        ipc-component types {args.package_name}",
              f"Load it:        ipc-component load /ComponentManager {args.package_name} "
              f"{args.package_name}::{component_class(args.package_name, args.component_name)}"]
    print("\n".join(lines), flush=True)
    return 0


def component_class(package: str, given: str | None) -> str:
    return given if given is not None else "".join(part.capitalize() for part in package.split("_") if part)


def snake_case(class_name: str) -> str:
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", class_name).lower()


def check_names(package: str, class_name: str) -> None:
    """CreateError unless ``package`` and ``class_name`` can be used (see the module docstring)."""
    if not PACKAGE_NAME.match(package) or keyword.iskeyword(package) or "__" in package:
        raise CreateError(f"Invalid package name '{package}': use lowercase letters, digits and single "
                          "underscores, starting with a letter (it is the Python package name too)")
    if not CLASS_NAME.match(class_name) or keyword.iskeyword(class_name):
        raise CreateError(f"Invalid component name '{class_name}': use a Python class name in CamelCase, "
                          "starting with an uppercase letter")
    try:
        taken = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        taken = None
    if taken is not None and taken.origin is not None:  # a plain folder (namespace package) does not count
        where = taken.origin
        raise CreateError(f"Invalid package name '{package}': a module of that name is already importable "
                          f"({where}); components of both would be confused, choose another name")


def create_package(package: str, destination: Path, class_name: str | None = None,
                   description: str | None = None) -> list[Path]:
    """Write the package folder ``destination/package``; the files written, pyproject.toml first."""
    class_name = component_class(package, class_name)
    root = destination / package
    if root.exists() or root.is_symlink():
        raise CreateError(f"Cannot create package '{package}': '{root}' already exists")
    check_names(package, class_name)
    if destination.exists() and not destination.is_dir():
        raise CreateError(f"Cannot create package '{package}': destination '{destination}' is not a directory")
    description = description or f"rclpy components of {package}"
    if not description.isprintable():
        raise CreateError("Invalid description: one line of printable characters, please")
    module = snake_case(class_name)
    values = {
        "package": package,
        "distribution": package.replace("_", "-"),
        "class_name": class_name,
        "module": module,
        "node_name": module,
        "plugin": f"{package}::{class_name}",
        "description": description,
        "description_toml": json.dumps(description),  # a JSON string is a TOML basic string
        "description_python": repr(description),
    }
    contents = {
        root / "pyproject.toml": PYPROJECT,
        root / "README.md": README,
        root / package / "__init__.py": INIT,
        root / package / f"{module}.py": COMPONENT,
    }
    try:
        (root / package).mkdir(parents=True)
        for path, template in contents.items():
            path.write_text(template.format(**values))
    except OSError as exc:
        raise CreateError(f"Cannot create package '{package}': {exc}") from exc
    return list(contents)


# --- templates (str.format: literal braces are doubled) ----------------------------------------------------
PYPROJECT = '''\
[build-system]
requires = ["setuptools>=77"]
build-backend = "setuptools.build_meta"

[project]
name = "{distribution}"
version = "0.0.1"
description = {description_toml}
readme = "README.md"
requires-python = ">=3.11"
dependencies = ["rclpy-ipc-container"]

[tool.setuptools.packages.find]
include = ["{package}*"]

# The component container finds components by these entry points: "<package>::<Class>" = "<module>:<Class>".
# The package name that LoadNode and `ipc-component load` take is the top-level module of the target.
[project.entry-points.rclpy_components]
"{plugin}" = "{package}.{module}:{class_name}"
'''

INIT = '''\
{description_python}
'''

COMPONENT = '''\
"""``{plugin}``: publishes std_msgs/String "{node_name} <n>" on ``~/out`` at ``rate`` Hz.

Parameter ``rate``: messages per second, a float in [0.1, 100]; can be changed at run time.
"""
from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.parameter import Parameter
from std_msgs.msg import String

from component_container import ComponentNode
from component_container.health import OK, Health


class {class_name}(ComponentNode):
    """A component: the container constructs it with rclpy Node keyword arguments, passed on as they are."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("{node_name}", **kwargs)
        self.rate = self.declare_parameter("rate", 1.0, ParameterDescriptor(
            description="messages per second, in [0.1, 100] (can be changed at run time)",
            floating_point_range=[FloatingPointRange(from_value=0.1, to_value=100.0)])).value
        self.count = 0
        self._publisher = self.create_publisher(String, "~/out", 10)
        self._timer = self.create_timer(1.0 / self.rate, self._tick)
        self.add_post_set_parameters_callback(self._apply)

    def _tick(self) -> None:
        self.count += 1
        # A new message object per publish: in-process subscribers get this very object, so it must never
        # be changed or published again after publish().
        self._publisher.publish(String(data=f"{node_name} {{self.count}}"))

    def _apply(self, parameters: list[Parameter]) -> None:
        """A change that rclpy accepted (type and range checked against the descriptor)."""
        for parameter in parameters:
            if parameter.name == "rate":
                self.rate = parameter.value
                self._timer.timer_period_ns = round(1e9 / self.rate)
                self._timer.reset()

    def health(self) -> Health:
        """This component's /diagnostics status, read about once a second from another thread."""
        return Health(OK, f"published {{self.count}}", {{"published": str(self.count), "rate": str(self.rate)}})

    def destroy_node(self) -> None:
        """Unloading: stop the timer, then let ComponentNode leave intra-process delivery and destroy the node."""
        self.destroy_timer(self._timer)
        super().destroy_node()
'''

README = '''\
# {package}

{description}.

| plugin | what it does |
|---|---|
| `{plugin}` | publishes std_msgs/String on `~/out` at `rate` Hz (parameter, can be changed at run time) |

```bash
pip install .                                   # where rclpy-ipc-container is installed
ipc-component types {package}
python -m component_container &                # or a container that is already running
ipc-component load /ComponentManager {package} {plugin} -e use_intra_process_comms:=true
```

Add a component: write its class (a `component_container.ComponentNode`) in `{package}/`, add a line to
`[project.entry-points.rclpy_components]` in `pyproject.toml` and install again.
'''
