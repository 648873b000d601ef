"""Message definitions and type hashes, looked up in the installed interface packages.

A bag is only self-describing if it carries the full text of every message type it stores: readers
such as Foxglove, ``rosbags`` and ``ros2 bag play`` on another machine have no other way to decode
the bytes. rosbag2 builds that text with ``LocalMessageDefinitionSource``; this module reproduces
its output exactly, because ``rosbags`` recomputes the RIHS01 type hash from the text and ignores
(or rejects) a definition whose hash does not match the one recorded for the topic.
"""
from __future__ import annotations

import importlib.util
import json
import re
import sys
from functools import cache
from pathlib import Path
from typing import Any, Callable

from baglib.format.service_events import EVENT_TYPE_SUFFIX, event_class, service_type

__all__ = [
    "message_class",
    "MessageDefinitionNotFoundError",
    "message_definition",
    "service_definitions",
    "type_hash",
    "type_hash_of_definition",
    "UNDESCRIBED",
]

#: How rosbag2 describes a type whose definition it cannot find (``MessageDefinition::empty_message_definition_for``,
#: used by ``SequentialWriter::create_topic``): ``(encoding, text)`` both empty. Readers take it as "no definition";
#: the messages are still there, as bytes.
UNDESCRIBED = ("", "")

#: A ROS package name (also a Python module name, so safe to look up with importlib).
#: The line rosbag2 puts between the root definition and each dependency.
_SEPARATOR = "=" * 80 + "\n"

# The same patterns rosbag2 uses, so the set of dependencies (and thus the text) is identical.
# Field types in .msg files: "foo_msgs/Bar" in "foo_msgs/Bar[] bar".
_MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
# Includes in .idl files: "foo_msgs/msg/Bar" in "#include <foo_msgs/msg/Bar.idl>".
_IDL_INCLUDE = re.compile(r'(?:^|\n)#include\s+(?:"|<)([a-zA-Z0-9_/]+)\.idl(?:"|>)')
# A whole #include line, removed from the sections of a service event definition.
_INCLUDE_LINE = re.compile(r"^#include\s[^\n]*\n?", re.MULTILINE)

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
    always live in this interpreter's ``share`` folder; an editable install's in its build tree.
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
    built = _built_share_directory(package)
    if built is not None and built not in candidates:
        candidates.append(built)
    return tuple(candidates)


def _built_share_directory(package: str) -> Path | None:
    """The share folder beside an interface package that this project builds (srv/build_interfaces.py writes
    ``build/interfaces/<distribution>/python/<pkg>`` and ``.../share/<pkg>``): an editable install (``make setup``,
    ``pip install -e``) imports the package from there and installs no ``share`` data."""
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return None
    if spec is None or spec.origin is None:
        return None
    python_dir = Path(spec.origin).parent.parent
    return python_dir.parent / "share" / package if python_dir.name == "python" else None


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
    if path is None and folder == "action" and extension == ".idl":
        generated = _action_idl(package, name)
        if generated is not None and _find_file(package, folder, _action_of(name), ".idl") is not None:
            return generated
    if path is None:
        raise MessageDefinitionNotFoundError(f"no {extension} file for {type_name}")
    # newline="" keeps the bytes as written, exactly as rosbag2 reads them.
    with open(path, encoding="utf-8", newline="") as file:
        return file.read()


def _action_of(name: str) -> str:
    """``Fib_SendGoal_Request`` -> ``Fib``: the action a generated struct belongs to."""
    event = _ACTION_EVENT.match(name)
    if event:
        return event.group(1)
    return next(name[: -len(suffix) - 1] for suffix in _ACTION_STRUCTS if name.endswith(f"_{suffix}"))


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


def _full_text(root: str, extension: str, label: str, root_text: str | None = None,
               clean: Callable[[str], str] = str) -> str:
    """Root text followed by every dependency once, depth first, each behind a separator.

    ``root_text`` replaces the root's file (for a type that has none); ``clean`` is applied to every
    section's text after its dependencies were read from it.
    """
    seen: set[str] = set()

    def append(type_name: str, text: str, depth: int) -> str:
        if depth <= 0:
            raise RecursionError(f"message definition of {root} nests deeper than {_MAX_DEPTH}")
        parts = [clean(text)]
        for dependency in _dependencies(text, type_name, extension):
            if dependency not in seen:
                seen.add(dependency)
                parts.append(f"\n{_SEPARATOR}{label}: {dependency}\n")
                parts.append(append(dependency, _read_definition(dependency, extension), depth - 1))
        return "".join(parts)

    return append(root, _read_definition(root, extension) if root_text is None else root_text, _MAX_DEPTH)


def _event_idl(service: str) -> str:
    """The IDL of ``pkg/srv/Name_Event``, the message rosidl generates for ``pkg/srv/Name`` (no file has it)."""
    package, _, name = service.split("/")
    return (f'#include "service_msgs/msg/ServiceEventInfo.idl"\n'
            f'#include "{service}.idl"\n\n'
            f"module {package} {{\n"
            "  module srv {\n"
            f"    struct {name}{EVENT_TYPE_SUFFIX} {{\n"
            "      service_msgs::msg::ServiceEventInfo info;\n\n"
            f"      sequence<{package}::srv::{name}_Request, 1> request;\n\n"
            f"      sequence<{package}::srv::{name}_Response, 1> response;\n"
            "    };\n"
            "  };\n"
            "};\n")


