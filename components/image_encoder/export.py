"""``ipc-component bag export``: a recorded compressed image topic as files other programs open, never re-encoded.

* ``foxglove_msgs/CompressedVideo`` -> an MP4 file (H.264 as ``avc1``, H.265 as ``hev1``: its parameter sets stay
  in the samples as recorded, AV1 as ``av01``). FFmpeg's raw-stream demuxer reads the recorded access units as
  one stream (its parser finds the keyframes and parameter sets, as ``ffmpeg -i x.h264 -c copy x.mp4`` does; no
  parser of our own) and the MP4 muxer stores its packets as they are. Each sample is one message, timed by the
  message's ``timestamp`` relative to the first, in 1/90000 s, each later than the one before by at least the
  stream's frame interval (frames stamped in a burst are spread: components/image_encoder/frame_times.py; the
  stamps are read in a first pass). The frames before the first keyframe cannot be decoded by anyone and are
  left out, counted.
* ``sensor_msgs/CompressedImage`` -> ``OUT_DIR/000001.jpg``, ``000002.jpg``... (``.png`` for PNG), each file
  the recorded bytes as they are, numbered in log-time order; for compressedDepth, the 16-bit PNG after
  image_transport's configuration header.

The bag is read with baglib (which knows nothing of codecs); this module is the codec side, beside the encoder's.
"""
from __future__ import annotations

import fractions
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import av

from baglib.format.cdr_read import deserialize
from baglib.format.message_definitions import message_class
from baglib.read.reader import BagReader, BagReadError, Connection
from components.image_encoder import compressed_depth
from components.image_encoder.decoding import still_kind
from components.image_encoder.frame_times import frame_times

#: CompressedVideo ``format`` -> FFmpeg's demuxer of the raw stream.
VIDEO_DEMUXERS = {"h264": "h264", "h265": "hevc", "av1": "obu"}
VIDEO_TYPE = "foxglove_msgs/msg/CompressedVideo"
STILL_TYPE = "sensor_msgs/msg/CompressedImage"
#: MP4 sample times: the usual 90 kHz video clock.
TIME_BASE = fractions.Fraction(1, 90_000)
_EXTENSIONS = {"jpeg": "jpg", "png": "png", compressed_depth.TRANSPORT: "png"}
#: How the summary names what was written, by kind.
_NAMES = {"jpeg": "JPEG", "png": "PNG", compressed_depth.TRANSPORT: "PNG (compressedDepth)",
          "jpeg, png": "JPEG and PNG", "": ""}


class ExportError(ValueError):
    """What cannot be exported, and why (the topic, its type, an output that exists, damaged data)."""


@dataclass
class ExportReport:
    """What an export wrote."""

    topic: str
    output: Path
    kind: str              # the video format (h264, h265, av1) or the still format (jpeg, png)
    written: int = 0       # frames in the MP4, or files
    skipped: int = 0       # video frames before the first keyframe

    def text(self) -> str:
        """``Wrote 1 MP4 file (154 frames) of ...`` or ``Wrote 12 JPEG files of ...``: what the output holds."""
        if self.kind in VIDEO_DEMUXERS:
            what = f"1 MP4 file ({_count(self.written, 'frame')}) of {self.topic} ({self.kind})"
        else:
            what = f"{_count(self.written, f'{_NAMES[self.kind]} file'.lstrip())} of {self.topic}"
        skipped = f"; {_count(self.skipped, 'frame')} before the first keyframe left out" if self.skipped else ""
        return f"Wrote {what} to {self.output}, as recorded (no re-encoding){skipped}"


def _count(number: int, noun: str) -> str:
    return f"{number} {noun}{'' if number == 1 else 's'}"


def export_topic(bag: str | os.PathLike[str], topic: str, output: str | os.PathLike[str]) -> ExportReport:
    """Export ``topic`` of ``bag`` to ``output``: an MP4 file for video, a directory of pictures for stills."""
    output = Path(output)
    try:
        with BagReader(bag) as reader:
            connection = _connection(reader, topic)
            video = connection.msgtype == VIDEO_TYPE
            if output.exists() and (video or not output.is_dir() or any(output.iterdir())):
                raise ExportError(f"'{output}' exists: name a new file (video) or a new or empty directory "
                                  "(stills)")
            def messages() -> Iterator[Any]:
                return (deserialize(m.data, message_class(connection.msgtype)) for m in reader.messages([topic]))

            if not video:
                return _pictures(messages(), topic, output)
            times = frame_times([_stamp_ns(message) for message in messages()])
            return _remux(messages(), topic, output, times)
    except BagReadError as exc:
        raise ExportError(f"cannot read {bag}: {exc}") from None


