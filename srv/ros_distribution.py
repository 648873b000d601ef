"""The ROS 2 distribution the project is built for, and its build backend: setuptools plus that distribution's
ROS wheels as build requirements.

The pins of each distribution live in one place, ``[tool.ros-distributions]`` of pyproject.toml; the project's
other requirements in ``[tool.rclpy-ipc-container]``. The ROS wheels are needed to build (``setup.py``
generates and compiles srv/ against them) and to run, and a wheel built against one distribution's libraries
works only with that distribution, so the package metadata names the distribution it was built with:

* what a build **installs** (``pip install .`` in an isolated build environment) is the distribution named by
  ``ROS_DISTRO``, the default (Jazzy) when it is not set: :func:`requested`;
* what a build **is for** (``setup.py``'s dependencies, the interfaces' build folder) is the distribution
  whose rclpy is installed where it runs, the requested one while none is: :func:`built_for`.

``make setup ROS_DISTRO=kilted`` installs ``python srv/ros_distribution.py requirements`` (everything, with the
test extras) into a venv of its own, then the project with ``--no-build-isolation --no-deps``.
"""
from __future__ import annotations

import importlib
import importlib.metadata
import os
import pathlib
import re
import sys
import tomllib
from typing import Any, Callable

PYPROJECT = pathlib.Path(__file__).resolve().parents[1] / "pyproject.toml"


def _tables() -> tuple[dict[str, Any], dict[str, Any]]:
    """pyproject.toml's ``tool.ros-distributions`` and ``tool.rclpy-ipc-container`` tables."""
    tool = tomllib.loads(PYPROJECT.read_text())["tool"]
    return tool["ros-distributions"], tool["rclpy-ipc-container"]


def distributions() -> dict[str, dict[str, list[str]]]:
    """Each distribution's pins: ``requires`` (build and run) and ``test`` (the test extra)."""
    return {name: pins for name, pins in _tables()[0].items() if isinstance(pins, dict)}


def requested(environ: dict[str, str] | os._Environ = os.environ) -> str:
    """The distribution ``ROS_DISTRO`` names, or the default; an unknown name is refused with the known ones."""
    table = _tables()[0]
    name = environ.get("ROS_DISTRO") or table["default"]
    if name not in distributions():
        raise SystemExit(f"rclpy-ipc-container has no pins for ROS_DISTRO={name}: it builds for "
                         f"{', '.join(distributions())} (pyproject.toml, tool.ros-distributions)")
    return name


def installed() -> str | None:
    """The distribution whose rclpy meta-package (its first pin) is installed, if one is."""
    for name, pins in distributions().items():
        try:
            importlib.metadata.distribution(requirement_name(pins["requires"][0]))
        except importlib.metadata.PackageNotFoundError:
            continue
        return name
    return None


def built_for() -> str:
    """The distribution a build here compiles against: the installed one, else the one its build installs."""
    return installed() or requested()


def interfaces_build_dir(distribution: str) -> pathlib.Path:
    """Where setup.py builds the srv/ interfaces for ``distribution``, relative to the project: one folder per
    distribution, so that the venvs of two distributions can hold editable installs of the same tree."""
    return pathlib.Path("build") / "interfaces" / distribution


def dependencies(distribution: str) -> list[str]:
    """The project's run requirements with ``distribution``'s ROS wheels."""
    return [*distributions()[distribution]["requires"], *_tables()[1]["dependencies"]]


def extras(distribution: str) -> dict[str, list[str]]:
    """The optional requirement sets; the test extra holds ``distribution``'s ROS test wheels."""
    own = {name: list(requirements) for name, requirements in _tables()[1]["optional-dependencies"].items()}
    own["test"] = [*distributions()[distribution]["test"], *own["test"]]
    return own


def requirement_name(requirement: str) -> str:
    """The normalized project name of a requirement string."""
    return re.match(r"[A-Za-z0-9._-]+", requirement).group(0).lower().replace("_", "-")


def _adding_ros(hook: str) -> Callable[[dict[str, Any] | None], list[str]]:
    """setuptools' PEP 517 ``hook`` (a get_requires_for_build_*) plus the requested distribution's ROS wheels:
    setup.py generates and compiles srv/ with them."""
    def get_requires(config_settings: dict[str, Any] | None = None) -> list[str]:
        setuptools_hook = getattr(importlib.import_module("setuptools.build_meta"), hook)
        return [*setuptools_hook(config_settings), *distributions()[requested()]["requires"]]
    get_requires.__name__ = hook
    return get_requires


get_requires_for_build_wheel = _adding_ros("get_requires_for_build_wheel")
get_requires_for_build_editable = _adding_ros("get_requires_for_build_editable")
get_requires_for_build_sdist = _adding_ros("get_requires_for_build_sdist")


def __getattr__(name: str) -> Any:
    """The other PEP 517 hooks are setuptools' (imported only when a build asks: the Makefile runs this module
    in a venv that may not have setuptools yet)."""
    if name.startswith(("build_", "prepare_metadata_")):
        return getattr(importlib.import_module("setuptools.build_meta"), name)
    raise AttributeError(name)


def _all_requirements(distribution: str) -> list[str]:
    """What ``make setup`` installs in one pip run: the build requirements, the dependencies and the test
    extra, for ``distribution``."""
    build = tomllib.loads(PYPROJECT.read_text())["build-system"]["requires"]
    return [*build, *dependencies(distribution), *extras(distribution)["test"]]


if __name__ == "__main__":
    # `python srv/ros_distribution.py default|requirements|extra NAME` for the Makefile (ROS_DISTRO picks the
    # distribution).
    if sys.argv[1:] == ["default"]:
        print(_tables()[0]["default"])
    elif sys.argv[1:] == ["requirements"]:
        print("\n".join(_all_requirements(requested())))
    elif sys.argv[1:2] == ["extra"] and len(sys.argv) == 3:
        print("\n".join(extras(requested())[sys.argv[2]]))
    else:
        raise SystemExit("usage: ros_distribution.py default|requirements|extra NAME")
