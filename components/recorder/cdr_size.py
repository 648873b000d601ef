"""The exact size of a message's CDR serialization, as Fast DDS puts it in a sample.

``rclpy.serialization.serialize_message`` does not report the size of what it serialized: rmw_fastrtps
sets the length of the serialized message to its *estimate* of the size, which can exceed the bytes
actually written (an ``rcl_interfaces/ParameterEvent`` of 104 bytes comes back as 112, the last 8 bytes
zeros), and readers that check the length (rosbags: "CDR message size mismatch") reject the excess. This
module computes the true size from the message's type definition, so the recorder can cut the excess off
and account for its cache without serializing.

The encoding is the one rmw_fastrtps_cpp uses (checked byte for byte against raw subscriptions,
``tests/test_wire_exact.py``): XCDR1 little endian after a 4-byte encapsulation header; every primitive
aligned to its own size (8-byte types to 8) relative to the end of that header; ``string`` as a ``uint32``
length counting the terminating NUL, the UTF-8 bytes up to the first NUL and the NUL; ``wstring`` as a
``uint32`` count of UTF-16 code units (embedded NULs included, no terminator) and 4 bytes per code unit;
sequences as a ``uint32`` element count and the elements (no element alignment when empty); arrays as
their elements; nested messages inline. A sample ends right after the last field: no final padding (a
message carried between processes arrives padded to a multiple of 4 by the RTPS layer, but that padding
is not part of the serialized message). A message without fields still has its one-byte
``structure_needs_at_least_one_member`` field, so ``std_msgs/Empty`` takes 5 bytes.

Sizes are computed from a per-class plan built once from ``SLOT_TYPES``: runs of fixed-size fields
collapse into one table lookup, primitive sequences and arrays cost ``len() * size``, and only strings
and sequences of variable-size messages are visited element by element.
"""
from __future__ import annotations

import functools
import importlib
import operator
from collections.abc import Callable, Sequence
from typing import Any

from rosidl_parser import definition

__all__ = ["ENCAPSULATION_HEADER_SIZE", "serialized_size"]

#: Bytes of the CDR encapsulation header (``00 01 00 00``) in front of the body.
ENCAPSULATION_HEADER_SIZE = 4

#: Serialized size (and alignment) of each primitive type that can appear in a .msg or .srv definition.
_PRIMITIVE_SIZES = {
    "boolean": 1, "octet": 1, "char": 1, "uint8": 1, "int8": 1,
    "uint16": 2, "int16": 2,
    "uint32": 4, "int32": 4, "float": 4,
    "uint64": 8, "int64": 8, "double": 8,
}
#: Alignments repeat with period 8, so a fixed-size part's size depends only on its start offset mod 8.
_PERIOD = 8
#: Bytes a fixed-size part occupies (padding included) when it starts at an offset ``o``: ``table[o % 8]``.
Table = tuple[int, ...]
#: One variable-size field: the offset after it, given the message and the offset it starts at.
Step = Callable[[Any, int], int]


def serialized_size(msg: Any) -> int:
    """The size in bytes of ``msg``'s serialized form, encapsulation header included.

    Exactly the length of the sample a raw subscription receives for ``msg`` from a publisher in the same
    process, for any ROS 2 message object.
    """
    return ENCAPSULATION_HEADER_SIZE + _layout(type(msg)).end(msg, 0)


def _align(offset: int, size: int) -> int:
    """``offset`` rounded up to a multiple of ``size`` (a power of two)."""
    return (offset + size - 1) & -size


def _primitive_table(size: int, count: int = 1) -> Table:
    """``count`` consecutive primitives of ``size`` bytes, the first aligned to its size."""
    return tuple(_align(start, size) - start + size * count for start in range(_PERIOD))


def _then(first: Table, second: Table) -> Table:
    """The table of ``first`` followed by ``second``."""
    return tuple(first[start] + second[(start + first[start]) % _PERIOD] for start in range(_PERIOD))


def _repeat(table: Table, offset: int, count: int) -> int:
    """The offset after ``count`` consecutive fixed-size parts of ``table`` starting at ``offset``.

    The offset mod 8 cycles after at most 8 parts; whole cycles are added at once, so a sequence of a
    million points costs a handful of steps.
    """
    seen: dict[int, tuple[int, int]] = {}
    done = 0
    while done < count:
        phase = offset % _PERIOD
        if phase in seen:
            first_done, first_offset = seen[phase]
            cycles = (count - done) // (done - first_done)
            offset += cycles * (offset - first_offset)
            done += cycles * (done - first_done)
            seen.clear()
            if done == count:
                break
            phase = offset % _PERIOD
        seen[phase] = (done, offset)
        offset += table[phase]
        done += 1
    return offset


def _string_end(value: str, offset: int) -> int:
    """After a ``string``: the C conversion keeps the UTF-8 bytes up to the first NUL and adds one NUL."""
    nul = value.find("\x00")
    if nul >= 0:
        value = value[:nul]
    length = len(value) if value.isascii() else len(value.encode())
    return _align(offset, 4) + 4 + length + 1


