"""S4, compressed recording: 1080p30 cameras with photographic content (``content:=photo``), drivers, encoder
and recorder in one container process, intra-process.

* **codec limit**, per compressed codec: cores x frame interval / the CPU time one frame costs the codec alone
  (benchmarks/record/codec_limit.py), measured first;
* **ramp**, per codec (``raw``, ``jpeg``, ``h264``, ``h265``, ``av1`` at the encoder's defaults, or
  ``codec:preset`` such as ``h264:ultrafast``): the largest camera count without loss, to the camera, searched
  from the target share of the codec limit (benchmarks/record/camera_search.py; raw, without a limit, from
  ``--s4-raw-cameras`` down), up to ``--s4-max-cameras``. ``raw`` records ``image_raw``; the others
  record with ``record.compress:=<codec>`` (the recorder loads its own ImageEncoder and records
  ``<image>/compressed`` or ``<image>/video`` instead). Every camera's CameraInfo is recorded too: the frames'
  accounting (benchmarks/record/frames.py).
* **beside**, per compressed codec: ``--s4-beside-cameras`` cameras recorded raw *and* compressed by one recorder,
  with a ``components::ImageEncoder`` of its own in the container: the raw recording must lose nothing, and the
  PSNR of the compressed frames is measured against the raw frames of the same bag, matched by stamp. The
  encoder is asked for a keyframe as the measured bag begins (its recorder's subscription is older than the bag).

Each run follows the recorder protocol of benchmarks/record/modes.py (warm-up, a fresh bag, the window).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Optional

import numpy as np
from std_srvs.srv import Trigger

from benchmarks.record.bench import Bench, guarded
from benchmarks.record.camera_search import largest_lossless, lossy_above, next_count, start_count
from benchmarks.record.codec_limit import measure_limits
from benchmarks.record.figures import good
from benchmarks.record.frames import camera_counts, decoded_frames, psnr, read_stamps, sample_stamps
from benchmarks.record.measure import MB
from benchmarks.record.modes import (Processes, RecorderServices, record_window, recorder_component,
                                     start_container, window_result)
from benchmarks.record.scenarios import PUBLISH_RATE_OK, Scenario, TopicSpec
from benchmarks.record.targets import S4_LIMIT_SHARE
from ipc_testing import call

CODECS = ("raw", "jpeg", "h264", "h265", "av1")
OUTPUT = {"jpeg": ("compressed", "sensor_msgs/msg/CompressedImage")}
VIDEO = ("video", "foxglove_msgs/msg/CompressedVideo")
TB = 1e12


def s4_scenario(args: argparse.Namespace, cameras: int) -> Scenario:
    return Scenario("S4", f"S4 compressed recording, {cameras} camera(s)", args.s4_seconds, cameras=cameras,
                    width=args.width, height=args.height, fps=args.fps, content="photo")


def codec_of(label: str) -> tuple[str, str]:
    """(codec, preset) of an S4 codec label: ``h264`` (the encoder's default preset) or ``h264:ultrafast``."""
    codec, _, preset = label.partition(":")
    return codec, preset


def output_topic(image_topic: str, codec: str) -> str:
    """Where the recorded frames of ``image_topic`` are: itself (raw), or the encoder's output."""
    return image_topic if codec == "raw" else f"{image_topic}/{OUTPUT.get(codec, VIDEO)[0]}"


def image_topics(scenario: Scenario) -> list[str]:
    return [name for name, spec in scenario.topics().items() if spec.kind == "image"]


def components(scenario: Scenario, label: str, name: str, uri: Path, args: argparse.Namespace,
               beside: bool) -> tuple[list[dict[str, Any]], Optional[str], dict[str, TopicSpec]]:
    """The recorder (and, beside raw, the encoder) of a run; the encoder's node name; the topics it records."""
    codec, preset = codec_of(label)
    settings = {"preset": preset} if preset else {}
    topics = scenario.topics()
    cameras = image_topics(scenario)
    expected = {spec.name: spec for spec in topics.values() if beside or codec == "raw" or spec.kind != "image"}
    for topic in cameras if codec != "raw" else []:
        out = output_topic(topic, codec)
        expected[out] = TopicSpec(out, OUTPUT.get(codec, VIDEO)[1], "compressed", scenario.fps)
    recorder = recorder_component(name, list(expected) if beside or codec == "raw" else
                                  [t for t, spec in topics.items() if spec.kind != "image"], uri, args, True)
    if codec == "raw":
        return [recorder], None, expected
    if not beside:
        recorder["parameters"]["record"].update({"compress": codec, "compress_topics": cameras,
                                                  **{f"compress_{key}": value for key, value in settings.items()}})
        return [recorder], f"{name}_encoder", expected
    encoder = {"package": "components", "plugin": "components::ImageEncoder", "name": f"enc_{name}",
               "parameters": {"codec": codec, "topics": cameras, **settings},
               "extra_arguments": {"use_intra_process_comms": True}}
    return [encoder, recorder], f"enc_{name}", expected


def run_compressed(bench: Bench, scenario: Scenario, label: str, beside: bool = False) -> dict[str, Any]:
    """One run of S4 (module docstring): the window's frames per camera, bytes, CPU, latency; PSNR beside raw."""
    args = bench.args
    codec = codec_of(label)[0]
    tag = bench.next_tag(scenario, codec + ("_beside" if beside else ""))
    uri, name = bench.workdir / tag, f"rec_{tag}"
    recorded, encoder, expected = components(scenario, label, name, uri, args, beside)
    files = [bench.write_yaml(f"{tag}_drivers", scenario.components()), bench.write_yaml(f"{tag}_recorder", recorded)]
    processes = Processes("ipc")
    processes.by_label["ipc"] = start_container(bench, f"bench_{tag}", files)
    services = RecorderServices(bench.node, name)
    clients = {verb: bench.node.create_client(Trigger, f"/{encoder}/{verb}")
               for verb in ("get_stats", "request_keyframe")} if encoder else {}
    keyframe = (lambda: call(bench.node, clients["request_keyframe"], timeout=30.0)) if beside and encoder else None
    try:
        window = record_window(bench, processes, services, expected, scenario.seconds, keyframe)
        encoder_stats = (json.loads(call(bench.node, clients["get_stats"], timeout=60.0, again=True).message)
                         if clients else None)
    finally:
        services.destroy()
        for client in clients.values():
            bench.node.destroy_client(client)
        processes.stop()
    bag = Path(f"{uri}_1")
    try:
        result = frames_result(bag, scenario, codec, beside, window.start.time_ns, window.end.time_ns,
                               args.s4_psnr_frames)
    finally:
        bench.discard_bags(bag, uri)
    result.update(window_result(window.start, window.end, processes.pids()))
    window_s = result["window_s"]
    result.update({"codec": label, "cameras": scenario.cameras, "beside": beside,
                   "latency_ms": window.live.get("write_latency_ms"), "recorder_error": window.final.get("error"),
                   "encoder_skipped": (sum(t["skipped"] for t in encoder_stats["topics"].values())
                                       if encoder_stats else None),
                   "mb_per_s": result["recorded_bytes"] / MB / window_s,
                   "cpu_per_camera": result["total_cpu_s"] / window_s / scenario.cameras,
                   "peak_rss_mb": window.rss})
    result["hours_per_tb"] = TB / (result["mb_per_s"] * MB) / 3600 if result["mb_per_s"] else None
    result["lossless"] = (result["lost"] == 0 and result["info_lost"] == 0
                          and result["min_pub_ratio"] >= PUBLISH_RATE_OK and not result["recorder_error"])
    return result


def frames_result(bag: Path, scenario: Scenario, codec: str, beside: bool, t0: int, t1: int,
                  psnr_frames: int) -> dict[str, Any]:
    """The bag's frames per camera in ``[t0, t1]`` (frames.camera_counts), totals, bytes against raw, and beside
    raw, the raw recording's own counts and the PSNR of camera 0's compressed frames."""
    topics = scenario.topics()
    cameras = image_topics(scenario)
    frame_bytes = scenario.width * scenario.height * 3
    first = output_topic(cameras[0], codec)
    stamps, kept, _ = read_stamps(bag, {first} if beside else set(), frame_bytes)
    info_of = {spec.image_topic: name for name, spec in topics.items() if spec.kind == "camera_info"}
    per_camera, raw_counts = {}, {}
    for topic in cameras:
        info = stamps.get(info_of[topic], [])
        per_camera[topic] = camera_counts(info, stamps.get(output_topic(topic, codec), []), t0, t1, scenario.fps)
        if beside:
            raw_counts[topic] = camera_counts(info, stamps.get(topic, []), t0, t1, scenario.fps)
    totals = {key: sum(c[key] for c in per_camera.values())
              for key in ("published", "recorded", "lost", "info_lost", "duplicates", "frame_bytes", "info_bytes")}
    raw_bytes = totals["published"] * topics[cameras[0]].size
    result: dict[str, Any] = {
        "per_camera": per_camera, **totals, "min_pub_ratio": min(c["pub_ratio"] for c in per_camera.values()),
        "raw_pct": 100.0 * totals["frame_bytes"] / raw_bytes if raw_bytes else None,
        "recorded_bytes": sum(size for entries in stamps.values() for stamp, size in entries if t0 <= stamp <= t1)}
    if beside:
        result["raw"] = {key: sum(c[key] for c in raw_counts.values()) for key in ("published", "recorded", "lost")}
        result["raw"]["min_pub_ratio"] = min(c["pub_ratio"] for c in raw_counts.values())
        sample = sample_stamps(stamps.get(first, []), t0, t1, psnr_frames)
        _, _, pixels = read_stamps(bag, set(), frame_bytes, sample)
        shape = (scenario.height, scenario.width, 3)
        raw = {stamp: np.frombuffer(data, np.uint8).reshape(shape) for stamp, data in pixels.items()}
        result["psnr"] = psnr(dict(decoded_frames(codec, kept.get(first, []), set(raw))), raw)
    return result


def cap_of(args: argparse.Namespace, label: str) -> int:
    """The most cameras a codec's ramp runs: raw, which has no codec limit to start from, starts at its cap."""
    return args.s4_raw_cameras if codec_of(label)[0] == "raw" else args.s4_max_cameras


def ramp(bench: Bench, s4: dict[str, Any], label: str) -> None:
    """The largest lossless camera count of ``label`` (camera_search.py), started near its codec limit."""
    args = bench.args
    limit = ((s4["limits"].get("codecs") or {}).get(label) or {}).get("cameras")
    cap = s4["caps"][label] = cap_of(args, label)
    start = start_count(limit, S4_LIMIT_SHARE, cap)
    outcomes: dict[int, bool] = {}
    kept: dict[int, float] = {}
    while (cameras := next_count(outcomes, start, cap, kept)) is not None:
        scenario = s4_scenario(args, cameras)
        step = guarded(bench, f"S4 {label} {cameras} camera(s)", lambda: run_compressed(bench, scenario, label))
        step.update({"codec": label, "cameras": cameras})
        s4["steps"].append(step)
        outcomes[cameras] = good(step) and step["lossless"]
        if good(step) and step["published"]:
            kept[cameras] = cameras * step["recorded"] / step["published"] * min(1.0, step["min_pub_ratio"])
    s4["largest_lossless"][label] = largest_lossless(outcomes)
    s4["limit_reached"][label] = lossy_above(outcomes) is not None


def run_s4(bench: Bench) -> dict[str, Any]:
    """S4: the codec limits, each codec's ramp, then each compressed codec recorded beside raw."""
    args = bench.args
    codecs = [codec.strip() for codec in args.s4_codecs.split(",") if codec.strip()]
    s4: dict[str, Any] = {"scenario": s4_scenario(args, 1).summary(), "codecs": codecs, "cap": args.s4_max_cameras,
                          "ramp": "search", "caps": {}, "seconds": args.s4_seconds, "steps": [],
                          "largest_lossless": {}, "limit_reached": {}, "beside": []}
    compressed = {label: codec_of(label) for label in codecs if codec_of(label)[0] != "raw"}
    s4["limits"] = guarded(bench, "S4 codec limits (CPU per frame of each codec alone)",
                           lambda: measure_limits(compressed, args.width, args.height, args.fps,
                                                  args.s4_cost_frames), retry=False)
    for codec in codecs:
        ramp(bench, s4, codec)
    scenario = s4_scenario(args, args.s4_beside_cameras)
    for codec in compressed:
        run = guarded(bench, f"S4 {codec} beside raw, {scenario.cameras} camera(s)",
                      lambda: run_compressed(bench, scenario, codec, beside=True))
        run.update({"codec": codec, "cameras": scenario.cameras, "beside": True})
        s4["beside"].append(run)
    s4["sizing"] = sizing(s4)
    return s4


def sizing(s4: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per codec, what one 1080p30 camera costs: from its largest lossless step (CPU and bytes per camera) and its
    run beside raw (PSNR). A codec that lost frames with one camera already is shown with that step: the CPU it
    got then, while frames were skipped (its ``largest_lossless`` is 0)."""
    out = {}
    for codec in s4["codecs"]:
        steps = [s for s in s4["steps"] if s["codec"] == codec and good(s)]
        if not steps:
            continue
        step = max((s for s in steps if s["lossless"]), key=lambda s: s["cameras"], default=steps[0])
        beside = next((b for b in s4["beside"] if b["codec"] == codec and good(b)), None)
        per_camera = step["mb_per_s"] / step["cameras"]
        out[codec] = {"cameras": step["cameras"], "cpu_per_camera": step["cpu_per_camera"],
                      "mb_per_s_per_camera": per_camera, "raw_pct": step["raw_pct"],
                      "hours_per_tb_per_camera": TB / (per_camera * MB) / 3600,
                      "psnr_db": (beside or {}).get("psnr", {}).get("psnr_db"),
                      "largest_lossless": s4["largest_lossless"][codec],
                      "limit_reached": s4["limit_reached"][codec]}
    return out
