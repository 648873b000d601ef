"""Temporary: the exact CDR size by serializing; replaced by the exact size walker (no serialization) at merge."""
from __future__ import annotations

from typing import Any

from rclpy.serialization import serialize_message


def serialized_size(msg: Any) -> int:
    """Bytes of ``msg``'s CDR serialization (with its 4-byte encapsulation header)."""
    return len(serialize_message(msg))
