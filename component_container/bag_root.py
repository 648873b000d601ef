"""The bag root: one directory tree that every path a load request or a component service names must stay in.

The load service answers anyone on the ROS domain, so a path parameter (a recorder's ``storage.uri``, a QoS
override file) is an instruction from an unauthenticated caller to create or read files. With a bag root
(``--bag-root DIR``) such a path is taken relative to the root and refused unless it resolves inside it, after
``..`` and symlinks. A refusal never depends on what exists outside the root: a path that is outside on its
face is refused before the filesystem is consulted, and the refusal reads the same whatever the resolution met.
"""
from __future__ import annotations

import os
from pathlib import Path


def bag_root_directory(path: str) -> Path:
    """The resolved root for ``--bag-root``; ValueError unless it is an existing directory.

    Resolved once at start-up, so that a symlink to the root given on the command line is fine and the later
    containment checks compare resolved paths with a resolved root.
    """
    resolved = Path(os.path.realpath(path))
    if not resolved.is_dir():
        raise ValueError(f"bag root {path!r} is not an existing directory")
    return resolved


def confine(root: Path, parameter: str, value: str) -> Path:
    """``value`` resolved inside ``root`` (relative values are joined to it); ValueError if it leaves the root.

    Resolution has ``os.path.realpath`` semantics: symlinks are followed, also dangling ones and those before a
    not-yet-existing tail, so a link inside the root that points out is refused. The message names the
    parameter and echoes only the caller's own value, never what the resolution found on disk.
    """
    if "\0" in value:
        raise ValueError(f"parameter '{parameter}': the path contains a NUL character")
    joined = os.path.join(root, value)  # an absolute value replaces the root
    outside = ValueError(f"parameter '{parameter}': {value!r} is outside the bag root {str(root)!r}")
    if not _within(root, Path(os.path.normpath(joined))):  # outside on its face: no filesystem access at all
        raise outside
    resolved = Path(os.path.realpath(joined))
    if not _within(root, resolved):
        raise outside
    return resolved


def _within(root: Path, path: Path) -> bool:
    return path == root or root in path.parents
