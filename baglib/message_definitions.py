"""Message definitions and type hashes, looked up in the installed interface packages.

A bag is only self-describing if it carries the full text of every message type it stores: readers
such as Foxglove, ``rosbags`` and ``ros2 bag play`` on another machine have no other way to decode
the bytes. rosbag2 builds that text with ``LocalMessageDefinitionSource``; this module reproduces
its output exactly, because ``rosbags`` recomputes the RIHS01 type hash from the text and ignores
(or rejects) a definition whose hash does not match the one recorded for the topic.
"""
from __future__ import annotations

import json
import re
import sys
from functools import cache
from pathlib import Path

__all__ = [
    "MessageDefinitionNotFoundError",
    "message_definition",
    "type_hash",
]

#: The line rosbag2 puts between the root definition and each dependency.
_SEPARATOR = "=" * 80 + "\n"

# The same patterns rosbag2 uses, so the set of dependencies (and thus the text) is identical.
# Field types in .msg files: "foo_msgs/Bar" in "foo_msgs/Bar[] bar".
_MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
# Includes in .idl files: "foo_msgs/msg/Bar" in "#include <foo_msgs/msg/Bar.idl>".
_IDL_INCLUDE = re.compile(r'(?:^|\n)#include\s+(?:"|<)([a-zA-Z0-9_/]+)\.idl(?:"|>)')

# rosbag2's list plus "wstring": rosbag2 forgets it and then falls back to IDL for any type with a
# wstring field; treating it as the builtin it is keeps such types in the readable .msg form.
_PRIMITIVE_TYPES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
    "int32", "uint32", "int64", "uint64", "string", "wstring",
})

_NAME = r"[a-zA-Z][a-zA-Z0-9_]*"
_TYPE_NAME = re.compile(rf"^({_NAME})/(?:({_NAME})/)?({_NAME})$")

# Recursion bound as in rosbag2: message nesting is never this deep unless something is cyclic.
_MAX_DEPTH = 50


class MessageDefinitionNotFoundError(LookupError):
    """No definition file for a type exists in any place the interface packages are installed."""


def _split_type_name(type_name: str) -> tuple[str, str, str]:
    """Split ``pkg/Type`` or ``pkg/msg/Type`` into package, interface folder and type."""
    match = _TYPE_NAME.match(type_name)
    if match is None:
        raise ValueError(f"not a ROS type name (expected 'pkg/msg/Type'): {type_name!r}")
    package, folder, name = match.groups()
    return package, folder or "msg", name


@cache
def _share_directories(package: str) -> tuple[Path, ...]:
    """Places a package's interface files may be in, best first.

    The ament index knows packages installed anywhere on ``AMENT_PREFIX_PATH``; interface packages
    installed from PyPI wheels are not indexed there (often the variable is not even set), but
    always live in this interpreter's ``share`` folder.
    """
    candidates: list[Path] = []
    try:
        from ament_index_python.packages import get_package_share_directory

        candidates.append(Path(get_package_share_directory(package)))
    except (ImportError, LookupError, OSError, ValueError):
        pass
    fallback = Path(sys.prefix) / "share" / package
    if fallback not in candidates:
        candidates.append(fallback)
    return tuple(candidates)


def _find_file(package: str, folder: str, name: str, extension: str) -> Path | None:
    for share in _share_directories(package):
        path = share / folder / f"{name}{extension}"
        if path.is_file():
            return path
    return None


@cache
def _read_definition(type_name: str, extension: str) -> str:
    package, folder, name = _split_type_name(type_name)
    path = _find_file(package, folder, name, extension)
    if path is None:
        raise MessageDefinitionNotFoundError(f"no {extension} file for {type_name}")
    # newline="" keeps the bytes as written, exactly as rosbag2 reads them.
    with open(path, encoding="utf-8", newline="") as file:
        return file.read()


def _dependencies(text: str, type_name: str, extension: str) -> list[str]:
    """Dependencies of one definition, sorted as rosbag2's ``std::set`` orders them."""
    if extension == ".idl":
        return sorted(set(_IDL_INCLUDE.findall(text)))
    package = _split_type_name(type_name)[0]
    found = set()
    for field_type in _MSG_FIELD_TYPE.findall(text):
        if field_type in _PRIMITIVE_TYPES:
            continue
        found.add(field_type if "/" in field_type else f"{package}/{field_type}")
    return sorted(found)


def _full_text(root: str, extension: str, label: str) -> str:
    """Root text followed by every dependency once, depth first, each behind a separator."""
    seen: set[str] = set()

    def append(type_name: str, depth: int) -> str:
        if depth <= 0:
            raise RecursionError(f"message definition of {root} nests deeper than {_MAX_DEPTH}")
        text = _read_definition(type_name, extension)
        parts = [text]
        for dependency in _dependencies(text, type_name, extension):
            if dependency not in seen:
                seen.add(dependency)
                parts.append(f"\n{_SEPARATOR}{label}: {dependency}\n")
                parts.append(append(dependency, depth - 1))
        return "".join(parts)

    return append(root, _MAX_DEPTH)


@cache
def message_definition(type_name: str) -> tuple[str, str]:
    """Return ``(encoding, text)`` of a message type as rosbag2 stores it in a bag.

    ``type_name`` is ``pkg/msg/Type`` (``pkg/Type`` is accepted too). The encoding is ``ros2msg``
    when the type and all its dependencies have ``.msg`` files; otherwise the whole definition
    falls back to ``ros2idl`` (as in rosbag2), with every type, the root included, behind an
    ``IDL: pkg/msg/Type`` header.

    Raises:
        MessageDefinitionNotFoundError: neither form is installed for the type or a dependency.
        ValueError: ``type_name`` is not a ROS type name.
    """
    package, folder, name = _split_type_name(type_name)
    try:
        return "ros2msg", _full_text(type_name, ".msg", "MSG")
    except MessageDefinitionNotFoundError:
        pass
    root = f"{package}/{folder}/{name}"
    try:
        return "ros2idl", f"{_SEPARATOR}IDL: {root}\n" + _full_text(root, ".idl", "IDL")
    except MessageDefinitionNotFoundError as error:
        raise MessageDefinitionNotFoundError(
            f"no message definition for {type_name}: {error} (is its interface package installed?)"
        ) from None


@cache
def type_hash(type_name: str) -> str:
    """Return the ``RIHS01_<sha256>`` type hash that rosidl generated for a type.

    Publishers announce this hash in their endpoint info; when none is at hand (no publisher seen
    yet), the hash of the locally installed type is the same value for an identical definition.

    Raises:
        MessageDefinitionNotFoundError: the package has no ``<Type>.json`` type description.
        ValueError: ``type_name`` is not a ROS type name.
    """
    package, folder, name = _split_type_name(type_name)
    path = _find_file(package, folder, name, ".json")
    if path is None:
        raise MessageDefinitionNotFoundError(f"no type description (.json) for {type_name}")
    with open(path, encoding="utf-8") as file:
        description = json.load(file)
    try:
        return str(description["type_hashes"][0]["hash_string"])
    except (KeyError, IndexError, TypeError):
        raise MessageDefinitionNotFoundError(f"{path} holds no type hash") from None