def _service_event_definition(type_name: str) -> str:
    """The ``ros2idl`` text of a service event type: its own IDL, then ServiceEventInfo, the service's
    ``_Request``/``_Response`` and their dependencies, each from the installed ``.idl`` files.

    rosbag2 Jazzy stores the ``.srv`` text here instead (behind an ``SRV:`` header, encoding ``ros2msg``,
    ``ros2idl`` or, for a service of primitive fields only, ``unknown``), which describes the request and
    the response but not the event message on the topic: no reader can decode the events with it, and the
    ``rosbags`` reader refuses the whole bag (ros2/rosbag2#2365). The text here decodes the events in
    ``rosbags`` (whose RIHS01 hash of it equals rosidl's) and in Foxglove. It is IDL because ``.msg`` cannot
    name the ``pkg/srv/...`` types the event is made of (readers turn them into ``pkg/msg/...``). The
    ``#include`` lines are left out: every included type is a section of the same text, and ``rosbags``'
    IDL parser rejects them.
    """
    root = f"{_SEPARATOR}IDL: {type_name}\n"
    return root + _full_text(type_name, ".idl", "IDL", root_text=_event_idl(service_type(type_name)),
                             clean=lambda text: _INCLUDE_LINE.sub("", text))


#: The structs rosidl generates for an action ``pkg/action/Name`` beyond its ``.idl`` file's Goal, Result and
#: Feedback: their fields, in rosidl's order (``{a}`` is ``pkg::action::Name``).
_ACTION_STRUCTS = {
    "SendGoal_Request": ("unique_identifier_msgs::msg::UUID goal_id;", "{a}_Goal goal;"),
    "SendGoal_Response": ("boolean accepted;", "builtin_interfaces::msg::Time stamp;"),
    "GetResult_Request": ("unique_identifier_msgs::msg::UUID goal_id;",),
    "GetResult_Response": ("int8 status;", "{a}_Result result;"),
    "FeedbackMessage": ("unique_identifier_msgs::msg::UUID goal_id;", "{a}_Feedback feedback;"),
}
_ACTION_EVENT = re.compile(r"^(.+)_(SendGoal|GetResult)_Event$")
_ACTION_INCLUDES = ("unique_identifier_msgs/msg/UUID", "builtin_interfaces/msg/Time",
                    "service_msgs/msg/ServiceEventInfo")


def _action_idl(package: str, name: str) -> str | None:
    """The IDL of a type rosidl generates for an action (``pkg/action/Fib_SendGoal_Event``, ``_FeedbackMessage``,
    a service's ``_Request`` / ``_Response``): no file has it. None for any other name."""
    event = _ACTION_EVENT.match(name)
    action, part = (event.group(1), event.group(2)) if event else next(
        ((name[: -len(suffix) - 1], suffix) for suffix in _ACTION_STRUCTS if name.endswith(f"_{suffix}")),
        (None, None))
    if action is None:
        return None
    qualified = f"{package}::action::{action}"
    if event:
        fields = ("service_msgs::msg::ServiceEventInfo info;",
                  f"sequence<{qualified}_{part}_Request, 1> request;",
                  f"sequence<{qualified}_{part}_Response, 1> response;")
    else:
        fields = tuple(field.format(a=qualified) for field in _ACTION_STRUCTS[part])
    includes = [*_ACTION_INCLUDES, f"{package}/action/{action}"]
    if event:
        includes += [f"{package}/action/{action}_{part}_Request", f"{package}/action/{action}_{part}_Response"]
    body = "".join(f"      {field}\n\n" for field in fields).rstrip("\n") + "\n"
    return ("".join(f'#include "{include}.idl"\n' for include in includes) + "\n"
            f"module {package} {{\n  module action {{\n    struct {name} {{\n{body}    }};\n  }};\n}};\n")


def _action_definition(type_name: str, text: str) -> str:
    """The ``ros2idl`` text of an action's generated type (see :func:`_action_idl`), like a service event's:
    rosbag2 Kilted stores the ``.action`` text, which describes no message on the topic."""
    root = f"{_SEPARATOR}IDL: {type_name}\n"
    return root + _full_text(type_name, ".idl", "IDL", root_text=text,
                             clean=lambda section: _INCLUDE_LINE.sub("", section))


