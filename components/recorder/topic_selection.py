"""Which topics the recorder subscribes to, and with which QoS: rosbag2's TopicFilter and QoS adaptation.

Selection: :mod:`baglib.format.topic_selection` (rosbag2 Jazzy's TopicFilter on names and types); topics without
publishers only with ``include_unpublished_topics`` (service event topics too). The recorder's own event topic is
never recorded.

QoS: reliable only if every publisher offers reliable, transient_local only if every publisher offers it,
keep_last with depth :data:`RECORDER_DEPTH`; an entry in the ``qos_profile_overrides_path`` YAML file replaces this.
"""
from __future__ import annotations

from pathlib import Path

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from baglib.format.topic_selection import TopicSelection
from components import qos_profiles
from components.recorder.recorder_options import RecordOptions

# rosbag2 uses 10. Here the subscription's queue is the only buffer between a publication and the intake
# callback, which runs on the container's (Python) executor: at 200 Hz, 10 messages are 50 ms, and a busy
# executor or a loaded machine stalls longer than that, losing messages long before the byte-bounded cache
# (max_cache_size) is anywhere near full. In-process the queue holds references to messages that exist anyway.
RECORDER_DEPTH = 100


class TopicFilter:
    """Decides per (topic, type) whether it is recorded: the options' selection, minus the recorder's own topics
    and, unless ``include_unpublished_topics``, topics without publishers."""

    def __init__(self, options: RecordOptions, own_topics: set[str]) -> None:
        self._options = options
        self._own_topics = own_topics
        self._selection = TopicSelection(options)

    def selects(self, topic: str, type_name: str, publisher_count: int) -> bool:
        if topic in self._own_topics:
            return False
        if publisher_count == 0 and not self._options.include_unpublished_topics:
            return False
        return self._selection.selects(topic, type_name)


def adapt_qos(offered: list[QoSProfile]) -> QoSProfile:
    """The subscription QoS that can receive from every offering publisher (rosbag2's rules)."""
    reliable = bool(offered) and all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    transient = bool(offered) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=RECORDER_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE)


def load_qos_overrides(parameter: str, path: Path | None) -> dict[str, QoSProfile]:
    """The recorder's ``record.qos_profile_overrides_path`` file (see qos_profiles.load_qos_overrides)."""
    return qos_profiles.load_qos_overrides(parameter, path, RECORDER_DEPTH)
