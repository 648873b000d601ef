"""``components::Recorder``: a rosbag2-compatible recorder that takes intra-process messages without a copy.

Loaded into a container next to the drivers with ``use_intra_process_comms``, it receives their message
objects by reference; topics from other processes arrive through raw DDS subscriptions as CDR bytes (never
deserialized). Both go to the same :class:`RecordingSession`, whose writer thread serializes and writes.

Services (private): ``~/pause``, ``~/resume``, ``~/toggle_paused``, ``~/is_paused``, ``~/split_bagfile``,
``~/snapshot`` and rosbag2's remote control ``~/record``, ``~/stop``, ``~/start_discovery``, ``~/stop_discovery``,
``~/is_discovery_running`` (rosbag2_interfaces, as rosbag2 Jazzy 0.26.10 answers them), ``~/start_recording``,
``~/stop_recording`` and ``~/get_stats`` (std_srvs/Trigger; get_stats answers the live counts as JSON in
``message``). Events: ``events/write_split``.

Fleet recording (components/recorder/schedule.py): ``record.start_at`` / ``record.stop_at`` bound the
recording to the messages received within a window, ``record.max_duration`` ends it even if no stop comes,
``record.split_at`` schedules a split; ``record.stop_at``, ``record.split_at`` and ``storage.custom_data`` may be
set while recording (``ros2 param set``). ``record.local_only`` records only what this container publishes.
``record.compress`` records chosen image topics compressed by an ImageEncoder the recorder loads into its
container (components/recorder/compression.py; video files begin at keyframes: keyframe_gate.py).

Recording starts at load (unless ``record.start_paused``) and the bag is finalized on unload, on ``~/stop`` or
``~/stop_recording``, when the context shuts down, and when the container receives SIGINT/SIGTERM, within the
container's shutdown timeout. A loaded recorder is a working one or says why not: a bad message, a type that
cannot be used here or a failing disk is logged, counted in ``~/get_stats`` and reported by :meth:`health`,
and never silently stops the recording (see RecordingSession).
"""
from __future__ import annotations

import functools
import json
import threading
import time
from pathlib import Path
from typing import Any, Callable

from rclpy.duration import Duration
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import InvalidHandle
from rcl_interfaces.msg import SetParametersResult
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile
from rclpy.type_support import check_is_valid_msg_type
from rosbag2_interfaces.msg import WriteSplitEvent
from rosbag2_interfaces.srv import (IsDiscoveryRunning, IsPaused, Pause, Record, Resume, Snapshot, SplitBagfile,
                                    StartDiscovery, Stop, StopDiscovery, TogglePaused)
from std_srvs.srv import Trigger

from component_container.component_node import ComponentNode
from component_container.health import OK, WARN, Health
from baglib.upload.journal import summary_text
from baglib.write.writer import BagWriter
from baglib.format.action_topics import INTERFACES, SERVICE_INTERFACES, actions_of
from baglib.format.message_definitions import message_definition
from baglib.format.metadata import TopicInfo, qos_profile_dict
from baglib.format.message_definitions import message_class
from components.image_encoder import outputs
from components.image_encoder.image_encoder import IMAGE_TYPE
from components.qos_profiles import absolute_topic
from components.recorder.bag_names import BagNames
from components.recorder.compression import Compression
from components.recorder.finished_bags import FinishedBags
from components.recorder.keyframe_gate import SPLIT_HOLD, VIDEO_TYPE, VideoTopics
from components.recorder.recorder_health import HealthMonitor
from components.recorder.recorder_options import custom_data_pairs, declare_options
from components.recorder.loss_events import MESSAGES_LOST_TOPIC, LossEvents
from components.recorder.recording_session import RecordingSession
from components.recorder.schedule import Schedule, instant_ns
from components.recorder.uploads import BagUploads, declare_upload_options, upload_values
from components.recorder.topic_selection import TopicFilter, adapt_qos, load_qos_overrides

