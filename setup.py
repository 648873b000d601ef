"""Build hook: compile the interface packages in srv/ into real ROS 2 typesupport during ``pip install``.

Everything else about the project is declared in pyproject.toml; the dependencies are those of
``tool.rclpy-ipc-container`` with the pins of the ROS 2 distribution built for (srv/ros_distribution.py). The
generated Python packages are built into ``build/interfaces/<distribution>/python`` and the shared libraries
into ``build/interfaces/<distribution>/lib``, then installed as the
``composition_interfaces`` / ``rosbag2_interfaces`` / ``foxglove_msgs`` packages (libraries inside) and ``<prefix>/share`` data
files (definitions, type descriptions, ament index markers), the layout the ROS wheels themselves use.
"""
from __future__ import annotations

import pathlib
import sys

from setuptools import Distribution, find_packages, setup
from setuptools.command.build_py import build_py

ROOT = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT / "srv"))
from build_interfaces import build_all, interface_packages  # noqa: E402
from ros_distribution import built_for, dependencies, extras, interfaces_build_dir  # noqa: E402

ROS_DISTRIBUTION = built_for()
BUILD_DIR = interfaces_build_dir(ROS_DISTRIBUTION)
INTERFACES = interface_packages()
# Every package of the source tree, found rather than listed (a hand list drifts: it once left out the player).
# tests/test_packaging.py checks this against the folders on disk and installs the built wheel.
NOT_SHIPPED = ["tests", "tests.*", "benchmarks", "benchmarks.*", "examples", "examples.*", "srv", "srv.*",
               "build", "build.*", "docs", "docs.*"]
SOURCE_PACKAGES = find_packages(where=str(ROOT), exclude=NOT_SHIPPED)


def _data_files() -> list[tuple[str, list[str]]]:
    """The share/ files the interface build produced, by install folder."""
    out = ROOT / BUILD_DIR
    groups: dict[str, list[str]] = {}
    for path in sorted(p for p in (out / "share").rglob("*") if p.is_file()):
        groups.setdefault(str(path.parent.relative_to(out)), []).append(str(path.relative_to(ROOT)))
    return sorted(groups.items())


class BinaryDistribution(Distribution):
    """The wheel carries compiled typesupport libraries: tag it for this Python and platform, not ``any``."""

    def has_ext_modules(self) -> bool:
        return True


class BuildPyWithInterfaces(build_py):
    """build_py that first generates and compiles the srv/ interface packages."""

    def run(self) -> None:
        build_all(ROOT / BUILD_DIR)
        self.distribution.data_files = _data_files()
        super().run()


INTERFACE_PACKAGES = [*INTERFACES, *(f"{name}.{kind}" for name in INTERFACES for kind in ("msg", "srv")
                                     if (ROOT / "srv" / name / kind).is_dir())]
for _name in INTERFACE_PACKAGES:  # setuptools checks package folders exist before build_py fills them
    (ROOT / BUILD_DIR / "python" / _name.replace(".", "/")).mkdir(parents=True, exist_ok=True)

setup(
    packages=[*SOURCE_PACKAGES, *INTERFACE_PACKAGES],
    package_dir={name: str(BUILD_DIR / "python" / name.replace(".", "/")) for name in INTERFACE_PACKAGES},
    package_data={**{name: ["*.so"] for name in INTERFACES}, "component_container": ["*.xml"]},
    install_requires=dependencies(ROS_DISTRIBUTION),
    extras_require=extras(ROS_DISTRIBUTION),
    cmdclass={"build_py": BuildPyWithInterfaces},
    distclass=BinaryDistribution,
)
