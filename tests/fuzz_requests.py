"""Random LoadNode / UnloadNode requests and recorder service calls for fuzzing a container (seeded).

Everything comes from one ``random.Random``, so a seed replays a run exactly (as far as the requests go; the
container's replies and their timing may differ). Plugin names are mostly valid ``components::*`` ones, so
that component constructors really run with garbage names, remaps and parameters.

Paths: every path-like value is relative garbage, an escape attempt (``../``, ``/tmp/...``) carrying the run's
marker (:data:`MARKER` and a random suffix, so that runs side by side do not see each other's files) in its
name, or an absolute path inside the bag root. A write outside the bag root therefore leaves a file whose
name contains the marker, which the test looks for; random text is never absolute.
"""
from __future__ import annotations

import math
import pathlib
import random
import string
from typing import Any

from composition_interfaces.srv import LoadNode, UnloadNode
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rosbag2_interfaces.srv import (IsDiscoveryRunning, IsPaused, Pause, Record, Resume, Snapshot, SplitBagfile,
                                    StartDiscovery, Stop, StopDiscovery, TogglePaused)
from std_srvs.srv import Trigger

MARKER = "ipcfuzz"
PLUGINS = ["components::Talker", "components::Listener", "components::CameraDriver", "components::LidarDriver",
           "components::ImuDriver", "components::Recorder", "components::Player"]
GARBAGE_PLUGINS = ["", "components::", "::", "components::NoSuch", "components::recorder", "os:system",
                   "components.recorder.recorder:Recorder", "components::Talker ", "COMPONENTS::TALKER"]
# Parameter names the built-in components read, so that garbage values reach their validation.
KNOWN_PARAMETERS = [
    "rate", "fps", "width", "height", "encoding", "frame_id", "topic", "qos", "points_per_scan", "rings",
    "use_sim_time", "record.all_topics", "record.topics", "record.topic_types", "record.exclude_topics",
    "record.all_services", "record.services", "record.exclude_services",
    "record.regex", "record.exclude_regex", "record.include_hidden_topics", "record.start_paused",
    "record.topic_polling_interval.sec", "record.topic_polling_interval.nsec", "storage.storage_id",
    "storage.max_bagfile_size", "storage.max_bagfile_duration", "storage.max_cache_size", "storage.stall_reserve",
    "storage.storage_preset_profile", "storage.snapshot_mode", "storage.custom_data", "record_all", "topics",
    "start_paused", "max_bag_size", "max_cache_size", "storage_id", "exclude", "start_recording_immediately",
    "play.rate", "play.loop", "play.topics_to_filter", "play.regex_to_filter", "play.exclude_regex_to_filter",
    "play.read_ahead_queue_size", "play.read_ahead_max_bytes", "play.start_paused", "play.delay.sec",
    "play.delay.nsec", "play.start_offset.sec", "play.playback_duration.sec", "play.playback_until_timestamp.nsec",
    "play.clock_publish_frequency", "play.clock_publish_on_topic_publish", "play.wait_acked_timeout.nsec",
    "play.service_requests_source", "play.publish_service_request", "play.services_to_filter", "play.message_order",
]
#: A finished bag in the bag root (FuzzScene writes it) that a fuzzed player may open.
REPLAY_BAG = "replay_bag"
PATH_PARAMETERS = ["storage.uri", "bag_file", "bag_name", "bag_prefix", "uri", "record.qos_profile_overrides_path",
                   "play.qos_profile_overrides_path"]
EXTRA_ARGUMENTS = ["use_intra_process_comms", "forward_global_arguments", "use_global_arguments", "unknown"]
RECORDER_SERVICES: dict[str, Any] = {
    "pause": Pause, "resume": Resume, "toggle_paused": TogglePaused, "is_paused": IsPaused,
    "split_bagfile": SplitBagfile, "snapshot": Snapshot, "start_recording": Trigger,
    "stop_recording": Trigger, "get_stats": Trigger, "record": Record, "stop": Stop,
    "start_discovery": StartDiscovery, "stop_discovery": StopDiscovery, "is_discovery_running": IsDiscoveryRunning,
}
INT64_MIN, INT64_MAX = -2**63, 2**63 - 1
UINT64_MAX = 2**64 - 1
# Code points from many scripts and classes: combining marks, RTL, CJK, emoji, controls, noncharacters.
UNICODE_POOL = ("aZ_09-~.:=*?[]{}()$%@!\\\"' \t\n\x01\x7f\u00e9\u0301\u05d0\u0627\u200b\u200f\u202e\u4e2d"
                "\u6587\uac00\u30a2\ufeff\ufffd\uffff\U0001f600\U0001f4a9\U00010348")


