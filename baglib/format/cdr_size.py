"""The exact size and padding of a message's CDR serialization, as Fast DDS puts it in a sample.

``rclpy.serialization.serialize_message`` does not report the size of what it serialized: rmw_fastrtps
sets the length of the serialized message to its *estimate* of the size, which can exceed the bytes
actually written (an ``rcl_interfaces/ParameterEvent`` of 104 bytes comes back as 112, the last 8 bytes
zeros), and readers that check the length (rosbags: "CDR message size mismatch") reject the excess. This
module computes the true size from the message's type definition, so the recorder can cut the excess off
and account for its cache without serializing, and where the alignment padding is, which serializers leave
uninitialized (rclpy always; Fast DDS once it reuses a sample buffer), so the recorder can zero it.

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
collapse into one table lookup, primitive sequences and arrays cost ``len() * size``, sequences of
fixed-size messages a few steps, and only strings and variable-size messages are visited one by one.
"""
from __future__ import annotations

import functools
import importlib
import operator
from collections.abc import Callable, Iterator, Sequence
from typing import Any, NamedTuple

from rosidl_parser import definition

__all__ = ["ENCAPSULATION_HEADER_SIZE", "CdrLayout", "serialized_layout", "serialized_size"]

#: Bytes of the CDR encapsulation header (``00 01 00 00``) in front of the body.
ENCAPSULATION_HEADER_SIZE = 4

#: Serialized size (and alignment) of each primitive type that can appear in a .msg or .srv definition.
_PRIMITIVE_SIZES = {
    "boolean": 1, "octet": 1, "char": 1, "uint8": 1, "int8": 1,
    "uint16": 2, "int16": 2,
    "uint32": 4, "int32": 4, "float": 4,
    "uint64": 8, "int64": 8, "double": 8,
}
#: Alignments repeat with period 8, so a fixed-size part's layout depends only on its start offset mod 8.
_PERIOD = 8
#: Alignment padding found by a walk: ``(start, end)`` offsets, or ``None`` when only the size is wanted.
Gaps = list[tuple[int, int]] | None
#: Sizer of one value: the offset after it, given the value, its start offset and where to note padding.
Sizer = Callable[[Any, int, Gaps], int]


class CdrLayout(NamedTuple):
    """Where a serialized message's bytes are: its size and its alignment padding."""

    size: int
    #: ``(start, end)`` byte ranges of alignment padding, positions in the whole serialized message.
    padding: list[tuple[int, int]]


def serialized_size(msg: Any) -> int:
    """The size in bytes of ``msg``'s serialized form, encapsulation header included.

    Exactly the length of the sample a raw subscription receives for ``msg`` from a publisher in the same
    process, for any ROS 2 message object (built from .msg/.srv definitions).
    """
    return ENCAPSULATION_HEADER_SIZE + _layout(type(msg)).end(msg, 0, None)


def serialized_layout(msg: Any) -> CdrLayout:
    """:func:`serialized_size` and the positions of the alignment padding, in one walk of ``msg``.

    Serializers leave padding uninitialized (rclpy's ``serialize_message`` and Fast DDS alike, whose
    samples carry stale bytes there once it reuses a buffer); knowing where it is lets a writer zero it.
    """
    gaps: list[tuple[int, int]] = []
    end = _layout(type(msg)).end(msg, 0, gaps)  # offsets relative to the end of the header, as alignment is
    header = ENCAPSULATION_HEADER_SIZE
    return CdrLayout(header + end, [(start + header, stop + header) for start, stop in gaps])


def _aligned(offset: int, size: int, gaps: Gaps) -> int:
    """``offset`` rounded up to a multiple of ``size`` (a power of two), the padding noted in ``gaps``."""
    aligned = (offset + size - 1) & -size
    if gaps is not None and aligned != offset:
        gaps.append((offset, aligned))
    return aligned


