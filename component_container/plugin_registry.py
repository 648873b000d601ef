"""Finding component classes by plugin name: the rclpy counterpart of pluginlib and the ament index.

rclcpp_components looks a plugin up in the ament index resource of a package and loads it from a shared
library. Here a Python distribution registers its components as entry points in the ``rclpy_components``
group (``"components::CameraDriver" = "components.camera_driver:CameraDriver"``); the package a component
belongs to is the top-level Python package of the entry point's module. The error strings start as rclcpp's, so
users and tools that match on them keep working; what follows says what they mean here.
"""
from __future__ import annotations

import fnmatch
import importlib
import sys
from collections.abc import Sequence
from importlib.metadata import EntryPoint, entry_points

from rclpy.node import Node

ENTRY_POINT_GROUP = "rclpy_components"

UNKNOWN_PACKAGE = "Could not find requested resource in ament index"
UNKNOWN_PLUGIN = "Failed to find class with the requested plugin name."


class PluginError(Exception):
    """A plugin could not be resolved; the message is the one reported to the LoadNode caller."""


def _package_of(entry_point: EntryPoint) -> str:
    return entry_point.module.split(".")[0]


class PluginRegistry:
    """Resolves ``(package_name, plugin_name)`` to an rclpy ``Node`` subclass.

    ``allow_module_plugins`` additionally accepts ``module.path:ClassName`` plugin names. It is off by
    default because the load service answers anyone on the ROS domain, who must not be able to make the
    container import arbitrary code. For the same reason ``allow_plugins`` (fnmatch patterns over plugin
    names, e.g. ``components::*``) narrows what may be loaded at all: when given, a plugin name (module plugins
    included) must match one of them. It is checked before anything is looked up, so a refused caller learns
    nothing about which plugins are installed.
    """

    def __init__(self, allow_module_plugins: bool = False, allow_plugins: Sequence[str] = ()) -> None:
        self._allow_module_plugins = allow_module_plugins
        self._allow_plugins = tuple(allow_plugins)

    @staticmethod
    def _entry_points() -> list[EntryPoint]:
        # Read on every request so that packages installed after the container started are found too.
        unique = {(ep.name, ep.value): ep for ep in entry_points(group=ENTRY_POINT_GROUP)}
        return list(unique.values())

    def plugins_by_package(self) -> dict[str, list[str]]:
        """Registered plugin names per package, both sorted (what ``ipc-component types`` lists)."""
        packages: dict[str, set[str]] = {}
        for ep in self._entry_points():
            packages.setdefault(_package_of(ep), set()).add(ep.name)
        return {package: sorted(names) for package, names in sorted(packages.items())}

    def resolve(self, package_name: str, plugin_name: str) -> type[Node]:
        """Import and return the component class, or raise :class:`PluginError` with rclcpp's message."""
        if self._allow_plugins and not any(fnmatch.fnmatchcase(plugin_name, p) for p in self._allow_plugins):
            raise PluginError(f"{UNKNOWN_PLUGIN} Plugin '{plugin_name}' is not allowed by this container "
                              "(--allow-plugins)")
        if ":" in plugin_name and "::" not in plugin_name:
            return self._resolve_module_plugin(package_name, plugin_name)
        in_package = [ep for ep in self._entry_points() if _package_of(ep) == package_name]
        if not in_package:
            raise PluginError(
                f"{UNKNOWN_PACKAGE}: package '{package_name}' is not installed in the Python environment "
                f"{sys.prefix} (no entry point of the group '{ENTRY_POINT_GROUP}' belongs to it); "
                "'ipc-component types' run in that environment lists the packages it has")
        matches = [ep for ep in in_package if ep.name == plugin_name]
        if not matches:
            raise PluginError(UNKNOWN_PLUGIN)
        try:
            cls = matches[0].load()
        except Exception as exc:  # any import-time failure of the plugin's module is reported, not raised
            raise PluginError(f"Failed to load library: {type(exc).__name__}: {exc}") from exc
        return _check_node_class(cls)

    def _resolve_module_plugin(self, package_name: str, plugin_name: str) -> type[Node]:
        if not self._allow_module_plugins:
            raise PluginError(
                f"{UNKNOWN_PLUGIN} Plugin names of the form 'module:Class' are accepted only by a container "
                "started with --allow-module-plugins")
        module_name, _, class_name = plugin_name.partition(":")
        if module_name.split(".")[0] != package_name:
            raise PluginError(f"{UNKNOWN_PACKAGE}: module '{module_name}' is not in package '{package_name}'")
        try:
            module = importlib.import_module(module_name)
        except Exception as exc:  # report import failures of user code to the caller
            raise PluginError(f"Failed to load library: {type(exc).__name__}: {exc}") from exc
        cls = getattr(module, class_name, None)
        if cls is None:
            raise PluginError(UNKNOWN_PLUGIN)
        return _check_node_class(cls)


def _check_node_class(cls: object) -> type[Node]:
    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise PluginError(f"{UNKNOWN_PLUGIN} ({cls!r} is not an rclpy Node subclass)")
    return cls
