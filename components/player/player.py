"""``components::Player``: rosbag2 Jazzy's player component, replaying into the container without copies.

Loaded with ``storage.uri`` (and rosbag2's ``play.*`` parameters, see player_options) it starts playing at
once, as rosbag2's ``rosbag2_transport::Player`` component does. With ``storage.uris`` it plays several bags as one
timeline, as rosbag2 Kilted's ``ros2 bag play -i A -i B`` does (baglib.read.timeline): one clock from the earliest
start to the latest end, the messages of all bags in log-time order (a tie goes to the bag named first), the
topics of all bags advertised (a topic of two bags with different types is refused, naming both). Remap its topics with the normal LoadNode
remap rules. Services (private, rosbag2_interfaces): ``~/pause``, ``~/resume``, ``~/toggle_paused``,
``~/is_paused``, ``~/get_rate``, ``~/set_rate``, ``~/play``, ``~/play_next``, ``~/burst``, ``~/seek``,
``~/stop``, plus ``~/get_stats`` (std_srvs/Trigger, JSON: position, published, publish-time error
percentiles, schedule shifts). Events: ``events/read_split`` when playback moves on to the next file.

In a container with intra-process comms, in-process subscribers get message objects (deserialized once, by
the playback thread before they are due, only while such a subscriber exists); DDS readers get the recorded CDR bytes.
Topics whose type is not installed are skipped with a warning naming the type; the rest plays.

Decoding (``play.decode``, ``play.decode_topics``): compressed image topics are played also as
``sensor_msgs/Image``, each decoded on a thread of its own ahead of playback (player/decoded_topics.py).

Timing: start the container with ``--low-latency`` (component_container.process_tuning; ``ipc-component bag
play`` does). Without it CPython hands the GIL over only every 5 ms and large frames are page-faulted in, so a
due message may be published several ms late; the player says so at load, and changes nothing itself.
"""
from __future__ import annotations

import contextlib
import json
import time
from typing import Any

from builtin_interfaces.msg import Time
from rclpy.duration import Duration
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosbag2_interfaces.msg import ReadSplitEvent
from rosbag2_interfaces.srv import (
    Burst,
    GetRate,
    IsPaused,
    Pause,
    Play,
    PlayNext,
    Resume,
    Seek,
    SetRate,
    Stop,
    TogglePaused,
)
from rosgraph_msgs.msg import Clock
from std_srvs.srv import Trigger

from baglib.read.reader import BagMessage, BagReadError
from baglib.read.timeline import Timeline
from baglib.format.message_definitions import message_class
from baglib.format.action_topics import SERVICE_INTERFACES, action_interface, action_name, is_action_topic
from baglib.format.service_events import is_service_event_topic
from component_container.component_node import ComponentNode
from component_container.health import OK, WARN, Health
from component_container.process_tuning import low_latency
from components.player.decoded_topics import DECODABLE, DecodedStream, Decoding, choose_topics
from components.player.playback import Playback, RunLimits
from components.player.playback_clock import PlaybackClock
from components.player.player_options import PlayOptions, declare_play_options
from components.player.player_topics import TopicPublisher, allow_topic, publisher_qos
from components.player.read_ahead import Queued, ReadAhead
from components.player.action_goals import ActionRequestSender, action_replays
from components.player.service_requests import ServiceRequestSender
from components.qos_profiles import load_qos_overrides

SPLIT_EVENT_TOPIC = "events/read_split"
QOS_OVERRIDES_PARAMETER = "play.qos_profile_overrides_path"
#: rclcpp::ClockQoS: keep_last 1, best effort.
CLOCK_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
_NS_PER_S = 1_000_000_000
ACK_POLL_NS = 100_000_000