class _Fixed:
    """A fixed-size part (primitives, arrays of them, messages of those): its layout for each start phase.

    ``sizes[p]`` is the bytes it occupies, padding included, when it starts at an offset ``o`` with
    ``o % 8 == p``; ``gaps[p]`` the padding in it, relative to ``o``.
    """

    __slots__ = ("gaps", "sizes")

    def __init__(self, sizes: Sequence[int], gaps: Sequence[tuple[tuple[int, int], ...]]) -> None:
        self.sizes = tuple(sizes)
        self.gaps = tuple(gaps)

    @classmethod
    def primitives(cls, size: int, count: int = 1) -> _Fixed:
        """``count`` consecutive primitives of ``size`` bytes, the first aligned to its size."""
        pads = [(-phase) % size for phase in range(_PERIOD)]
        return cls([pad + size * count for pad in pads], [((0, pad),) if pad else () for pad in pads])

    def then(self, other: _Fixed) -> _Fixed:
        """This part followed by ``other``."""
        sizes, gaps = [], []
        for phase, (size, own) in enumerate(zip(self.sizes, self.gaps, strict=True)):
            after = (phase + size) % _PERIOD
            sizes.append(size + other.sizes[after])
            gaps.append(own + tuple((size + start, size + stop) for start, stop in other.gaps[after]))
        return _Fixed(sizes, gaps)

    def end(self, offset: int, gaps: Gaps) -> int:
        """The offset after this part, starting at ``offset``."""
        phase = offset % _PERIOD
        if gaps is not None:
            for start, stop in self.gaps[phase]:
                gaps.append((offset + start, offset + stop))
        return offset + self.sizes[phase]

    def repeat_end(self, offset: int, count: int, gaps: Gaps) -> int:
        """The offset after ``count`` consecutive parts.

        The start phase cycles after at most 8 parts; whole cycles without padding (or all of them when
        only the size is wanted) are added at once, so a sequence of a million points costs a few steps.
        """
        seen: dict[int, tuple[int, int, int]] = {}
        done = 0
        while done < count:
            phase = offset % _PERIOD
            if phase in seen:
                first_done, first_offset, first_gaps = seen.pop(phase)
                if gaps is None or len(gaps) == first_gaps:
                    cycles = (count - done) // (done - first_done)
                    offset += cycles * (offset - first_offset)
                    done += cycles * (done - first_done)
                    seen.clear()
                    continue
            seen[phase] = (done, offset, 0 if gaps is None else len(gaps))
            offset = self.end(offset, gaps)
            done += 1
        return offset


def _string_end(value: str, offset: int, gaps: Gaps) -> int:
    """After a ``string``: the C conversion keeps the UTF-8 bytes up to the first NUL and adds one NUL."""
    if "\x00" in value:
        value = value[:value.index("\x00")]
    length = len(value) if value.isascii() else len(value.encode())
    return (_aligned(offset, 4, gaps) if offset & 3 else offset) + 4 + length + 1


def _wstring_end(value: str, offset: int, gaps: Gaps) -> int:
    """After a ``wstring``: a count of UTF-16 code units, then each one as a 4-byte ``wchar_t``."""
    units = len(value) if value.isascii() else len(value.encode("utf-16-le")) // 2
    return (_aligned(offset, 4, gaps) if offset & 3 else offset) + 4 + 4 * units


class _Layout:
    """How to walk one message class: a fixed part, or steps for runs of fields."""

    __slots__ = ("fixed", "steps")

    def __init__(self, fixed: _Fixed | None, steps: Sequence[Sizer]) -> None:
        self.fixed = fixed
        self.steps = tuple(steps)

    def end(self, msg: Any, offset: int, gaps: Gaps) -> int:
        """The offset after ``msg`` serialized from ``offset`` (relative to the end of the header)."""
        if self.fixed is not None:
            return self.fixed.end(offset, gaps)
        for step in self.steps:
            offset = step(msg, offset, gaps)
        return offset


def _message_class(namespaced: definition.NamespacedType) -> type:
    """The Python class of a nested message type (``pkg/msg/Name`` or a service's ``pkg/srv/Name_Request``)."""
    return getattr(importlib.import_module(".".join(namespaced.namespaces)), namespaced.name)


def _primitive_size(slot: definition.BasicType) -> int:
    """The size of a primitive; ``wchar`` and ``long double`` (IDL-only types) are not supported."""
    try:
        return _PRIMITIVE_SIZES[slot.typename]
    except KeyError:
        raise TypeError(f"serialized_size does not support the IDL type {slot.typename!r}") from None