class RequestGenerator:
    """Seeded requests; ``bag_root`` is where absolute, legitimate paths point, ``marker`` names escapes."""

    def __init__(self, rng: random.Random, bag_root: pathlib.Path, marker: str) -> None:
        self.rng = rng
        self.bag_root = bag_root
        self.marker = marker
        self._paths = 0

    # --- text -------------------------------------------------------------------------------------------
    def text(self, max_length: int = 24) -> str:
        """Random text; 1 % of it very long (10-100 k characters)."""
        rng = self.rng
        if rng.random() < 0.01:
            max_length = rng.randint(10_000, 100_000)
        length = rng.randint(0, max_length)
        pool = rng.choice([string.ascii_letters + "_", UNICODE_POOL, string.printable])
        return "".join(rng.choice(pool) for _ in range(length))

    def name(self) -> str:
        """A node name or namespace: valid ones, plausible mistakes and garbage."""
        rng = self.rng
        return rng.choice([
            lambda: "", lambda: f"fuzz_{rng.randint(0, 99)}", lambda: f"/ns{rng.randint(0, 9)}",
            lambda: "/", lambda: "//", lambda: "~/x", lambda: "1abc", lambda: "a b", lambda: "{x}",
            lambda: "/ns/" + self.text(8), self.text,
        ])()

    def path(self) -> str:
        """A path-like parameter value (see the module docstring)."""
        rng = self.rng
        self._paths += 1
        tag = f"{self.marker}_{self._paths}"
        return rng.choice([
            lambda: self.text(12).replace("/", "_").replace("\0", "") or tag,
            lambda: f"{tag}/sub",
            lambda: "../" * rng.randint(1, 4) + tag,
            lambda: f"/tmp/{tag}",
            lambda: f"sub/../../{tag}",
            lambda: str(self.bag_root / tag),
            lambda: "",
            lambda: f"{tag}\0nul",
        ])()

    # --- parameter values -------------------------------------------------------------------------------
    def integer(self) -> int:
        rng = self.rng
        return rng.choice([
            lambda: rng.randint(-10, 10), lambda: rng.randint(0, 4096),
            lambda: rng.choice([0, -1, 1, 2**31 - 1, -2**31, INT64_MAX, INT64_MIN]),
            lambda: rng.randint(INT64_MIN, INT64_MAX),
        ])()

    def double(self) -> float:
        rng = self.rng
        return rng.choice([
            lambda: rng.uniform(-10.0, 10.0), lambda: rng.uniform(0.0, 500.0),
            lambda: rng.choice([0.0, -0.0, 1e-300, 1e300, math.inf, -math.inf, math.nan]),
            lambda: rng.uniform(-1e308, 1e308),
        ])()

    def value(self, name: str) -> ParameterValue:
        """A value of a random ParameterType (NOT_SET included); sometimes a type that lies about its fields."""
        rng = self.rng
        n = rng.randint(0, 6)
        kind = rng.randint(ParameterType.PARAMETER_NOT_SET, ParameterType.PARAMETER_STRING_ARRAY)
        value = ParameterValue(type=kind)
        if kind == ParameterType.PARAMETER_BOOL:
            value.bool_value = rng.random() < 0.5
        elif kind == ParameterType.PARAMETER_INTEGER:
            value.integer_value = self.integer()
        elif kind == ParameterType.PARAMETER_DOUBLE:
            value.double_value = self.double()
        elif kind == ParameterType.PARAMETER_STRING:
            value.string_value = self.path() if name in PATH_PARAMETERS else self.text()
        elif kind == ParameterType.PARAMETER_BYTE_ARRAY:
            value.byte_array_value = [bytes([rng.randint(0, 255)]) for _ in range(n)]
        elif kind == ParameterType.PARAMETER_BOOL_ARRAY:
            value.bool_array_value = [rng.random() < 0.5 for _ in range(n)]
        elif kind == ParameterType.PARAMETER_INTEGER_ARRAY:
            value.integer_array_value = [self.integer() for _ in range(n)]
        elif kind == ParameterType.PARAMETER_DOUBLE_ARRAY:
            value.double_array_value = [self.double() for _ in range(n)]
        elif kind == ParameterType.PARAMETER_STRING_ARRAY:
            value.string_array_value = [self.text(10) for _ in range(n)]
        if rng.random() < 0.05:  # the type says one thing, the fields another
            value.type = rng.randint(0, 255)
        return value

    def parameters(self, names: list[str]) -> list[Parameter]:
        rng = self.rng
        chosen = [rng.choice(names) if rng.random() < 0.85 else self.text(16) for _ in range(rng.randint(0, 4))]
        return [Parameter(name=name, value=self.value(name)) for name in chosen]

    # --- requests ---------------------------------------------------------------------------------------
    def load(self) -> LoadNode.Request:
        rng = self.rng
        plugin = rng.choice(PLUGINS) if rng.random() < 0.85 else rng.choice(GARBAGE_PLUGINS + [self.text()])
        package = "components" if rng.random() < 0.9 else rng.choice(["", "tests", "os", self.text()])
        names = KNOWN_PARAMETERS + PATH_PARAMETERS
        parameters = self.parameters(names)
        if plugin == "components::CameraDriver" and rng.random() < 0.5:  # keep cameras small and cheap
            parameters += [Parameter(name="width", value=ParameterValue(type=ParameterType.PARAMETER_INTEGER,
                                                                         integer_value=rng.randint(1, 64) * 2)),
                           Parameter(name="height", value=ParameterValue(type=ParameterType.PARAMETER_INTEGER,
                                                                          integer_value=rng.randint(1, 64) * 2))]
        if plugin == "components::Recorder" and rng.random() < 0.7:
            parameters.append(Parameter(name="storage.uri", value=ParameterValue(
                type=ParameterType.PARAMETER_STRING, string_value=self.path())))
        if plugin == "components::Player" and rng.random() < 0.8:
            parameters.append(Parameter(name="storage.uri", value=ParameterValue(
                type=ParameterType.PARAMETER_STRING, string_value=REPLAY_BAG if rng.random() < 0.6 else self.path())))
        # Each field is mostly plausible, so that most requests get as far as a constructor; the garbage in one
        # field at a time is what is being tested.
        remaps = [rng.choice([f"chatter:={self.name()}", f"__node:={self.text(8)}", f"__ns:={self.name()}",
                              ":=", "a:=", ":=b", "~/x:=y", self.text(12)])
                  for _ in range(rng.randint(0, 3) if rng.random() < 0.4 else 0)]
        extra = [Parameter(name=rng.choice(EXTRA_ARGUMENTS + [self.text(8)]), value=self.value(""))
                 for _ in range(rng.randint(0, 2) if rng.random() < 0.3 else 0)]
        log_level = rng.choice([0, 10, 20, 30, 40, 50]) if rng.random() < 0.8 else rng.randint(0, 255)
        return LoadNode.Request(
            package_name=package, plugin_name=plugin, node_name=self.name() if rng.random() < 0.5 else "",
            node_namespace=self.name() if rng.random() < 0.5 else "", log_level=log_level, remap_rules=remaps,
            parameters=parameters, extra_arguments=extra)

    def unload(self, loaded: list[int], protected: set[int]) -> UnloadNode.Request:
        """Mostly a component a fuzz request loaded; otherwise any id except the ``protected`` ones."""
        rng = self.rng
        if loaded and rng.random() < 0.8:
            return UnloadNode.Request(unique_id=rng.choice(loaded))
        unique_id = rng.choice([0, UINT64_MAX, rng.randint(0, 100_000), rng.randint(0, UINT64_MAX)])
        return UnloadNode.Request(unique_id=unique_id if unique_id not in protected else 0)

    def recorder_call(self) -> tuple[str, Any]:
        """(service name under the recorder, request)."""
        service = self.rng.choice(list(RECORDER_SERVICES))
        if service == "record":  # rosbag2's ~/record takes a uri: escapes and odd names, as for parameters
            return service, Record.Request(uri=self.path())
        return service, RECORDER_SERVICES[service].Request()