def _wstring_end(value: str, offset: int) -> int:
    """After a ``wstring``: a count of UTF-16 code units, then each one as a 4-byte ``wchar_t``."""
    units = len(value) if value.isascii() else len(value.encode("utf-16-le")) // 2
    return _align(offset, 4) + 4 + 4 * units


class _Layout:
    """How to size one message class: a fixed table, or steps for the variable-size fields."""

    __slots__ = ("steps", "table")

    def __init__(self, table: Table | None, steps: Sequence[Step]) -> None:
        self.table = table
        self.steps = tuple(steps)

    def end(self, msg: Any, offset: int) -> int:
        """The offset after ``msg`` serialized from ``offset`` (relative to the end of the header)."""
        if self.table is not None:
            return offset + self.table[offset % _PERIOD]
        for step in self.steps:
            offset = step(msg, offset)
        return offset


def _message_class(namespaced: definition.NamespacedType) -> type:
    """The Python class of a nested message type (``pkg/msg/Name`` or a service's ``pkg/srv/Name_Request``)."""
    return getattr(importlib.import_module(".".join(namespaced.namespaces)), namespaced.name)


def _fixed_table(slot: definition.AbstractType) -> Table | None:
    """The table of a fixed-size type, or ``None`` if its size depends on the values."""
    if isinstance(slot, definition.BasicType):
        return _primitive_table(_primitive_size(slot))
    if isinstance(slot, definition.NamespacedType):
        return _layout(_message_class(slot)).table
    if isinstance(slot, definition.Array):
        element = slot.value_type
        if isinstance(element, definition.BasicType):
            return _primitive_table(_primitive_size(element), slot.size)
        table = _fixed_table(element)
        if table is None:
            return None
        combined = table
        for _ in range(slot.size - 1):
            combined = _then(combined, table)
        return combined
    return None  # strings and sequences


def _primitive_size(slot: definition.BasicType) -> int:
    """The size of a primitive; ``wchar`` and ``long double`` (IDL-only types) are not supported."""
    try:
        return _PRIMITIVE_SIZES[slot.typename]
    except KeyError:
        raise TypeError(f"serialized_size does not support the IDL type {slot.typename!r}") from None


def _element_end(slot: definition.AbstractType) -> Callable[[Any, int], int]:
    """Sizer of one element of a variable-size type: ``(value, offset) -> offset after it``."""
    if isinstance(slot, definition.AbstractString):
        return _string_end
    if isinstance(slot, definition.AbstractWString):
        return _wstring_end
    if isinstance(slot, definition.NamespacedType):
        return _layout(_message_class(slot)).end
    if isinstance(slot, definition.Array):
        return _elements_end(slot.value_type)
    if isinstance(slot, definition.AbstractSequence):
        return _sequence_end(slot.value_type)
    raise TypeError(f"serialized_size does not support {slot!r}")


def _elements_end(element: definition.AbstractType) -> Callable[[Any, int], int]:
    """Sizer of consecutive elements (an array's or a sequence's), given as one iterable value."""
    table = _fixed_table(element)
    if table is not None:
        if isinstance(element, definition.BasicType):
            size = _primitive_size(element)
            return lambda values, offset: _align(offset, size) + size * len(values) if len(values) else offset
        return lambda values, offset: _repeat(table, offset, len(values))
    end = _element_end(element)

    def elements_end(values: Any, offset: int) -> int:
        for value in values:
            offset = end(value, offset)
        return offset

    return elements_end


def _sequence_end(element: definition.AbstractType) -> Callable[[Any, int], int]:
    """Sizer of a sequence: the ``uint32`` count, then the elements."""
    elements_end = _elements_end(element)
    return lambda values, offset: elements_end(values, _align(offset, 4) + 4)


def _field_step(name: str, slot: definition.AbstractType) -> Step:
    """The step of one variable-size field: read the attribute, size the value."""
    end = _element_end(slot)
    value = operator.attrgetter(name)
    return lambda msg, offset: end(value(msg), offset)


def _fixed_step(table: Table) -> Step:
    """A run of fixed-size fields as one step."""
    return lambda msg, offset: offset + table[offset % _PERIOD]


@functools.cache
def _layout(cls: type) -> _Layout:
    """The plan for ``cls``, built once: consecutive fixed-size fields merged into one table."""
    if not cls.SLOT_TYPES:  # the C struct (and so the sample) has a uint8 structure_needs_at_least_one_member
        return _Layout(_primitive_table(_PRIMITIVE_SIZES["uint8"]), ())
    steps: list[Step] = []
    run: Table | None = None
    for name, slot in zip(cls.get_fields_and_field_types(), cls.SLOT_TYPES, strict=True):
        table = _fixed_table(slot)
        if table is not None:
            run = table if run is None else _then(run, table)
            continue
        if run is not None:
            steps.append(_fixed_step(run))
            run = None
        steps.append(_field_step(name, slot))
    if not steps:
        return _Layout(run, ())
    if run is not None:
        steps.append(_fixed_step(run))
    return _Layout(None, steps)
