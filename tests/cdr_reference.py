"""An independent reference CDR encoder for the tests of the fast serializer and deserializer.

Plain CDR (XCDR1) written from the message's own field list (``get_fields_and_field_types``), in either
byte order, with zeros for alignment padding and the positions of that padding recorded: rclpy leaves
padding uninitialized, so comparisons with its bytes must skip exactly those positions.
"""
from __future__ import annotations

import struct
from typing import Any

#: The encapsulation header of plain CDR in each byte order.
ENCAPSULATION = {"<": b"\x00\x01\x00\x00", ">": b"\x00\x00\x00\x00"}

_PRIMITIVES = {
    "boolean": "?", "octet": "B", "byte": "B", "char": "B", "uint8": "B", "int8": "b", "uint16": "H",
    "int16": "h", "uint32": "I", "int32": "i", "uint64": "Q", "int64": "q", "float": "f", "double": "d",
}


class Reference:
    """Plain CDR from the message's own field list; padding is zero and its positions are recorded."""

    def __init__(self, byte_order: str = "<") -> None:
        self.byte_order = byte_order
        self.body = bytearray()
        self.padding: list[int] = []  # positions in the whole message (after the 4-byte header)

    def align(self, size: int) -> None:
        while len(self.body) % size:
            self.padding.append(4 + len(self.body))
            self.body.append(0)

    def value(self, type_name: str, value: Any) -> None:
        if type_name in _PRIMITIVES:
            fmt = _PRIMITIVES[type_name]
            self.align(struct.calcsize(fmt))
            self.body += struct.pack(self.byte_order + fmt, value)
        elif type_name == "string":
            raw = value.encode().split(b"\x00")[0]  # a C string ends at its first NUL
            self.value("uint32", len(raw) + 1)
            self.body += raw + b"\x00"
        elif type_name == "sequence<uint8>":
            self.value("uint32", len(value))
            self.body += bytes(value)
        elif type_name.startswith("sequence<"):
            self.value("uint32", len(value))
            for element in value:
                self.value(type_name[len("sequence<"):-1], element)
        elif type_name.endswith("]"):  # a fixed-size array: the elements (of any shape, in C order), no length
            for element in getattr(value, "flat", value):
                self.value(type_name[:type_name.index("[")], element)
        elif "/" in type_name:
            self.message(value)
        else:
            raise NotImplementedError(type_name)

    def message(self, msg: Any) -> None:
        for name, type_name in msg.get_fields_and_field_types().items():
            self.value(type_name, getattr(msg, name))


def reference(msg: Any, byte_order: str = "<") -> tuple[bytes, list[int]]:
    """``msg`` in plain CDR of ``byte_order`` (``<`` or ``>``), and the positions of its padding."""
    encoder = Reference(byte_order)
    encoder.message(msg)
    return ENCAPSULATION[byte_order] + bytes(encoder.body), encoder.padding
