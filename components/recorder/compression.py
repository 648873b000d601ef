"""``record.compress``: image topics recorded compressed, by an ImageEncoder the recorder loads itself.

``record.compress:=h264`` (or ``jpeg``, ``png``, ``h265``, ``av1`` or an FFmpeg encoder name) loads a
``components::ImageEncoder`` into the recorder's container, through the container's own load path
(:meth:`ComponentNode.load_owned_component`): it is listed like any component (``ipc-component top`` shows its
skips), runs on the container's executor, takes the camera frames in-process, and is unloaded with the recorder.
The image topics it encodes are ``record.compress_topics`` and/or those ``record.compress_regex`` matches (neither:
every ``sensor_msgs/msg/Image`` topic). The recorder then records each one's output (``<image>/video`` or
``<image>/compressed``) instead of the raw topic, whatever its own topic selection says about either.
``record.compress_<name>`` is the encoder's ``<name>`` parameter (preset, quality, bitrate, keyframe_interval,
width); an encoder that refuses its parameters is a load error of the recorder naming the recorder's parameter.

Video files stay decodable on their own, as those of any encoder in the container: see
components/recorder/keyframe_gate.py.
"""
from __future__ import annotations

import re
from typing import Any

from component_container.component_manager import ComponentConstructionError
from component_container.component_node import ComponentNode
from component_container.component_options import LoadRequestError
from component_container.startup_file import load_request
from components.image_encoder.image_encoder import IMAGE_TYPE, ImageEncoder
from components.recorder.recorder_options import ENCODER_SETTINGS, RecordOptions

PACKAGE = "components"
PLUGIN = "components::ImageEncoder"
#: The encoder's parameter names -> the recorder's, for the encoder's load errors.
_NAMES = {"codec": "record.compress", "topics": "record.compress_topics", "regex": "record.compress_regex",
          **{name: f"record.compress_{name}" for name in ENCODER_SETTINGS}}
_PARAMETER = re.compile(r"'(" + "|".join(_NAMES) + r")'")


class Compression:
    """The encoder a recorder loaded, which topics it replaces, and (video) the keyframes it published."""

    def __init__(self, recorder: ComponentNode, options: RecordOptions) -> None:
        if not recorder.uses_intra_process:
            raise ValueError("parameter 'record.compress' encodes the container's images in-process: load the "
                             "recorder with use_intra_process_comms:=true")
        parameters: dict[str, Any] = {"codec": options.compress, "polling_interval": max(0.05,
                                                                                          options.polling_interval)}
        if options.compress_topics:
            parameters["topics"] = options.compress_topics
        parameters["regex"] = options.compress_regex or ("" if options.compress_topics else ".")
        parameters.update(options.compress_settings)
        request = load_request({"package": PACKAGE, "plugin": PLUGIN, "name": f"{recorder.get_name()}_encoder",
                                "namespace": recorder.get_namespace(), "parameters": parameters,
                                "extra_arguments": {"use_intra_process_comms": True}}, 1)
        try:
            encoder = recorder.load_owned_component(request)
        except (ComponentConstructionError, LoadRequestError) as exc:  # with the encoder's own message
            text = _PARAMETER.sub(lambda m: f"'{_NAMES[m.group(1)]}'", str(exc))
            raise ValueError(f"record.compress:={options.compress}: the image encoder cannot be loaded: "
                             f"{text}") from None
        assert isinstance(encoder, ImageEncoder)
        self.encoder = encoder

    def replaces(self, topic: str, type_name: str) -> bool:
        """A raw image topic that is recorded compressed instead (never itself)."""
        return type_name == IMAGE_TYPE and self.encoder.encodes(topic)

    def output(self, topic: str) -> bool:
        """The encoder's output of an image topic it encodes (recorded whatever the topic selection says)."""
        parent = topic.rpartition("/")[0]
        return bool(parent) and topic == self.encoder.output_topic(parent) and self.encoder.encodes(parent)

