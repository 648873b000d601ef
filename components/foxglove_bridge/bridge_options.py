"""The Foxglove bridge's parameters: ``foxglove_bridge``'s names where they mean the same, checked at load.

==========================  ==================  ==========================================================
``port``                    8765                WebSocket port on ``address`` (0: any free port, logged)
``address``                 ``'127.0.0.1'``     the interface the server binds; anything but a loopback
                                                address exposes the graph to the network (docs/security.md)
``topic_whitelist``         ``['.*']``          regexes; a topic is advertised if one matches all of it
``param_whitelist``         ``['.*']``          regexes over ``/node.parameter`` names clients may get/set
``service_whitelist``       ``['.*']``          regexes over the service names clients may call
``include_hidden``          False               advertise hidden topics and services (a name part starting
                                                with ``_``)
``min_qos_depth``           1                   the bridge's subscription depth is the publishers' summed
``max_qos_depth``           25                  depth, clamped to [min_qos_depth, max_qos_depth]
``message_backlog_size``    32                  per-client outbox of the SDK server, in messages: when a
                                                client reads too slowly its oldest message is dropped
                                                (foxglove_bridge 3's name; its default of 1024 would let a
                                                stalled client hold 6 GB of 1080p frames)
``rate_limits``             ``['']``            ``REGEX=HZ`` entries: the first whose regex matches all of
                                                a topic caps that channel at HZ messages a second (e.g.
                                                ``'.*/image_raw=5'``); others are forwarded at full rate
``polling_interval``        1.0                 s between looks at the ROS graph (topics, the
                                                connection graph)
``use_sim_time``            False               (rclpy's) also: send ``/clock`` to clients as the server
                                                time, so a replay plays in Foxglove
``video.codec``             ``'h264'``          each Image topic is also offered as ``<image>/video``
                                                (foxglove_msgs/CompressedVideo) in this codec (h264, h265,
                                                av1 or an FFmpeg encoder name); ``''``: no video channels
``video.max_width``         640                 pixels; wider images are scaled down (0: the image's width)
``video.max_rate``          10.0                frames a second, by the images' stamps (0: every frame)
``video.quality``           -1                  the codec's CRF (-1: its default, image_encoder.codecs)
==========================  ==================  ==========================================================

Every number is checked against a range (the load service answers anyone on the ROS domain): a value outside
is a load error naming the parameter and its range.
"""
from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass
from typing import Any

from rclpy.node import Node

from components.bounds import Bounds
from components.image_encoder.codecs import STILLS, VIDEO_ENCODERS, CodecChoice, check_codec, choose
from components.node_parameters import clean, declare_defaults

DEFAULTS: dict[str, Any] = {
    "port": 8765,
    "address": "127.0.0.1",
    "topic_whitelist": [".*"],
    "param_whitelist": [".*"],
    "service_whitelist": [".*"],
    "include_hidden": False,
    "min_qos_depth": 1,
    "max_qos_depth": 25,
    "message_backlog_size": 32,
    "rate_limits": [""],
    "polling_interval": 1.0,
    "video.codec": "h264",
    "video.max_width": 640,
    "video.max_rate": 10.0,
    "video.quality": -1,
}

PORT = Bounds(0, 65535)
QOS_DEPTH = Bounds(1, 1000, "messages")
#: Per client: the SDK holds up to this many messages for a client that reads slowly (frames included).
BACKLOG = Bounds(1, 4096, "messages")
RATE_LIMIT = Bounds(0.01, 10000.0, "Hz")
POLLING_INTERVAL = Bounds(0.05, 60.0, "s")
VIDEO_WIDTH = Bounds(2, 16384, "pixels")
VIDEO_RATE = Bounds(0.01, 1000.0, "Hz")
#: Frames between two keyframes of a video channel (3 s at 10 Hz): what a client that lost a frame in its
#: outbox waits at most for a clean picture (a client that joins gets a keyframe at once).
VIDEO_KEYFRAME_INTERVAL = 30


@dataclass(frozen=True)
class RateLimit:
    """At most ``hz`` messages a second on the topics ``pattern`` matches (whole names, as in topic_whitelist)."""

    pattern: re.Pattern[str]
    hz: float


@dataclass(frozen=True)
class VideoOptions:
    """How the video channels encode: the codec, at most ``max_width`` pixels wide and ``max_rate`` Hz."""

    choice: CodecChoice
    max_width: int
    max_rate: float