def _connection(reader: BagReader, topic: str) -> Connection:
    compressed = sorted({c.topic for c in reader.connections if c.msgtype in (VIDEO_TYPE, STILL_TYPE)})
    found = [c for c in reader.connections if c.topic == topic]
    if not found:
        raise ExportError(f"the bag has no topic '{topic}' (its compressed image topics: "
                          f"{', '.join(compressed) or 'none'})")
    if found[0].msgtype not in (VIDEO_TYPE, STILL_TYPE):
        raise ExportError(f"'{topic}' is a {found[0].msgtype}; export takes {VIDEO_TYPE} or {STILL_TYPE}")
    return found[0]


def _pictures(messages: Iterator[Any], topic: str, output: Path) -> ExportReport:
    output.mkdir(parents=True, exist_ok=True)
    report = ExportReport(topic, output, "")
    for message in messages:
        try:
            kind = still_kind(message.format)
            data = bytes(message.data)
            if kind == compressed_depth.TRANSPORT:
                data = compressed_depth.png_of(message.format, data)
        except ValueError as exc:  # a DecodeError, or a compressedDepth message without its PNG
            raise ExportError(f"message {report.written + 1} of '{topic}': {exc}") from None
        report.kind = kind if report.kind in ("", kind) else "jpeg, png"
        report.written += 1
        (output / f"{report.written:06d}.{_EXTENSIONS[kind]}").write_bytes(data)
    return report


class _AccessUnits:
    """The recorded access units as one byte stream for FFmpeg's demuxer (a file-like ``read``)."""

    def __init__(self, messages: Iterator[Any], topic: str) -> None:
        self._messages = messages
        self._topic = topic
        self._pending = bytearray()
        self.format = ""

    def first_format(self) -> str:
        """The video format of the first message (read ahead, kept for the demuxer)."""
        self._take()
        return self.format

    def _take(self) -> bool:
        message = next(self._messages, None)
        if message is None:
            return False
        if self.format and message.format != self.format:
            raise ExportError(f"'{self._topic}' changes format from {self.format} to {message.format}")
        self.format = message.format
        self._pending += message.data
        return True

    def read(self, size: int) -> bytes:
        while len(self._pending) < size and self._take():
            pass
        chunk = bytes(self._pending[:size])
        del self._pending[:size]
        return chunk


def _stamp_ns(message: Any) -> int:
    return message.timestamp.sec * 1_000_000_000 + message.timestamp.nanosec


def _remux(messages: Iterator[Any], topic: str, output: Path, times: list[float]) -> ExportReport:
    """``messages`` remuxed into the MP4 file ``output``, message ``i`` at ``times[i]`` (ns)."""
    units = _AccessUnits(messages, topic)
    video_format = units.first_format()
    if video_format not in VIDEO_DEMUXERS:
        raise ExportError(f"'{topic}' has no frames" if not video_format else
                          f"'{topic}' is {video_format!r} video; MP4 export takes {', '.join(VIDEO_DEMUXERS)}")
    report = ExportReport(topic, output, video_format)
    try:
        with av.open(units, format=VIDEO_DEMUXERS[video_format]) as source, av.open(
                str(output), "w", format="mp4") as target:
            _copy_packets(source, target, times, report)
    except av.FFmpegError as exc:
        output.unlink(missing_ok=True)
        raise ExportError(f"the {video_format} stream of '{topic}' cannot be stored in MP4: {exc}") from None
    except ExportError:
        output.unlink(missing_ok=True)
        raise
    return report


def _copy_packets(source: Any, target: Any, times: list[float], report: ExportReport) -> None:
    """Every demuxed packet (one per message) into ``target``, at its message's time, from the first keyframe."""
    stream = target.add_stream_from_template(source.streams.video[0], opaque=True)  # the decoder: no encoder needed
    stream.time_base = TIME_BASE
    first_ns: float | None = None
    last_pts = duration = -1
    index = 0
    for packet in source.demux(source.streams.video[0]):
        if packet.size == 0:
            continue  # the demuxer's final empty packet
        if index == len(times):
            raise ExportError(f"FFmpeg's parser found more frames in '{report.topic}' than it has messages: "
                              "a message holds less than one access unit")
        time_ns, index = times[index], index + 1
        if first_ns is None and not packet.is_keyframe:
            report.skipped += 1
            continue
        first_ns = time_ns if first_ns is None else first_ns
        pts = max(round((time_ns - first_ns) * TIME_BASE.denominator / 1_000_000_000), last_pts + 1)
        duration = pts - last_pts if last_pts >= 0 else 3000
        packet.stream, packet.time_base = stream, TIME_BASE
        packet.pts = packet.dts = last_pts = pts
        packet.duration = duration
        target.mux(packet)
        report.written += 1
    if index < len(times):
        raise ExportError(f"FFmpeg's parser found fewer frames in '{report.topic}' than it has messages: a message "
                          "holds more than one access unit")