def _fixed(slot: definition.AbstractType) -> _Fixed | None:
    """The layout of a fixed-size type, or ``None`` if its size depends on the values."""
    if isinstance(slot, definition.BasicType):
        return _Fixed.primitives(_primitive_size(slot))
    if isinstance(slot, definition.NamespacedType):
        return _layout(_message_class(slot)).fixed
    if isinstance(slot, definition.Array):
        element = slot.value_type
        if isinstance(element, definition.BasicType):
            return _Fixed.primitives(_primitive_size(element), slot.size)
        fixed = _fixed(element)
        if fixed is None:
            return None
        combined = fixed
        for _ in range(slot.size - 1):
            combined = combined.then(fixed)
        return combined
    return None  # strings and sequences


def _sizer(slot: definition.AbstractType) -> Sizer:
    """Sizer of a value of a variable-size type."""
    if isinstance(slot, definition.AbstractString):
        return _string_end
    if isinstance(slot, definition.AbstractWString):
        return _wstring_end
    if isinstance(slot, definition.NamespacedType):
        return _layout(_message_class(slot)).end
    if isinstance(slot, definition.Array):
        return _elements_sizer(slot.value_type)
    if isinstance(slot, definition.AbstractSequence):
        return _sequence_sizer(slot.value_type)
    raise TypeError(f"serialized_size does not support {slot!r}")


def _elements_sizer(element: definition.AbstractType) -> Sizer:
    """Sizer of consecutive elements (an array's or a sequence's), given as one iterable value."""
    if isinstance(element, definition.BasicType):
        size = _primitive_size(element)
        return lambda values, offset, gaps: _aligned(offset, size, gaps) + size * len(values) if len(values) else offset
    fixed = _fixed(element)
    if fixed is not None:
        return lambda values, offset, gaps: fixed.repeat_end(offset, len(values), gaps)
    end = _sizer(element)

    def elements_end(values: Any, offset: int, gaps: Gaps) -> int:
        for value in values:
            offset = end(value, offset, gaps)
        return offset

    return elements_end


def _sequence_sizer(element: definition.AbstractType) -> Sizer:
    """Sizer of a sequence: the ``uint32`` count, then the elements."""
    elements_end = _elements_sizer(element)
    return lambda values, offset, gaps: elements_end(values, (_aligned(offset, 4, gaps) if offset & 3 else offset) + 4,
                                                     gaps)


def _field_step(path: str, slot: definition.AbstractType) -> Sizer:
    """The step of one variable-size field: read the attribute (a dotted path), size the value."""
    end = _sizer(slot)
    value = operator.attrgetter(path)
    return lambda msg, offset, gaps: end(value(msg), offset, gaps)


def _fixed_step(fixed: _Fixed) -> Sizer:
    """A run of fixed-size fields as one step (a table lookup when only the size is wanted)."""
    sizes = fixed.sizes
    return lambda msg, offset, gaps: offset + sizes[offset % _PERIOD] if gaps is None else fixed.end(offset, gaps)


_STRUCTURE_NEEDS_AT_LEAST_ONE_MEMBER = definition.BasicType("uint8")


def _flat_fields(cls: type, prefix: str = "") -> Iterator[tuple[str, definition.AbstractType]]:
    """``cls``'s fields with nested messages (not in sequences or arrays) replaced by their fields.

    Paths name the instance slots rclpy's generated classes keep a field's value in (``_header``), which
    read much faster than the properties in front of them, when the class has them. Flattening lets
    fixed-size fields on both sides of a message boundary merge into one run.
    """
    if not cls.SLOT_TYPES:  # the C struct (and so the sample) has a uint8 structure_needs_at_least_one_member
        yield prefix, _STRUCTURE_NEEDS_AT_LEAST_ONE_MEMBER
        return
    for name, slot in zip(cls.get_fields_and_field_types(), cls.SLOT_TYPES, strict=True):
        path = prefix + (f"_{name}" if f"_{name}" in cls.__slots__ else name)
        if isinstance(slot, definition.NamespacedType):
            yield from _flat_fields(_message_class(slot), path + ".")
        else:
            yield path, slot


@functools.cache
def _layout(cls: type) -> _Layout:
    """The plan for ``cls``, built once: consecutive fixed-size fields merged into one part."""
    steps: list[Sizer] = []
    run: _Fixed | None = None
    for path, slot in _flat_fields(cls):
        fixed = _fixed(slot)
        if fixed is not None:
            run = fixed if run is None else run.then(fixed)
            continue
        if run is not None:
            steps.append(_fixed_step(run))
            run = None
        steps.append(_field_step(path, slot))
    if not steps:
        return _Layout(run, ())
    if run is not None:
        steps.append(_fixed_step(run))
    return _Layout(None, steps)
