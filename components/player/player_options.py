"""The player's parameters: rosbag2 Jazzy's ``storage.*`` / ``play.*`` names, defaults and ranges.

Several bags play as one timeline (rosbag2 Kilted's ``ros2 bag play -i A -i B``) with ``storage.uris`` in place of
``storage.uri``, and optionally ``storage.storage_ids``, one per bag; rosbag2's component has no parameter for
that (only its command line does), so these two names are this player's.

They are read the way rosbag2_transport's ``get_play_options_from_node_params`` reads them, durations included:
``play.delay``, ``play.start_offset``, ``play.playback_duration``, ``play.playback_until_timestamp`` and
``play.wait_acked_timeout`` are each a ``.sec`` / ``.nsec`` pair, negative when either part is negative.
``play.message_order`` (Kilted's ``PlayOptions::message_order``) takes the names of rosbag2's ``MessageOrder``
values, as ``play.service_requests_source`` takes those of ``ServiceRequestsSource``.
``play.read_ahead_max_bytes`` is not rosbag2's: its read-ahead queue counts messages only, and 1000 1080p frames
are 6 GB. Neither are ``play.decode`` and ``play.decode_topics``: compressed image topics played also as
``sensor_msgs/Image`` (components/player/decoded_topics.py).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from rclpy.node import Node

from baglib.format.service_events import event_topic
from components.bounds import Bounds
from components.qos_profiles import absolute_topic
from components.node_parameters import action_names, clean, declare_defaults

_DURATIONS = {  # name -> (default sec, default nsec), from get_play_options_from_node_params
    "play.delay": (0, 0),
    "play.playback_duration": (-1, 0),
    "play.playback_until_timestamp": (0, -1),
    "play.start_offset": (0, 0),
    "play.wait_acked_timeout": (0, -1),
}
DEFAULTS: dict[str, Any] = {
    "storage.uri": "",
    "storage.uris": [""],
    "storage.storage_id": "",
    "storage.storage_ids": [""],
    "play.read_ahead_queue_size": 1000,
    "play.read_ahead_max_bytes": 256 * 1024 * 1024,
    "play.node_prefix": "",
    "play.rate": 1.0,
    "play.topics_to_filter": [""],
    "play.services_to_filter": [""],
    "play.regex_to_filter": "",
    "play.exclude_regex_to_filter": "",
    "play.exclude_topics_to_filter": [""],
    "play.exclude_services_to_filter": [""],
    "play.qos_profile_overrides_path": "",
    "play.loop": False,
    "play.topic_remapping_options": [""],
    "play.clock_publish_frequency": 0.0,
    "play.clock_publish_on_topic_publish": False,
    "play.clock_trigger_topics": [""],
    "play.start_paused": False,
    "play.disable_keyboard_controls": False,
    "play.disable_loan_message": False,
    "play.service_requests_source": "SERVICE_INTROSPECTION",
    "play.publish_service_request": False,
    "play.message_order": "RECEIVED_TIMESTAMP",
    # rosbag2 Kilted (ros2/rosbag2#1955): actions by name; their recorded goals sent to the live server.
    "play.actions_to_filter": [""],
    "play.exclude_actions_to_filter": [""],
    "play.send_actions_as_client": False,
    "play.decode": False,
    "play.decode_topics": [""],
    **{f"{name}.{part}": value for name, pair in _DURATIONS.items() for part, value in zip(("sec", "nsec"), pair)},
}
STORAGE_IDS = ("", "mcap", "sqlite3")
SERVICE_REQUEST_SOURCES = ("SERVICE_INTROSPECTION", "CLIENT_INTROSPECTION")
#: rosbag2_transport::MessageOrder (Kilted, #1876): play in receive-time or in publish-time order.
MESSAGE_ORDERS = ("RECEIVED_TIMESTAMP", "SENT_TIMESTAMP")
#: rosbag2: read_ahead_queue_size in [1, INT64_MAX]; more than a million queued messages is a memory bug here.
READ_AHEAD_QUEUE = Bounds(1, 1_000_000, "messages")
READ_AHEAD_BYTES = Bounds(1024 * 1024, 2**40, "bytes")
#: rosbag2 accepts rates down to 1e-6; the clock publisher's frequency likewise must leave the executor room.
RATE = Bounds(0.000001, 1_000_000, "x")
CLOCK_FREQUENCY = Bounds(0.001, 10_000, "Hz")
_NS_PER_S = 1_000_000_000
_MAX_SEC = (2**63 - 1) // _NS_PER_S - 1


@dataclass(frozen=True)
class PlayOptions:
    """What one ``components::Player`` plays and how (rosbag2_transport::PlayOptions plus the storage uris)."""

    uris: list[str]              # one bag, or several played as one timeline
    uri_parameter: str           # the parameter that named them, for errors
    storage_ids: list[str]       # one per bag ("": detect)
    read_ahead_queue_size: int
    read_ahead_max_bytes: int
    rate: float
    topics: list[str]
    services: list[str]          # as service event topics (``/srv/_service_event``), like rosbag2
    regex: str
    exclude_regex: str
    exclude_topics: list[str]
    exclude_services: list[str]  # as service event topics
    qos_profile_overrides_path: str
    loop: bool
    clock_publish_frequency: float
    clock_publish_on_topic_publish: bool
    clock_trigger_topics: list[str]
    delay_ns: int
    playback_duration_ns: int
    playback_until_timestamp_ns: int
    start_paused: bool
    start_offset_ns: int
    wait_acked_timeout_ns: int
    service_requests_source: str
    publish_service_requests: bool
    message_order: str           # one of MESSAGE_ORDERS
    actions: list[str]           # action names (``/fibonacci``)
    exclude_actions: list[str]
    send_actions_as_client: bool
    decode: bool                 # every played compressed image topic also as sensor_msgs/Image
    decode_topics: list[str]     # only these (implies decode)


def declare_play_options(node: Node) -> PlayOptions:
    """Declare every parameter on ``node`` and return the validated options; ValueError names a bad one."""
    values = declare_defaults(node, DEFAULTS)
    if clean(values["play.topic_remapping_options"]):
        node.get_logger().warning("Remappings shall be applied through standard CLI/Launch options. "
                                  "'topic_remapping_options' content will be ignored.")
    return _validate(values)


def _duration_ns(values: dict[str, Any], name: str) -> int:
    """rosbag2's ``get_duration_from_node_param``: |sec| s + |nsec| ns, negative if either part is."""
    sec, nsec = values[f"{name}.sec"], values[f"{name}.nsec"]
    if not -_MAX_SEC <= sec <= _MAX_SEC:
        raise ValueError(f"parameter '{name}.sec' must be in [{-_MAX_SEC}, {_MAX_SEC}], got {sec}")
    if not -_NS_PER_S < nsec < _NS_PER_S:
        raise ValueError(f"parameter '{name}.nsec' must be in [-999999999, 999999999], got {nsec}")
    total = abs(sec) * _NS_PER_S + abs(nsec)
    return -total if sec < 0 or nsec < 0 else total


