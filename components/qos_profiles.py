"""QoS profiles as rosbag2 writes them: ``{history: keep_last, depth: 10, reliability: reliable, ...}``.

The same mapping appears in ``qos_profile_overrides_path`` files (recorder and player) and, once per offering
publisher, in a bag's ``offered_qos_profiles``; this module turns either into rclpy's QoSProfile.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy

from component_container.request_file import read_yaml

__all__ = ["load_qos_overrides", "profile_from_dict"]

_POLICIES = {
    "history": HistoryPolicy,
    "reliability": ReliabilityPolicy,
    "durability": DurabilityPolicy,
    "liveliness": LivelinessPolicy,
}
_DURATIONS = ("deadline", "lifespan", "liveliness_lease_duration")
_KEYS = ("depth", *_POLICIES, *_DURATIONS, "avoid_ros_namespace_conventions")


def absolute_topic(topic: str) -> str:
    return topic if topic.startswith("/") else f"/{topic}"


def load_qos_overrides(parameter: str, path: Path | None, default_depth: int) -> dict[str, QoSProfile]:
    """Parse a rosbag2 QoS override file: ``{topic: {history: keep_last, depth: 10, ...}}``.

    ``path`` is what the node's ``resolve_path`` made of ``parameter`` (None: no file). The file may be anything
    an anonymous caller pointed at, so errors give the parameter and the entry's position, never a key or a
    value from the file.
    """
    if path is None:
        return {}
    document = read_yaml(parameter, path) or {}
    if not isinstance(document, dict) or not all(isinstance(topic, str) for topic in document):
        raise ValueError(f"parameter '{parameter}': the file must map topic names to QoS profiles")
    overrides: dict[str, QoSProfile] = {}
    for position, (topic, spec) in enumerate(document.items(), 1):
        try:
            overrides[absolute_topic(topic)] = profile_from_dict(spec, default_depth)
        except (ValueError, TypeError, KeyError, AttributeError, OverflowError):
            raise ValueError(
                f"parameter '{parameter}': entry {position} is not a valid QoS profile (expected a mapping of "
                f"{', '.join(_KEYS)} with rosbag2's values)") from None
    return overrides


def profile_from_dict(spec: Any, default_depth: int) -> QoSProfile:
    """One rosbag2 QoS mapping as a QoSProfile; raises TypeError/KeyError/ValueError on anything else."""
    if not isinstance(spec, dict):
        raise TypeError("a QoS profile must be a mapping")
    kwargs: dict[str, Any] = {"depth": int(spec.get("depth", default_depth))}
    for key, value in spec.items():
        if key in _POLICIES:
            kwargs[key] = _POLICIES[key][str(value).upper()]
        elif key in _DURATIONS:
            kwargs[key] = Duration(seconds=int(value.get("sec", 0)), nanoseconds=int(value.get("nsec", 0)))
        elif key == "avoid_ros_namespace_conventions":
            kwargs[key] = bool(value)
        elif key != "depth":
            raise KeyError("unknown key")
    return QoSProfile(**kwargs)