@dataclass(frozen=True)
class BridgeOptions:
    port: int
    address: str
    topic_whitelist: tuple[re.Pattern[str], ...]
    param_whitelist: tuple[re.Pattern[str], ...]
    service_whitelist: tuple[re.Pattern[str], ...]
    include_hidden: bool
    min_qos_depth: int
    max_qos_depth: int
    message_backlog_size: int
    rate_limits: tuple[RateLimit, ...]
    polling_interval: float
    video: VideoOptions | None  # None: no video channels

    def rate_limit(self, topic: str) -> float:
        """The rate cap of ``topic`` in Hz; 0 for none."""
        return next((limit.hz for limit in self.rate_limits if limit.pattern.fullmatch(topic)), 0.0)

    def advertises(self, topic: str) -> bool:
        """Whether ``topic`` is in ``topic_whitelist`` (and not hidden, unless ``include_hidden``)."""
        return self._listed(topic, self.topic_whitelist)

    def offers_service(self, service: str) -> bool:
        """Whether ``service`` is in ``service_whitelist`` (and not hidden, unless ``include_hidden``)."""
        return self._listed(service, self.service_whitelist)

    def _listed(self, name: str, whitelist: tuple[re.Pattern[str], ...]) -> bool:
        if not self.include_hidden and any(part.startswith("_") for part in name.split("/")):
            return False
        return any(pattern.fullmatch(name) for pattern in whitelist)

    def exposes_parameter(self, name: str) -> bool:
        """Whether ``/node.parameter`` is in ``param_whitelist``."""
        return any(pattern.fullmatch(name) for pattern in self.param_whitelist)


def declare_options(node: Node) -> BridgeOptions:
    """Declare the parameters on ``node`` and return them checked; ValueError naming the parameter otherwise."""
    values = declare_defaults(node, DEFAULTS)
    PORT.check("'port'", values["port"])
    for name in ("min_qos_depth", "max_qos_depth"):
        QOS_DEPTH.check(f"'{name}'", values[name])
    if values["min_qos_depth"] > values["max_qos_depth"]:
        raise ValueError(f"parameter 'min_qos_depth' ({values['min_qos_depth']}) must not exceed 'max_qos_depth' "
                         f"({values['max_qos_depth']})")
    BACKLOG.check("'message_backlog_size'", values["message_backlog_size"])
    POLLING_INTERVAL.check("'polling_interval'", values["polling_interval"])
    return BridgeOptions(
        port=values["port"], address=_address(values["address"]),
        topic_whitelist=_patterns("topic_whitelist", clean(values["topic_whitelist"])),
        param_whitelist=_patterns("param_whitelist", clean(values["param_whitelist"])),
        service_whitelist=_patterns("service_whitelist", clean(values["service_whitelist"])),
        include_hidden=values["include_hidden"], min_qos_depth=values["min_qos_depth"],
        max_qos_depth=values["max_qos_depth"], message_backlog_size=values["message_backlog_size"],
        rate_limits=tuple(_rate_limit(entry) for entry in clean(values["rate_limits"])),
        polling_interval=values["polling_interval"], video=_video(values))


def _video(values: dict[str, Any]) -> VideoOptions | None:
    """The video channels' settings, the codec opened once (an encoder the machine lacks fails the load)."""
    codec = values["video.codec"].strip().lower()
    if not codec:
        return None
    if codec in STILLS:
        raise ValueError(f"parameter 'video.codec': {codec!r} is a still codec; video channels take "
                         f"{', '.join(VIDEO_ENCODERS)} or an FFmpeg video encoder name ('' for none)")
    choice = choose(codec, "", values["video.quality"], 0, VIDEO_KEYFRAME_INTERVAL, prefix="video.")
    check_codec(choice, prefix="video.")
    VIDEO_WIDTH.check("'video.max_width'", values["video.max_width"], zero_means="the image's width")
    VIDEO_RATE.check("'video.max_rate'", values["video.max_rate"], zero_means="every frame")
    return VideoOptions(choice, values["video.max_width"], values["video.max_rate"])


def _address(value: str) -> str:
    """An IP address to bind (names are not resolved: what is bound must be what the parameter says)."""
    try:
        return str(ipaddress.ip_address(value))
    except ValueError:
        raise ValueError(f"parameter 'address' must be an IPv4 or IPv6 address, got {value!r}") from None


def _patterns(name: str, values: list[str]) -> tuple[re.Pattern[str], ...]:
    patterns = []
    for value in values:
        try:
            patterns.append(re.compile(value))
        except re.error as exc:
            raise ValueError(f"parameter '{name}': {value!r} is not a valid regular expression ({exc})") from None
    return tuple(patterns)


def _rate_limit(entry: str) -> RateLimit:
    pattern, separator, rate = entry.rpartition("=")
    try:
        hz = float(rate)
    except ValueError:
        hz = float("nan")
    if not separator or not pattern:
        raise ValueError(f"parameter 'rate_limits' entries must be 'REGEX=HZ', got {entry!r}")
    RATE_LIMIT.check(f"'rate_limits' ({entry!r})", hz)
    return RateLimit(_patterns("rate_limits", [pattern])[0], hz)