@cache
def message_definition(type_name: str) -> tuple[str, str]:
    """Return ``(encoding, text)`` of a message type as rosbag2 stores it in a bag.

    ``type_name`` is ``pkg/msg/Type`` (``pkg/Type`` is accepted too). The encoding is ``ros2msg``
    when the type and all its dependencies have ``.msg`` files; otherwise the whole definition
    falls back to ``ros2idl`` (as in rosbag2), with every type, the root included, behind an
    ``IDL: pkg/msg/Type`` header. A service event type ``pkg/srv/Name_Event`` is ``ros2idl``
    (see :func:`_service_event_definition`).

    Raises:
        MessageDefinitionNotFoundError: neither form is installed for the type or a dependency.
        ValueError: ``type_name`` is not a ROS type name.
    """
    package, folder, name = _split_type_name(type_name)
    root = f"{package}/{folder}/{name}"
    try:
        if folder == "srv" and name.endswith(EVENT_TYPE_SUFFIX):
            return "ros2idl", _service_event_definition(root)
        if folder == "action" and (generated := _action_idl(package, name)) is not None:
            return "ros2idl", _action_definition(root, generated)
        try:
            return "ros2msg", _full_text(type_name, ".msg", "MSG")
        except MessageDefinitionNotFoundError:
            pass
        return "ros2idl", f"{_SEPARATOR}IDL: {root}\n" + _full_text(root, ".idl", "IDL")
    except MessageDefinitionNotFoundError as error:
        raise MessageDefinitionNotFoundError(
            f"no message definition for {type_name}: {error} (is its interface package installed?)"
        ) from None


#: The line of a ``.srv`` file between the request and the response.
_SRV_SEPARATOR = re.compile(r"^---[ \t]*\r?$\n?", re.MULTILINE)


@cache
def service_definitions(service: str) -> tuple[str, str]:
    """The ``ros2msg`` texts of ``pkg/srv/Name``'s request and response, each followed by its dependencies
    like a message's (what Foxglove reads to encode a service call and decode its answer).

    Raises:
        MessageDefinitionNotFoundError: no ``.srv`` file for the service, or no ``.msg`` for a dependency.
        ValueError: ``service`` is not a ``pkg/srv/Name`` name, or its file has no ``---`` line.
    """
    package, folder, name = _split_type_name(service)
    if folder != "srv":
        raise ValueError(f"not a service type name (expected 'pkg/srv/Name'): {service!r}")
    parts = _SRV_SEPARATOR.split(_read_definition(service, ".srv"), maxsplit=1)
    if len(parts) != 2:
        raise ValueError(f"the .srv file of {service} has no '---' line")
    request, response = (_full_text(f"{package}/srv/{name}_{part}", ".msg", "MSG", root_text=text)
                         for part, text in zip(("Request", "Response"), parts))
    return request, response


@cache
def type_hash(type_name: str) -> str:
    """Return the ``RIHS01_<sha256>`` type hash that rosidl generated for a type.

    Publishers announce this hash in their endpoint info; when none is at hand (no publisher seen
    yet), the hash of the locally installed type is the same value for an identical definition.
    A service event type ``pkg/srv/Name_Event`` has no ``.json`` of its own: rosidl lists its hash
    in the service's ``pkg/srv/Name.json``.

    Raises:
        MessageDefinitionNotFoundError: the package has no ``<Type>.json`` type description.
        ValueError: ``type_name`` is not a ROS type name.
    """
    package, folder, name = _split_type_name(type_name)
    path = _find_file(package, folder, name, ".json")
    if path is None and folder == "srv" and name.endswith(EVENT_TYPE_SUFFIX):
        path = _find_file(package, folder, name[: -len(EVENT_TYPE_SUFFIX)], ".json")
    if path is None and folder == "action" and _action_idl(package, name) is not None:
        path = _find_file(package, folder, _action_of(name), ".json")
    if path is None:
        raise MessageDefinitionNotFoundError(f"no type description (.json) for {type_name}")
    with open(path, encoding="utf-8") as file:
        description = json.load(file)
    full_name = f"{package}/{folder}/{name}"
    try:
        return next(str(entry["hash_string"]) for entry in description["type_hashes"]
                    if entry["type_name"] == full_name)
    except (KeyError, TypeError, StopIteration):
        raise MessageDefinitionNotFoundError(f"{path} holds no type hash for {full_name}") from None


def type_hash_of_definition(type_name: str, definition: tuple[str, str], recorded: str = "") -> str:
    """The type hash that agrees with ``definition`` (``(encoding, text)``) of ``type_name``: the installed type's
    when ``definition`` is the installed one, else ``recorded`` (the hash that came with the definition, e.g. from
    another bag; empty when it had none, as in bags of rosbag2 before Iron). Readers such as ``rosbags`` check a
    topic's hash against the definition its bag carries."""
    try:
        return type_hash(type_name) if message_definition(type_name) == definition else recorded
    except (MessageDefinitionNotFoundError, ValueError):
        return recorded


def message_class(type_name: str) -> Any:
    """The Python class of ``pkg/msg/Type`` or of a service event ``pkg/srv/Name_Event``.

    Raises ImportError / AttributeError if it is not installed, ValueError for a name of another form.
    """
    parts = type_name.split("/")
    if len(parts) != 3:
        raise ValueError(f"not a ROS message type name (pkg/msg/Type): {type_name!r}")
    package, folder, name = parts
    if folder == "srv":
        return event_class(type_name)
    module = importlib.import_module(f"{package}.{folder}")
    if folder == "action" and not hasattr(module, name) and name.endswith("_FeedbackMessage"):
        return getattr(module, name[: -len("_FeedbackMessage")]).Impl.FeedbackMessage
    return getattr(module, name)