def _time_msg(nanoseconds: int) -> Time:
    return Time(sec=nanoseconds // _NS_PER_S, nanosec=nanoseconds % _NS_PER_S)


def _ns(stamp: Any) -> int:
    return stamp.sec * _NS_PER_S + stamp.nanosec


class Player(ComponentNode):
    """Plays a rosbag2 bag (see module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("rosbag2_player", **kwargs)
        self._reader: Timeline | None = None
        self._read_ahead: ReadAhead | None = None
        self._decoding: Decoding | None = None
        self._read_error: str | None = None
        try:
            self._options = declare_play_options(self)
            self._reader = self._open_bag(self._options)
            self._senders = self._make_publishers()
            self._decoding = self._make_decoding()
            self._clock_publisher = None
            if self._options.clock_publish_frequency > 0 or self._options.clock_publish_on_topic_publish:
                self._clock_publisher = self.create_publisher(Clock, "/clock", CLOCK_QOS)
            self._split_events = self.create_publisher(ReadSplitEvent, SPLIT_EVENT_TOPIC, 1)
            self._file_index = [self._reader.file_range(bag).start for bag in range(len(self._reader.bags))]
            self._read_ahead = ReadAhead(self._reader, list(self._senders), self._options.read_ahead_queue_size,
                                         self._options.read_ahead_max_bytes, self._on_read_error, self._decoding,
                                         self._options.message_order == "SENT_TIMESTAMP")
            clock = PlaybackClock(self._reader.starting_time_ns, self._options.rate, self._options.start_paused)
            if low_latency() is None:
                self.get_logger().warning(
                    "The container runs without --low-latency: messages may be published up to ~5 ms late "
                    "(CPython's switch interval); start it with --low-latency for sub-millisecond replay timing")
            self._playback = Playback(clock, self._read_ahead, self._reader.starting_time_ns, self._prepare,
                                      self._publish, self.get_logger(), self._options.loop,
                                      self._options.delay_ns, self._wait_for_acks, self._finish_files)
        except Exception:
            with contextlib.suppress(Exception):  # the caller needs the original error, not a cleanup's
                self._close_bag()
                super().destroy_node()
            raise
        if self._options.clock_publish_frequency > 0:
            self._clock_timer = self.create_timer(1.0 / self._options.clock_publish_frequency, self._publish_clock)
        self._player_services = [
            self.create_service(Pause, "~/pause", self._on_pause),
            self.create_service(Resume, "~/resume", self._on_resume),
            self.create_service(TogglePaused, "~/toggle_paused", self._on_toggle_paused),
            self.create_service(IsPaused, "~/is_paused", self._on_is_paused),
            self.create_service(GetRate, "~/get_rate", self._on_get_rate),
            self.create_service(SetRate, "~/set_rate", self._on_set_rate),
            self.create_service(Play, "~/play", self._on_play),
            self.create_service(PlayNext, "~/play_next", self._on_play_next),
            self.create_service(Burst, "~/burst", self._on_burst),
            self.create_service(Seek, "~/seek", self._on_seek),
            self.create_service(Stop, "~/stop", self._on_stop),
            self.create_service(Trigger, "~/get_stats", self._on_get_stats),
        ]
        self.play(self._options.start_offset_ns, self._options.playback_duration_ns,
                  self._options.playback_until_timestamp_ns)

    # --- set-up -------------------------------------------------------------------------------------------
    def _open_bag(self, options: PlayOptions) -> Timeline:
        paths = [self.resolve_path(options.uri_parameter, uri) for uri in options.uris]
        try:
            timeline = Timeline(paths, options.storage_ids)
        except BagReadError as exc:
            raise ValueError(f"parameter '{options.uri_parameter}': {exc}") from exc
        try:
            timeline.topics()  # refuses a topic with two types
        except BagReadError as exc:
            timeline.close()
            raise ValueError(f"parameter '{options.uri_parameter}': {exc}") from exc
        bags = ", ".join(f"{bag.path} ({bag.storage_id})" for bag in timeline.bags)
        self.get_logger().info(f"Playing {bags}{' as one timeline' if len(paths) > 1 else ''}: "
                               f"{timeline.message_count} messages, {timeline.duration_ns / 1e9:.3f} s")
        return timeline

    def _make_publishers(self) -> dict[str, TopicPublisher | ServiceRequestSender | ActionRequestSender]:
        assert self._reader is not None
        path = self._options.qos_profile_overrides_path
        overrides = load_qos_overrides(
            QOS_OVERRIDES_PARAMETER, self.resolve_path(QOS_OVERRIDES_PARAMETER, path) if path else None, 10)
        publishers: dict[str, TopicPublisher | ServiceRequestSender | ActionRequestSender] = {}
        actions = action_replays(self, self._reader.connections, self._options.service_requests_source) \
            if self._options.send_actions_as_client else {}
        for connection in self._reader.connections:
            if connection.topic in publishers or not allow_topic(connection, self._options):
                continue
            try:
                msg_class = message_class(connection.msgtype)
                if is_action_topic(connection.topic, connection.msgtype) and self._options.send_actions_as_client:
                    replay = actions.get(action_name(connection.topic))
                    if replay is not None and action_interface(connection.topic) in SERVICE_INTERFACES:
                        publishers[connection.topic] = ActionRequestSender(replay, connection)
                    continue  # feedback and status come from the server
                if self._options.publish_service_requests and is_service_event_topic(connection.topic,
                                                                                     connection.msgtype) \
                        and not is_action_topic(connection.topic, connection.msgtype):
                    publishers[connection.topic] = ServiceRequestSender(
                        self, connection, self._options.service_requests_source)
                    continue
            except (ImportError, AttributeError, ValueError):
                self.get_logger().warning(f"Ignoring a topic '{connection.topic}', reason: its type "
                                          f"'{connection.msgtype}' is not installed.")
                continue
            if connection.serialization_format != "cdr":
                self.get_logger().warning(f"Ignoring a topic '{connection.topic}', reason: serialization format "
                                          f"'{connection.serialization_format}' is not cdr.")
                continue
            qos = publisher_qos(connection, overrides, self.get_logger().warning)
            publishers[connection.topic] = TopicPublisher(self, connection, msg_class, qos)
        if not publishers:
            self.get_logger().warning("No topic of the bag is played (filters, or no installed type)")
        return publishers

    def _make_decoding(self) -> Decoding | None:
        """The decoded streams ``play.decode`` / ``play.decode_topics`` ask for (None: none)."""
        played = {topic: sender.connection.msgtype for topic, sender in self._senders.items()
                  if isinstance(sender, TopicPublisher)}
        outputs = choose_topics(played, self._options.decode, self._options.decode_topics)
        if not outputs:
            if self._options.decode:
                self.get_logger().warning("play.decode: the bag has no played compressed image topic "
                                          f"({', '.join(DECODABLE)})")
            return None
        streams = []
        for topic, output in outputs.items():
            sender = self._senders[topic]
            assert isinstance(sender, TopicPublisher)
            streams.append(DecodedStream(self, topic, output, DECODABLE[played[topic]],
                                         sender.publisher.qos_profile, sender.msg_class, self.get_logger().error))
            self.get_logger().info(f"Decoding '{topic}' to sensor_msgs/msg/Image on '{output}'")
        return Decoding(streams)

    # --- the read-ahead and playback threads' hooks -------------------------------------------------------
    def _prepare(self, message: BagMessage) -> Any:
        publisher = self._senders[message.connection.topic]
        return publisher.make(message.data) if publisher.wants_object() else None

    def _on_read_error(self, exc: BaseException) -> None:
        self._read_error = str(exc)
        self.get_logger().error(f"Failed to read the bag: {exc}")

    def _publish(self, item: Queued) -> bool:
        message = item.message
        if message.file_index not in self._file_index:
            self._move_to_file(message.file_index)
        if self._clock_publisher is not None and self._options.clock_publish_on_topic_publish and (
                not self._options.clock_trigger_topics
                or message.connection.topic in self._options.clock_trigger_topics):
            self._publish_clock()
        try:
            published = self._senders[message.connection.topic].publish(message.data, item.prepared)
            if item.decoded is not None:
                assert self._decoding is not None
                self._decoding.publish(message.connection.topic, item.decoded)
            return published
        except Exception as exc:  # noqa: BLE001 - rosbag2 logs a failed publish and plays on
            self.get_logger().error(f"Failed to publish message on '{message.connection.topic}' topic. "
                                    f"\nError: {exc}")
            return False

    def _move_to_file(self, file_index: int) -> None:
        """``events/read_split`` as rosbag2's sequential reader of the file's bag sends them (each bag has its
        own): one per file it moves on to, the files whose messages the filters skipped included; one for a jump
        back (a loop, a seek)."""
        assert self._reader is not None
        files, bag = self._reader.files, self._reader.bag_of_file(file_index)
        current = self._file_index[bag]
        for opened in range(current + 1, file_index + 1) if file_index > current else (file_index,):
            self._split_events.publish(ReadSplitEvent(
                closed_file=str(files[current]), opened_file=str(files[opened]),
                node_name=self.get_fully_qualified_name()))
            current = self._file_index[bag] = opened

    def _finish_files(self) -> None:
        """At the end of the bags their readers have gone through their last files too (a bag already there
        sends nothing)."""
        assert self._reader is not None
        for bag in range(len(self._reader.bags)):
            files = self._reader.file_range(bag)
            if files and self._file_index[bag] != files[-1]:
                self._move_to_file(files[-1])

    def _wait_for_acks(self) -> None:
        """rosbag2's end of a run: with ``play.wait_acked_timeout`` >= 0 (0: no limit), wait until every
        reliable reader acknowledged what was published; in short waits, so that stop/unload is not held up."""
        timeout_ns = self._options.wait_acked_timeout_ns
        if timeout_ns < 0:
            return
        deadline = time.monotonic_ns() + timeout_ns if timeout_ns else None
        decoded = list(self._decoding.streams.values()) if self._decoding is not None else []
        for topic, publisher in [*self._senders.items(), *((s.output, s) for s in decoded)]:
            while not self._playback.stopping:
                step = ACK_POLL_NS if deadline is None else min(ACK_POLL_NS, deadline - time.monotonic_ns())
                if publisher.publisher.wait_for_all_acked(Duration(nanoseconds=max(step, 0))):
                    break
                if deadline is not None and time.monotonic_ns() >= deadline:
                    self.get_logger().error("Timed out while waiting for all published messages to be "
                                            f"acknowledged for topic {topic}")
                    break

    def _publish_clock(self) -> None:
        if self._clock_publisher is not None:
            self._clock_publisher.publish(Clock(clock=_time_msg(self._playback.clock.now())))

    # --- control (rosbag2's Player API) -------------------------------------------------------------------
    def play(self, start_offset_ns: int = 0, playback_duration_ns: int = -1, until_ns: int = -1) -> bool:
        """Start a run; False while one is going on.

        As rosbag2's PlayerImpl: playback starts at the bag's start plus ``start_offset_ns`` (negative: ignored,
        with a warning), and ``configure_play_until_timestamp`` sets where it ends: ``playback_duration_ns``
        after that start (0: nothing is played) or at ``until_ns``, the later of the two; both negative: the
        end of the bag. Unlike rosbag2 Jazzy, whose ``~/play`` ignores the request's start_offset for where
        playback starts, the offset of every ``play`` call is used.
        """
        assert self._reader is not None
        if start_offset_ns < 0:
            self.get_logger().warning(f"Invalid start offset value: {start_offset_ns / 1e9}. "
                                      "Negative start offset ignored.")
        start = self._reader.starting_time_ns + max(start_offset_ns, 0)
        until = -1
        if playback_duration_ns >= 0 or until_ns >= 0:
            until = max(0 if playback_duration_ns == 0 else start + playback_duration_ns, until_ns)
        self._file_index = [self._reader.file_range(bag).start for bag in range(len(self._reader.bags))]
        return self._playback.play(RunLimits(start, until))

    def pause(self) -> None:
        self._playback.clock.pause()
        self.get_logger().info("Pausing play.")

    def resume(self) -> None:
        self._playback.clock.resume()
        self.get_logger().info("Resuming play.")

    def is_paused(self) -> bool:
        return self._playback.clock.paused

    def set_rate(self, rate: float) -> bool:
        ok = self._playback.clock.set_rate(rate)
        if ok:
            self.get_logger().info(f"Set rate to {rate}")
        else:
            self.get_logger().warning(f"Failed to set rate to invalid value {rate}")
        return ok

    def stop(self) -> None:
        if self._playback.in_playback:
            self.get_logger().info("Stopping playback.")
        self._playback.stop(self.shutdown_timeout / 2)

    # --- services -----------------------------------------------------------------------------------------
    def _on_pause(self, request: Any, response: Any) -> Any:
        self.pause()
        return response

    def _on_resume(self, request: Any, response: Any) -> Any:
        self.resume()
        return response

    def _on_toggle_paused(self, request: Any, response: Any) -> Any:
        self.resume() if self.is_paused() else self.pause()
        return response

    def _on_is_paused(self, request: Any, response: Any) -> Any:
        response.paused = self.is_paused()
        return response

    def _on_get_rate(self, request: Any, response: Any) -> Any:
        response.rate = self._playback.clock.rate
        return response

    def _on_set_rate(self, request: Any, response: Any) -> Any:
        response.success = self.set_rate(request.rate)
        return response

    def _on_play(self, request: Play.Request, response: Play.Response) -> Play.Response:
        duration = request.playback_duration.sec * _NS_PER_S + request.playback_duration.nanosec
        response.success = self.play(_ns(request.start_offset), duration, _ns(request.playback_until_timestamp))
        return response

    def _on_play_next(self, request: Any, response: Any) -> Any:
        response.success = self._playback.play_next()
        return response

    def burst(self, count: int) -> int:
        """rosbag2's ``Player::burst``: publish the next ``count`` messages at once while paused (0: the rest of
        the bag); how many went out (0 when not paused, with a warning)."""
        return self._playback.burst(count)

    def _on_burst(self, request: Burst.Request, response: Burst.Response) -> Burst.Response:
        response.actually_burst = self.burst(request.num_messages)
        return response

    def _on_seek(self, request: Seek.Request, response: Seek.Response) -> Seek.Response:
        self._playback.seek(_ns(request.time))
        response.success = True
        return response

    def _on_stop(self, request: Any, response: Any) -> Any:
        self.stop()
        return response

    def _on_get_stats(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = True, json.dumps(self.stats())
        return response

    # --- reporting ----------------------------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """Live numbers: where playback is, what went out, how punctual it was, how often it fell behind."""
        assert self._reader is not None and self._read_ahead is not None
        p50, p99, worst = self._playback.timing.percentiles(0.5, 0.99, 1.0)
        decoded = list(self._decoding.streams.values()) if self._decoding is not None else []
        return {
            "bag": ", ".join(str(path) for path in self._reader.paths),
            "position_ns": self._playback.position_ns - self._reader.starting_time_ns,
            "duration_ns": self._reader.duration_ns,
            "rate": self._playback.clock.rate,
            "paused": self._playback.clock.paused,
            "playing": self._playback.in_playback,
            "published": {**{topic: p.published for topic, p in self._senders.items()},
                          **{s.output: s.published for s in decoded}},
            "decoded": self._decoding.stats() if self._decoding is not None else {},
            "publish_error_ms": {"p50": p50, "p99": p99, "max": worst, "count": self._playback.timing.count},
            "behind": {"count": self._playback.behind_count, "total_s": self._playback.behind_ns / 1e9},
            "queue_starved": self._read_ahead.starved,
            "read_error": self._read_error,
        }

    def health(self) -> Health:
        stats = self.stats()
        values = {"bag": stats["bag"], "position_s": f"{stats['position_ns'] / 1e9:.3f}",
                  "duration_s": f"{stats['duration_ns'] / 1e9:.3f}", "rate": f"{stats['rate']:g}",
                  "paused": str(stats["paused"]).lower(), "playing": str(stats["playing"]).lower(),
                  "published": str(sum(stats["published"].values())), "behind": str(stats["behind"]["count"])}
        if stats["read_error"]:
            return Health(WARN, f"bag read failed: {stats['read_error']}", values)
        state = "paused" if stats["paused"] else ("playing" if stats["playing"] else "finished")
        return Health(OK, state, values)

    # --- teardown -----------------------------------------------------------------------------------------
    def _close_bag(self) -> None:
        if self._read_ahead is not None:
            self._read_ahead.close()
        if self._reader is not None:
            self._reader.close()

    def destroy_node(self) -> None:
        """Stop the run and close the bag, then destroy the node (within the container's shutdown timeout)."""
        try:
            if hasattr(self, "_playback"):
                self._playback.stop(self.shutdown_timeout / 2)
            self._close_bag()
        finally:
            super().destroy_node()