SPLIT_EVENT_TOPIC = "events/write_split"
URI_PARAMETER = "storage.uri"
QOS_OVERRIDES_PARAMETER = "record.qos_profile_overrides_path"
#: Share of the container's shutdown_timeout that finalizing a bag may take: the node must still be destroyed
#: (its endpoints, the split event acknowledgement) within the rest.
FINISH_SHARE = 0.8
ACK_SHARE = 0.1
#: s: how often the schedule (a split or the end of the window) is looked at
SCHEDULE_PERIOD = 0.05
#: ``~/get_stats`` answers the final counts of this many of the last bags closed (and how many were closed in
#: all): every bag's would grow the container and every reply by ~0.7 kB per bag, for as long as it is loaded.
FINISHED_STATS_KEPT = 10
#: rosbag2's service return codes (RecorderImpl's kServiceReturnCodeSuccess / kServiceReturnCodeError)
RETURN_CODE_SUCCESS = 0
RETURN_CODE_ERROR = 1


class Recorder(ComponentNode):
    """Records selected topics into rosbag2 bags (see module docstring)."""

    #: What writes the bags; a subclass may record through its own BagWriter.
    writer_class: type[BagWriter] = BagWriter

    def __init__(self, **kwargs: Any) -> None:
        overrides = {p.name: p for p in kwargs.get("parameter_overrides") or []}
        self._lock = threading.RLock()
        self._session: RecordingSession | None = None
        self._health = HealthMonitor()
        self._uploads: BagUploads | None = None
        # Bags whose writer a stop gave up on (a hung disk), until the writer closes them after all.
        self._closing: set[RecordingSession] = set()
        self._closing_lock = threading.Lock()
        super().__init__("recorder", **kwargs)
        try:
            self._options = declare_options(self, overrides)
            upload_options = declare_upload_options(self)
            self._uploads = BagUploads(upload_options) if upload_options else None
            if self._options.local_only and not self.uses_intra_process:
                raise ValueError("parameter 'record.local_only' records what this container publishes in-process: "
                                 "load the recorder with use_intra_process_comms:=true")
            options = self._options
            self._compression = Compression(self, options) if options.compress else None
            # The recorded video topics: their files begin at keyframes (keyframe_gate).
            self._video = VideoTopics(self._ipm if self.uses_intra_process else None, self.get_logger().warning)
            self._schedule = Schedule(options.start_ns or time.time_ns(), options.stop_ns, options.max_duration_ns,
                                      options.split_ns)
            self._finalizer: threading.Thread | None = None
            self._qos_overrides = self._load_qos_overrides()
            self._split_events = self.create_publisher(WriteSplitEvent, SPLIT_EVENT_TOPIC, 10)
            self._loss_events = LossEvents(self, lambda: self._session)
            self._filter = TopicFilter(self._options, {self._split_events.topic_name,
                                                       self.resolve_topic_name(MESSAGES_LOST_TOPIC)})
            self._paused = self._options.start_paused
            self._topics: dict[str, TopicInfo] = {}
            self._repeat_depths: dict[str, int] = {}  # per topic: record.repeat_transient_local depth (0: none)
            self._topic_subscriptions: dict[str, Any] = {}
            self._ignored: set[str] = set()
            self._names = BagNames(options.uri, functools.partial(self.resolve_path, URI_PARAMETER))
            # Topic discovery (the polling timer) subscribes new topics while this holds: from each start of a
            # bag until its stop or ~/stop_discovery (rosbag2's discovery_running_).
            self._discovery_running = False
            self._finished = FinishedBags(FINISHED_STATS_KEPT)
            # The bag the end of the recording window closed, and that window: a message received inside it
            # that reaches the intake after the close is counted as lost in that bag (see _intake).
            self._window_bag: tuple[RecordingSession, int, int] | None = None
            self._start_session()
        except Exception:
            self.stop_recording()  # no half-built node or open bag is left behind
            if self._uploads is not None:
                self._uploads.close()
            super().destroy_node()
            raise
        self._recorder_services = [
            self.create_service(Pause, "~/pause", self._on_pause),
            self.create_service(Resume, "~/resume", self._on_resume),
            self.create_service(TogglePaused, "~/toggle_paused", self._on_toggle_paused),
            self.create_service(IsPaused, "~/is_paused", self._on_is_paused),
            self.create_service(SplitBagfile, "~/split_bagfile", self._on_split_bagfile),
            self.create_service(Snapshot, "~/snapshot", self._on_snapshot),
            self.create_service(Trigger, "~/start_recording", self._on_start_recording),
            self.create_service(Trigger, "~/stop_recording", self._on_stop_recording),
            self.create_service(Trigger, "~/get_stats", self._on_get_stats),
            self.create_service(Record, "~/record", self._on_record),
            self.create_service(Stop, "~/stop", self._on_stop),
            self.create_service(StartDiscovery, "~/start_discovery", self._on_start_discovery),
            self.create_service(StopDiscovery, "~/stop_discovery", self._on_stop_discovery),
            self.create_service(IsDiscoveryRunning, "~/is_discovery_running", self._on_is_discovery_running),
        ]
        self.context.on_shutdown(self.stop_recording)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._discover_topics()
        self._poll_timer = self.create_timer(self._options.polling_interval, self._discover_topics)
        self._schedule_timer = self.create_timer(SCHEDULE_PERIOD, self._run_schedule)

    def _load_qos_overrides(self) -> dict[str, QoSProfile]:
        """The override file, if any, read only after its path passed the container's bag root."""
        path = self._options.qos_profile_overrides_path
        return load_qos_overrides(
            QOS_OVERRIDES_PARAMETER, self.resolve_path(QOS_OVERRIDES_PARAMETER, path) if path else None)

    # --- sessions -----------------------------------------------------------------------------------------
    def _start_session(self, uri: Path | None = None) -> RecordingSession:
        """A new bag at ``uri`` (default: the next name, see BagNames), with every topic known so far declared;
        topic discovery runs (again)."""
        # Queue drops count per subscription since it was created; a session counts only its own.
        baseline = {topic: getattr(sub, "dropped_count", 0) for topic, sub in self._topic_subscriptions.items()}
        session = RecordingSession(self._options, str(uri or self._names.next()), self.get_logger(),
                                   self._publish_split,
                                   queue_drops=functools.partial(self._queue_drops, baseline),
                                   writer_class=self.writer_class, video=self._video)
        for info in self._topics.values():
            session.add_topic(info, self._repeat_depths.get(info.name, 0))
            self._account_encoder(session, info.name)
        self._window_bag = None
        self._session = session
        if self._uploads is not None:
            self._uploads.open(session.writer.path)
            session.disk.reclaim = self._uploads.reclaim
        if session.gate is not None:  # after the session takes messages, so that the keyframes asked for reach it
            start_ns = self._schedule.start_ns  # record.start_at: the keyframes are due when the window opens
            session.gate.begin(start_ns if start_ns > time.time_ns() else None)
        self._discovery_running = True
        self.get_logger().info(f"Recording to {session.writer.path} ({self._options.storage_id})"
                               + (" paused" if self._paused else ""))
        return session

    def stop_recording(self, window_ended: bool = False) -> dict[str, Any] | None:
        """Finalize the current bag (flush, summary, metadata.yaml); returns its final counts. Idempotent.

        Closing the bag's cache is its cut point: every message offered before is written or counted as
        dropped, nothing offered after is counted (see MessageCache.close). With ``window_ended`` (the
        recording window's end closes the bag) a message received inside the window that a busy executor hands
        over only after the close is counted as lost in this bag (``recording_stopped``).

        Bounded by the container's shutdown_timeout: a writer stuck on a hung disk is abandoned (and its bag
        left unfinalized, see RecordingSession.finish) rather than blocking an unload or a shutdown forever.
        The losses of the bag's last second are published on ``events/messages_lost`` before this returns.
        """
        with self._lock:
            session, self._session = self._session, None
            self._discovery_running = False
            if session is not None and window_ended:
                self._window_bag = (session, self._schedule.start_ns, self._schedule.end_ns)
        if session is None:
            return None
        self._warn_missing_action_topics()
        session.finish(timeout=FINISH_SHARE * self.shutdown_timeout,
                       on_late_close=functools.partial(self._bag_closed_late, session))
        with self._closing_lock:
            if session.writing_after_finish:
                self._closing.add(session)
        self._loss_events.close_bag(session)
        if self._uploads is not None and session.writer.closed:
            self._uploads.bag_closed(session.writer.path)
        return self._finished.add(session, may_change=window_ended or session.writing_after_finish)

    def _bag_closed_late(self, session: RecordingSession) -> None:
        """The writer the stop gave up on closed the bag after all (on its thread, maybe after the unload): its
        counts changed, and the finalized bag is uploaded like any other."""
        self._finished.changed(session)
        if self._uploads is not None:
            self._uploads.bag_closed(session.writer.path)
        with self._closing_lock:
            self._closing.discard(session)  # only now: work_left goes on to report its upload

    def _warn_missing_action_topics(self) -> None:
        """A warning per action of ``record.actions`` whose five topics were not all recorded (rosbag2 is silent):
        an action of a process without action introspection has no service events."""
        recorded = actions_of((info.name, info.type) for info in self._topics.values())
        for action in self._options.actions:
            missing = [i for i in INTERFACES if i not in recorded.get(absolute_topic(action), {})]
            if missing:
                hint = (" (service events exist only where the action's server and client enable introspection: "
                        "configure_introspection, see docs/recorder.md#actions)"
                        if set(missing) & set(SERVICE_INTERFACES) else "")
                self.get_logger().warning(f"record.actions: action {action} recorded without its "
                                          f"{', '.join(missing)} topic{'s' if len(missing) > 1 else ''}{hint}")

    def _publish_split(self, closed_file: str, opened_file: str) -> None:
        if self._uploads is not None and closed_file:
            self._uploads.file_closed(Path(closed_file))
        if not self.context.ok():
            return
        try:
            self._split_events.publish(WriteSplitEvent(closed_file=closed_file, opened_file=opened_file,
                                                       node_name=self.get_fully_qualified_name()))
        except InvalidHandle:  # a bag closed late, by a writer given up on at the unload: no node left to say so
            pass

    # --- discovery and intake -----------------------------------------------------------------------------
    def _discover_topics(self) -> None:
        """Subscribe the selected topics that appeared since the last look; nothing while discovery is off."""
        if not self._discovery_running:
            return
        for topic, types in self.get_topic_names_and_types():
            if topic in self._topic_subscriptions or topic in self._ignored:
                continue
            if len(types) != 1:
                self._ignore(topic, f"it has more than one type ({', '.join(types)})")
                continue
            if self._options.local_only and not self.has_local_publisher(topic):
                continue  # not (yet) published here; a local publisher may still come
            compression = self._compression
            if compression is not None and compression.replaces(topic, types[0]):
                continue  # recorded compressed: its encoder's output is
            publishers = self.get_publishers_info_by_topic(topic)
            if (compression is not None and compression.output(topic)) or \
                    self._filter.selects(topic, types[0], len(publishers)):
                self._subscribe(topic, types[0], publishers)

    def _ignore(self, topic: str, reason: str) -> None:
        self._ignored.add(topic)
        self.get_logger().warning(f"Not recording {topic}: {reason}")

    def _subscribe(self, topic: str, type_name: str, publishers: list[Any]) -> None:
        """Record ``topic``. A type this process cannot record is logged and ignored; discovery goes on.

        Everything that can fail for a type (its module, its class, its type support, the definition the bag
        must carry) is checked before the topic is registered, so a failure leaves nothing half-registered
        that a later ~/start_recording would trip over.
        """
        try:
            msg_type = message_class(type_name)
            check_is_valid_msg_type(msg_type)
            message_definition(type_name)
        except Exception as exc:  # noqa: BLE001 - any broken installation of a type: that topic only
            self._ignore(topic, f"type {type_name} cannot be recorded here ({type(exc).__name__}: {exc})")
            return
        offered = [p.qos_profile for p in publishers]
        qos: QoSProfile = self._qos_overrides.get(topic) or adapt_qos(offered)
        depth = self._repeat_depth(topic, qos)
        if depth and qos.durability != DurabilityPolicy.TRANSIENT_LOCAL:
            self.get_logger().warning(
                f"{topic} is in record.repeat_transient_local, but " + (
                    "its QoS override is not transient_local: the override is used" if topic in self._qos_overrides
                    else "not every publisher offers transient_local: subscribing transient_local anyway, "
                         "so volatile publishers of it are not recorded"))
            if topic not in self._qos_overrides:  # rosbag2 Rolling asks for transient_local here too
                qos = adapt_qos(offered)
                qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
        type_hash = next((str(p.topic_type_hash) for p in publishers if str(p.topic_type_hash).startswith("RIHS01_")),
                         "")
        info = TopicInfo(topic, type_name, "cdr", [qos_profile_dict(q) for q in offered], type_hash)
        if self._compression is not None and type_name == IMAGE_TYPE:
            self.get_logger().warning(
                f"record.compress:={self._options.compress} does not encode {topic} (record.compress_topics / "
                "record.compress_regex do not name it): recording it raw")
        if type_name == VIDEO_TYPE and not self._video.add(topic):
            self.get_logger().info(
                f"{topic} carries video from outside this container: its files begin at its keyframes as FFmpeg's "
                "parser reads them; its encoder cannot be asked for one, so its delta frames before its first "
                "keyframe, and at a split that waits for one longer than "
                f"{SPLIT_HOLD:g} s, are dropped as awaiting_keyframe (load its encoder into the recorder's "
                "container, or use record.compress, to have no frame dropped)")
        try:
            with self._lock:  # declared in the bag before the first message can reach the writer
                if self._session is not None:
                    self._session.add_topic(info, depth)
                    self._account_encoder(self._session, topic)
                self._topics[topic] = info
                self._repeat_depths[topic] = depth
            self._topic_subscriptions[topic] = self.create_subscription(
                msg_type, topic, functools.partial(self._intake, topic), qos, raw=True,
                intra_process_inline=True,  # the intake only hands over to the writer thread: no executor hop
                intra_process_only=self._options.local_only,
                event_callbacks=SubscriptionEventCallbacks(
                    message_lost=functools.partial(self._loss_events.dds_lost, topic)))
        except Exception as exc:  # noqa: BLE001 - as above; the bag may list the topic, without messages
            with self._lock:
                self._topics.pop(topic, None)
            self._ignore(topic, f"cannot subscribe with type {type_name} ({type(exc).__name__}: {exc})")
            return
        self.get_logger().info(f"Subscribed to {topic} ({type_name})"
                               + (f", repeating its last {depth} at every split and snapshot" if depth else ""))

    def _account_encoder(self, session: RecordingSession, topic: str) -> None:
        """An encoder of this container publishes ``topic``: the bag accounts for its raw frames, and a rate
        limit on the recorder's own encoder thins its input (RecordingSession.account_encoder)."""
        stream = outputs.stream_for(self._ipm, topic)
        if stream is None:
            return
        owned = self._compression is not None and self._compression.output(topic)
        warning = session.account_encoder(topic, stream, owned)
        if warning:
            self.get_logger().warning(warning)
        if owned:
            stream.set_input_filter(functools.partial(self._admits_raw, topic))

    def _admits_raw(self, topic: str) -> bool:
        """The input filter of the recorder's own encoder of ``topic`` (in the camera's thread): record.max_rates
        of the current bag; everything while paused or not recording (the frames are not recorded anyway)."""
        session = self._session
        return session is None or self._paused or session.admits_raw(topic)

    def _repeat_depth(self, topic: str, qos: QoSProfile) -> int:
        """How many of the topic's last messages start every split file and snapshot: its entry in
        record.repeat_transient_local, else record.repeat_all_transient_local if it is recorded transient_local
        (0: none)."""
        named = self._options.repeat_transient_local.get(topic)
        if named is not None:
            return named
        return self._options.repeat_all_transient_local if qos.durability == DurabilityPolicy.TRANSIENT_LOCAL else 0

    def _intake(self, topic: str, message: Any, info: dict[str, Any]) -> None:
        """Hand the message (object or CDR bytes) to the writer thread, nothing more.

        Runs on the executor for DDS messages and in the publisher's thread for intra-process ones, so it
        must stay thread-safe, non-blocking and exception-free (MessageCache.push is all three). A message
        offered after its bag's cut point belongs to no bag (see stop_recording), unless it was received
        inside a window that has ended meanwhile (:meth:`_missed`).
        """
        if self._paused:
            return
        session = self._session
        received = info.get("received_timestamp") or time.time_ns()
        if session is not None and self._schedule.admits(received) and \
                session.offer(topic, message, received, info.get("source_timestamp") or received) is not None:
            return
        if self._window_bag is not None:
            self._missed(topic, received)

    def _missed(self, topic: str, received_ns: int) -> None:
        """A message that reached the intake after the window's bag closed; lost there if received inside it
        (DDS decides by the receive time, so a busy executor may hand it over well after the instant)."""
        window = self._window_bag
        if window is not None and window[1] <= received_ns < window[2]:
            window[0].missed(topic)
            self._finished.changed(window[0])

    # --- the schedule ---------------------------------------------------------------------------------------
    def _run_schedule(self) -> None:
        """A scheduled split, and the end of the window: the bag is finalized off the executor."""
        now = time.time_ns()
        session = self._session
        if session is not None and self._schedule.split_due(now):
            session.split()
        if session is not None and self._schedule.finalize_due(now) and self._finalizer is None:
            self.get_logger().info(f"Recording window ended at {self._schedule.end_ns / 1e9:.3f}: finalizing")
            self._finalizer = threading.Thread(target=self.stop_recording, args=(True,), name="recorder-finalize",
                                               daemon=True)
            self._finalizer.start()

    def _on_set_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """The parameters that may change while recording; a bad value is refused with the reason."""
        try:
            for parameter in parameters:
                if parameter.name == "record.stop_at":
                    self._schedule.set_stop(instant_ns(parameter.name, float(parameter.value)))
                elif parameter.name == "record.split_at":
                    self._schedule.set_split(instant_ns(parameter.name, float(parameter.value)))
                elif parameter.name == "storage.custom_data":
                    self._update_custom_data(list(parameter.value or []))
        except (TypeError, ValueError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _update_custom_data(self, items: list[str]) -> None:
        pairs = custom_data_pairs(items)
        self._options.custom_data.update(pairs)
        session = self._session
        if session is not None:
            session.writer.update_custom_data(pairs)

    # --- statistics ---------------------------------------------------------------------------------------
    def _queue_drops(self, baseline: dict[str, int]) -> dict[str, int]:
        """Messages the in-process queues dropped (they never reached the intake) since ``baseline``."""
        return {topic: getattr(subscription, "dropped_count", 0) - baseline.get(topic, 0)
                for topic, subscription in list(self._topic_subscriptions.items())}

    def stats(self) -> dict[str, Any]:
        """Live counts of the current bag, the final counts of the last FINISHED_STATS_KEPT bags closed (oldest
        first) and how many bags were closed in all. Every count is read under the lock of whatever writes it,
        or from a value replaced whole (never waiting on the storage)."""
        session, schedule = self._session, self._schedule
        return {"recording": session is not None, "paused": self._paused,
                "discovery_running": self._discovery_running,
                "window_ns": [schedule.start_ns, schedule.end_ns],
                "custom_data": dict(self._options.custom_data),
                "current": session.stats() if session else None,
                "finished": self._finished.stats(), "finished_bags": self._finished.count,
                **({"upload": self._uploads.stats()} if self._uploads is not None else {})}

    def health(self) -> Health:
        """For /diagnostics: OK while recording, WARN when not (or dropping), ERROR after a storage failure."""
        session = self._session
        health = self._health.sample(session.stats() if session else None, self._paused)
        if self._uploads is not None:
            upload = self._uploads.stats()
            health.values.update(upload_values(upload))
            if upload["last_error"] and health.level == OK:
                health = Health(WARN, f"upload {summary_text(upload)}", health.values)
            else:
                health.message += f"; upload {summary_text(upload)}"
        return health

    def work_left(self) -> Health | None:
        """After the unload: bags whose writer the stop gave up on, until it closes them (if the disk comes back),
        and uploads going on (the container's upload process finishes them), until complete."""
        with self._closing_lock:
            closing = sorted(str(session.writer.path) for session in self._closing)
        upload = self._uploads.stats() if self._uploads is not None else None
        values = upload_values(upload) if upload is not None else {}
        if closing:
            return Health(WARN, f"{len(closing)} bag(s) not finalized, the writer stuck on its storage (it closes "
                                "them if the storage comes back)", {"bags not finalized": ", ".join(closing), **values})
        if upload is None or upload["complete"] or not upload["running"]:
            return None
        return Health(WARN if upload["last_error"] else OK, f"upload {summary_text(upload)}", values)

    # --- services -----------------------------------------------------------------------------------------
    def _set_paused(self, paused: bool) -> None:
        if paused != self._paused:
            session = self._session
            gate = session.gate if session is not None else None
            if paused and gate is not None:
                gate.paused()  # frames are left out: after the resume, each video topic begins anew
            if not paused and gate is not None:
                with gate.video.publication_held():  # no delta frame between the resume and the request
                    self._paused = paused
                    gate.begin()  # ... at the keyframe asked for now
            self._paused = paused
            self.get_logger().info("Recording paused" if paused else "Recording resumed")

    def _on_pause(self, request: Pause.Request, response: Pause.Response) -> Pause.Response:
        self._set_paused(True)
        return response

    def _on_resume(self, request: Resume.Request, response: Resume.Response) -> Resume.Response:
        self._set_paused(False)
        return response

    def _on_toggle_paused(self, request: TogglePaused.Request,
                          response: TogglePaused.Response) -> TogglePaused.Response:
        self._set_paused(not self._paused)
        return response

    def _on_is_paused(self, request: IsPaused.Request, response: IsPaused.Response) -> IsPaused.Response:
        response.paused = self._paused
        return response

    def _on_split_bagfile(self, request: SplitBagfile.Request,
                          response: SplitBagfile.Response) -> SplitBagfile.Response:
        session = self._session
        if session is None or not session.split():
            self.get_logger().warning("split_bagfile ignored: not recording")
        return response

    def _on_snapshot(self, request: Snapshot.Request, response: Snapshot.Response) -> Snapshot.Response:
        """Write the ring; success=false (with the reason in the log) when the snapshot would not be written."""
        session = self._session
        refusal = "not recording" if session is None else session.snapshot()
        if refusal is not None:
            # throttled: anyone on the domain may call ~/snapshot in a loop
            self.get_logger().warning(f"snapshot refused: {refusal}", throttle_duration_sec=1.0)
        response.success = refusal is None
        return response

    def _start_again(self, uri: Callable[[], Path] | None = None) -> RecordingSession | str:
        """A new bag after a stop (the caller holds the lock and there is no session): the session, or why not.

        After the recording window has ended, an explicit start records from now on. Discovery runs again, and
        at once: topics that appeared while no bag was open are in the new one from its start.
        """
        if self._schedule.end_ns and self._schedule.end_ns <= time.time_ns():
            self._schedule = Schedule(time.time_ns())
            self._finalizer = None
        try:
            session = self._start_session(uri() if uri is not None else None)
        except (OSError, ValueError) as exc:
            reason = f"cannot start recording: {exc}"
            self.get_logger().error(reason)
            return reason
        self._discover_topics()
        return session

    def _on_start_recording(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            if self._session is not None:
                response.success, response.message = False, f"already recording to {self._session.writer.path}"
                return response
            started = self._start_again()
        if isinstance(started, str):
            response.success, response.message = False, started
        else:
            response.success, response.message = True, f"recording to {started.writer.path}"
        return response

    def _on_stop_recording(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        stats = self.stop_recording()
        if stats is None:
            response.success, response.message = False, "not recording"
        else:  # the final counts; on failure, "error" and "serialize_errors" in them say why
            response.success = stats["error"] is None and not stats["serialize_errors"]
            response.message = json.dumps(stats)
        return response

    # --- rosbag2's remote control (rosbag2_interfaces, Jazzy 0.26.10: ros2/rosbag2#2248) -------------------
    def _on_record(self, request: Record.Request, response: Record.Response) -> Record.Response:
        """A new bag after a stop, at ``uri`` or, empty, where the previous one was (BagNames.record)."""
        with self._lock:
            if self._session is not None:
                started: RecordingSession | str = ("Called record(uri) while already in recording "
                                                   f"(to {self._session.writer.path}).")
                self.get_logger().warning(f"Record request dismissed: {started}")
            else:
                started = self._start_again(functools.partial(self._names.record, request.uri))
        if isinstance(started, str):
            response.return_code, response.error_string = RETURN_CODE_ERROR, started
        else:
            response.return_code, response.error_string = RETURN_CODE_SUCCESS, ""
        return response

    def _on_stop(self, request: Stop.Request, response: Stop.Response) -> Stop.Response:
        """Finalize the bag, as ~/stop_recording; Jazzy's Stop has an empty response (a return code came later,
        in ros2/rosbag2#2312, not backported), so a stop while not recording is only logged, as rosbag2 does."""
        if self.stop_recording() is None:
            self.get_logger().warning("Received Stop request while not in recording. Ignoring request.")
        return response

    def _on_start_discovery(self, request: StartDiscovery.Request,
                            response: StartDiscovery.Response) -> StartDiscovery.Response:
        """Subscribe new topics again, at once; refused when not recording or already discovering."""
        with self._lock:
            if self._session is None:
                refusal: str | None = "Recorder is not currently recording."
            elif self._discovery_running:
                refusal = "Discovery is already running."
            else:
                refusal, self._discovery_running = None, True
                self._discover_topics()
        self._discovery_answer(response, "StartDiscovery", refusal)
        return response

    def _on_stop_discovery(self, request: StopDiscovery.Request,
                           response: StopDiscovery.Response) -> StopDiscovery.Response:
        """Subscribe no new topic until ~/start_discovery (or the next bag); subscribed ones go on recording."""
        with self._lock:
            refusal = None if self._discovery_running else "Discovery is not running."
            self._discovery_running = False
        self._discovery_answer(response, "StopDiscovery", refusal)
        return response

    def _discovery_answer(self, response: Any, request_name: str, refusal: str | None) -> None:
        if refusal is not None:
            self.get_logger().warning(f"{request_name} request ignored: {refusal}")
        response.return_code = RETURN_CODE_SUCCESS if refusal is None else RETURN_CODE_ERROR
        response.error_string = refusal or ""

    def _on_is_discovery_running(self, request: IsDiscoveryRunning.Request,
                                 response: IsDiscoveryRunning.Response) -> IsDiscoveryRunning.Response:
        response.running = self._discovery_running
        return response

    def _on_get_stats(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = True, json.dumps(self.stats())
        return response

    def destroy_node(self) -> None:
        # The intake first: once the subscriptions are gone (in-process ones after their inline callbacks
        # running in publishers' threads returned), the bag's last message is written rather than refused.
        for subscription in getattr(self, "_topic_subscriptions", {}).values():
            self.destroy_subscription(subscription)
        self.stop_recording()
        if self._uploads is not None:
            self._uploads.close()
        # The bag's closing event was just published; a publisher destroyed at once can take it along with it
        # before a (reliable) subscriber has it. Give them a moment to acknowledge it.
        events = getattr(self, "_split_events", None)
        if events is not None and self.context.ok():
            try:
                events.wait_for_all_acked(Duration(seconds=min(1.0, ACK_SHARE * self.shutdown_timeout)))
            except Exception:  # noqa: BLE001 - never let this keep the node from being destroyed
                pass
        super().destroy_node()