def _bags(values: dict[str, Any]) -> tuple[list[str], str, list[str]]:
    """The bags to play, the parameter that named them, and their storage ids."""
    uri, uris = values["storage.uri"], clean(values["storage.uris"])
    if uri and uris:
        raise ValueError("parameters 'storage.uri' and 'storage.uris' are both set: name one bag with "
                         "'storage.uri', or several with 'storage.uris'")
    if not uri and not uris:
        raise ValueError("parameter 'storage.uri' must name the bag to play (a bag directory or a storage file), "
                         "or 'storage.uris' the bags to play as one timeline")
    uris = uris or [uri]
    ids, ids_parameter = values["storage.storage_ids"], "storage.storage_ids"
    if ids == [""]:
        ids, ids_parameter = [values["storage.storage_id"]] * len(uris), "storage.storage_id"
    elif len(ids) != len(uris):
        raise ValueError(f"parameter 'storage.storage_ids' needs one entry per bag ({len(uris)}), got {len(ids)}")
    for storage_id in ids:
        if storage_id not in STORAGE_IDS:
            raise ValueError(f"parameter '{ids_parameter}' must be one of mcap, sqlite3 (or empty: detect), "
                             f"got '{storage_id}'")
    return uris, "storage.uri" if uri else "storage.uris", ids


def _validate(values: dict[str, Any]) -> PlayOptions:
    uris, uri_parameter, storage_ids = _bags(values)
    READ_AHEAD_QUEUE.check("'play.read_ahead_queue_size'", values["play.read_ahead_queue_size"])
    READ_AHEAD_BYTES.check("'play.read_ahead_max_bytes'", values["play.read_ahead_max_bytes"])
    RATE.check("'play.rate'", values["play.rate"])
    CLOCK_FREQUENCY.check("'play.clock_publish_frequency'", values["play.clock_publish_frequency"],
                          zero_means="no /clock timer")
    for name in ("play.regex_to_filter", "play.exclude_regex_to_filter"):
        try:
            re.compile(values[name])
        except re.error as exc:
            raise ValueError(f"parameter '{name}' is not a valid regular expression: {exc}") from None
    if values["play.service_requests_source"] not in SERVICE_REQUEST_SOURCES:
        raise ValueError(f"parameter 'play.service_requests_source' must be one of "
                         f"{', '.join(SERVICE_REQUEST_SOURCES)}, got '{values['play.service_requests_source']}'")
    if values["play.message_order"] not in MESSAGE_ORDERS:
        raise ValueError(f"parameter 'play.message_order' must be one of {', '.join(MESSAGE_ORDERS)}, "
                         f"got '{values['play.message_order']}'")
    durations = {name: _duration_ns(values, name) for name in _DURATIONS}
    return PlayOptions(
        uris=uris,
        uri_parameter=uri_parameter,
        storage_ids=storage_ids,
        read_ahead_queue_size=int(values["play.read_ahead_queue_size"]),
        read_ahead_max_bytes=int(values["play.read_ahead_max_bytes"]),
        rate=float(values["play.rate"]),
        topics=clean(values["play.topics_to_filter"]),
        services=[event_topic(s) for s in clean(values["play.services_to_filter"])],
        regex=values["play.regex_to_filter"],
        exclude_regex=values["play.exclude_regex_to_filter"],
        exclude_topics=clean(values["play.exclude_topics_to_filter"]),
        exclude_services=[event_topic(s) for s in clean(values["play.exclude_services_to_filter"])],
        qos_profile_overrides_path=values["play.qos_profile_overrides_path"],
        loop=values["play.loop"],
        clock_publish_frequency=float(values["play.clock_publish_frequency"]),
        clock_publish_on_topic_publish=values["play.clock_publish_on_topic_publish"],
        clock_trigger_topics=clean(values["play.clock_trigger_topics"]),
        delay_ns=durations["play.delay"],
        playback_duration_ns=durations["play.playback_duration"],
        playback_until_timestamp_ns=durations["play.playback_until_timestamp"],
        start_paused=values["play.start_paused"],
        start_offset_ns=durations["play.start_offset"],
        wait_acked_timeout_ns=durations["play.wait_acked_timeout"],
        service_requests_source=values["play.service_requests_source"],
        publish_service_requests=values["play.publish_service_request"],
        message_order=values["play.message_order"],
        actions=[absolute_topic(a) for a in action_names(values["play.actions_to_filter"],
                                                         "'play.actions_to_filter'")],
        exclude_actions=[absolute_topic(a) for a in action_names(values["play.exclude_actions_to_filter"],
                                                                 "'play.exclude_actions_to_filter'")],
        send_actions_as_client=values["play.send_actions_as_client"],
        decode=values["play.decode"],
        decode_topics=clean(values["play.decode_topics"]),
    )
