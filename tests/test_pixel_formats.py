"""The camera pixel formats the image encoder takes, checked with Debian's ``ffmpeg`` program (not PyAV).

YUV 4:2:2 (``yuv422_yuy2``/``yuyv`` = YUYV, ``yuv422``/``uyvy`` = UYVY) and Bayer (``bayer_*8``) frames are
encoded by the real codecs, decoded by ffmpeg, and compared with what ffmpeg itself makes of the camera's raw
bytes: a wrong byte order, filter pattern or colour range shows as a picture far from it. 16-bit depth comes back
bit-exact from PNG and from image_transport's ``compressedDepth`` format. A seeded stream of malformed images is
rejected frame by frame, each time with a reason that names the image. In-process with rclpy at the end: a depth
camera through the ImageEncoder and through a recorder's ``record.compress`` (and ``bag export``), and a Bayer
camera's H.264 stream.
"""
from __future__ import annotations

import random
import struct
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from foxglove_msgs.msg import CompressedVideo
from sensor_msgs.msg import CompressedImage, Image

from component_container.component_manager import ComponentManager
from components.image_encoder import codecs
from components.image_encoder.decoding import DecodeError, StillDecoder
from components.image_encoder.export import export_topic
from components.image_encoder.image_encoder import ImageEncoder
from components.image_encoder.pixel_formats import FORMATS
from components.image_encoder.stream import EncodeStream
from ffmpeg_tools import ffmpeg
from ipc_testing import wait_until
from test_compressed_recording import bag_messages, stamp_ns
from ipc_testing.in_process import probe
from test_image_encoder import decode, load, manager, psnr  # noqa: F401 - manager: the fixture

WIDTH, HEIGHT = 64, 48
FRAMES = 4
#: FFmpeg's names of the camera encodings (what the reference conversions read).
RAW = {"yuv422_yuy2": "yuyv422", "yuyv": "yuyv422", "yuv422": "uyvy422", "uyvy": "uyvy422",
       **{f"bayer_{order}8": f"bayer_{order}8" for order in ("rggb", "bggr", "gbrg", "grbg")}}


def colourful(index: int, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """A smooth moving RGB picture whose three channels differ everywhere (a swapped channel shows)."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    return np.stack([40 + x * 2.5 + index, 60 + y * 3.0, 200 - (x + y) * 1.2], axis=-1).clip(0, 255).astype(np.uint8)


def ffmpeg_raw(data: bytes, pix_fmt: str, out_fmt: str, width: int = WIDTH, height: int = HEIGHT) -> bytes:
    """Raw frames of ``pix_fmt`` converted by Debian's ffmpeg to raw ``out_fmt`` frames."""
    done = subprocess.run([ffmpeg(), "-v", "error", "-f", "rawvideo", "-pix_fmt", pix_fmt, "-s", f"{width}x{height}",
                           "-i", "pipe:0", "-f", "rawvideo", "-pix_fmt", out_fmt, "pipe:1"], input=data,
                          capture_output=True, timeout=60, check=True)
    return done.stdout


def camera_frames(encoding: str, pictures: list[np.ndarray]) -> list[bytes]:
    """What a camera of ``encoding`` sends for each RGB picture: YUV 4:2:2 made by ffmpeg (one run for all), a
    Bayer mosaic by slicing."""
    height, width = pictures[0].shape[:2]
    if encoding.startswith("bayer_"):
        mosaics = []
        for rgb in pictures:
            mosaic = np.empty((height, width), np.uint8)
            for cell, colour in enumerate(encoding[6:10]):
                mosaic[cell // 2::2, cell % 2::2] = rgb[cell // 2::2, cell % 2::2, "rgb".index(colour)]
            mosaics.append(mosaic.tobytes())
        return mosaics
    data = ffmpeg_raw(b"".join(rgb.tobytes() for rgb in pictures), "rgb24", RAW[encoding], width, height)
    size = len(data) // len(pictures)
    return [data[index * size:(index + 1) * size] for index in range(len(pictures))]


def image(encoding: str, data: bytes, width: int = WIDTH, height: int = HEIGHT, step: int | None = None,
          index: int = 0, bigendian: int = 0) -> Image:
    """An Image of ``data`` (``step``: rows without padding unless given)."""
    message = Image(width=width, height=height, encoding=encoding, is_bigendian=bigendian,
                    step=width * FORMATS[encoding].bytes_per_pixel if step is None else step)
    message.header.stamp.nanosec = index
    message.data = data
    return message


def encoded(codec: str, images: list[Image], **parameters: Any) -> list[bytes]:
    """Each image through the codec as the encoder's worker runs it (stills: one picture each; video: the access
    units of one stream)."""
    choice = codecs.choose(codec, "", parameters.get("quality", -1), 0, 30)
    if not choice.is_video:
        still = codecs.StillCodec(choice, parameters.get("width", 0))
        return [still.encode(message) for message in images]
    video = codecs.VideoCodec(choice, images[0].width, images[0].height)
    return [unit for message in images
            for _, _, unit in video.encode(codecs.pixels_of(message), message.encoding, keyframe=False)]


# --- YUV 4:2:2 and Bayer -------------------------------------------------------------------------------------
@pytest.mark.parametrize("encoding", list(RAW))
def test_yuv_and_bayer_frames_decode_with_ffmpeg_as_ffmpeg_reads_the_camera_bytes(encoding: str) -> None:
    raw = camera_frames(encoding, [colourful(index) for index in range(FRAMES)])
    images = [image(encoding, data, index=index) for index, data in enumerate(raw)]
    reference = np.frombuffer(ffmpeg_raw(b"".join(raw), RAW[encoding], "rgb24"), np.uint8)
    for codec, demuxer in (("h264", "h264"), ("jpeg", "mjpeg")):
        decoded = decode(b"".join(encoded(codec, images)), demuxer, WIDTH, HEIGHT)
        assert len(decoded) == FRAMES
        quality = [psnr(decoded[i], reference.reshape(decoded.shape)[i]) for i in range(FRAMES)]
        assert min(quality) > 35, (codec, quality)


def test_yuv_and_bayer_stills_are_named_as_what_they_decode_to() -> None:
    """image_transport's subscribers read the first part of ``format`` as the decoded image's encoding. A JPEG of
    a Bayer or YUV frame, and a PNG of a YUV frame, are colour pictures FFmpeg made: named rgb8, decoded
    (decoding.py) to rgb8. A PNG of a Bayer frame keeps the mosaic as it is: named as the camera's, it decodes to
    the very bytes sent."""
    for encoding in ("yuv422", "bayer_grbg8"):
        message = image(encoding, camera_frames(encoding, [colourful(0)])[0])
        for codec in ("jpeg", "png"):
            still = codecs.StillCodec(codecs.choose(codec, "", -1, 0, 30), 0)
            compressed = CompressedImage(format=still.format_of(encoding), data=still.encode(message))
            back = StillDecoder().decode(compressed)
            if codec == "png" and encoding.startswith("bayer"):
                assert compressed.format == f"{encoding}; png compressed "
                assert (back.encoding, back.step, bytes(back.data)) == (encoding, WIDTH, bytes(message.data))
            else:
                assert compressed.format == f"rgb8; {codec} compressed bgr8"
                assert (back.encoding, back.width, back.height, back.step) == ("rgb8", WIDTH, HEIGHT, WIDTH * 3)


def test_scaled_yuv_bayer_and_depth_frames_keep_their_pictures() -> None:
    """``width`` scales in the same swscale pass that converts; depth by nearest sample (no blended ranges)."""
    rgb = colourful(0, 128, 96)
    for encoding, codec in (("yuyv", "jpeg"), ("bayer_bggr8", "jpeg"), ("uyvy", "png"), ("uyvy", "h264")):
        message = image(encoding, camera_frames(encoding, [rgb])[0], 128, 96)
        if codec == "h264":
            video = codecs.VideoCodec(codecs.choose(codec, "", -1, 0, 30), 64, 48)
            data = b"".join(u for _, _, u in video.encode(codecs.pixels_of(message), encoding, keyframe=True))
        else:
            data = encoded(codec, [message], width=64)[0]
        small = decode(data, {"jpeg": "mjpeg", "png": "png_pipe", "h264": "h264"}[codec], 64, 48)
        assert len(small) == 1 and psnr(small[0], rgb[::2, ::2]) > 25, encoding
    depth = np.arange(128 * 96, dtype=np.uint16).reshape(96, 128) * 7
    data = encoded("compressedDepth", [image("16UC1", depth.tobytes(), 128, 96)], width=64)[0]
    half = np.frombuffer(ffmpeg_png(data[12:], 64, 48), "<u2").reshape(48, 64)
    assert np.isin(half, depth).all()  # every sample one of the camera's
    with pytest.raises(codecs.EncodeError, match="^a 128x96 bayer_bggr8 image: PNG keeps a Bayer mosaic as it is"):
        encoded("png", [image("bayer_bggr8", camera_frames("bayer_bggr8", [rgb])[0], 128, 96)], width=64)


# --- 16-bit depth ----------------------------------------------------------------------------------------------
def ffmpeg_png(data: bytes, width: int, height: int) -> bytes:
    """A 16-bit PNG decoded by Debian's ffmpeg to little-endian samples."""
    done = subprocess.run([ffmpeg(), "-v", "error", "-f", "png_pipe", "-i", "pipe:0", "-f", "rawvideo", "-pix_fmt",
                           "gray16le", "pipe:1"], input=data, capture_output=True, timeout=60, check=True)
    assert len(done.stdout) == width * height * 2, done.stderr
    return done.stdout


def depth_frame(index: int, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """Millimetres with the whole 16-bit range in use: a ramp, a far corner, invalid (0) samples."""
    y, x = np.mgrid[0:height, 0:width]
    depth = (500 + 37 * x + 101 * y + index * 13).astype(np.uint16)
    depth[:4, :4], depth[-1, -1] = 0, 65535
    return depth


@pytest.mark.parametrize(("encoding", "bigendian"), [("16UC1", 0), ("mono16", 0), ("16UC1", 1)])
def test_depth_comes_back_bit_exact_from_compressed_depth_and_png(encoding: str, bigendian: int) -> None:
    depths = [depth_frame(index) for index in range(FRAMES)]
    images = [image(encoding, depth.astype(">u2" if bigendian else "<u2").tobytes(), bigendian=bigendian)
              for depth in depths]
    for codec, expected_format in (("compressedDepth", f"{encoding}; compressedDepth png"),
                                   ("png", f"{encoding}; png compressed ")):
        still = codecs.StillCodec(codecs.choose(codec, "", -1, 0, 30), 0)
        for depth, message in zip(depths, images):
            data = still.encode(message)
            if codec == "compressedDepth":  # compression_common.h's ConfigHeader: INV_DEPTH, two zero floats
                assert struct.unpack("<iff", data[:12]) == (0, 0.0, 0.0)
                data = data[12:]
            assert np.array_equal(np.frombuffer(ffmpeg_png(data, WIDTH, HEIGHT), "<u2").reshape(HEIGHT, WIDTH), depth)
            back = StillDecoder().decode(CompressedImage(format=still.format_of(encoding), data=still.encode(message)))
            assert (back.encoding, back.width, back.height, back.step, back.is_bigendian) == (encoding, WIDTH, HEIGHT,
                                                                                             WIDTH * 2, 0)
            assert bytes(back.data) == depth.astype("<u2").tobytes()


def test_compressed_depth_messages_other_than_16_bit_png_are_refused_by_name() -> None:
    png = encoded("compressedDepth", [image("16UC1", depth_frame(0).tobytes())])[0]
    cases = {("16UC1; compressedDepth rvl", png): "RVL", ("32FC1; compressedDepth png", png): "32-bit float",
             ("16UC1; compressedDepth png", png[:12]): "12-byte header"}
    for (format_, data), named in cases.items():
        with pytest.raises(DecodeError, match=named):
            StillDecoder().decode(CompressedImage(format=format_, data=data))


# --- the formats the encoder took before -----------------------------------------------------------------------
@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8"])
@pytest.mark.parametrize("codec", ["jpeg", "png"])
def test_every_eight_bit_format_makes_a_picture_ffmpeg_reads(codec: str, encoding: str) -> None:
    """mono8 JPEG and bgr8/bgra8 PNG were rejected, every frame (simplejpeg wants 3-D arrays; FFmpeg's PNG
    encoder has no bgr24)."""
    rgb = colourful(0)
    channels = {"rgb8": rgb, "bgr8": rgb[:, :, ::-1], "rgba8": np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)]),
                "bgra8": np.dstack([rgb[:, :, ::-1], np.full(rgb.shape[:2], 255, np.uint8)]),
                "mono8": rgb[:, :, 1:2]}[encoding]
    data = encoded(codec, [image(encoding, np.ascontiguousarray(channels).tobytes())])[0]
    decoded = decode(data, "mjpeg" if codec == "jpeg" else "png_pipe", WIDTH, HEIGHT)[0]
    expected = np.repeat(rgb[:, :, 1:2], 3, axis=2) if encoding == "mono8" else rgb
    assert psnr(decoded, expected) > (38 if codec == "jpeg" else 99)


def test_one_decoder_gives_every_png_of_a_topic_its_own_picture() -> None:
    """The player decodes a topic with one StillDecoder: its PNG decoder, kept between pictures, gave each
    picture after the first offset by the one before."""
    still, decoder = codecs.StillCodec(codecs.choose("png", "", -1, 0, 30), 0), StillDecoder()
    for index in range(3):
        rgb = colourful(index * 20)
        data = still.encode(image("rgb8", rgb.tobytes()))
        back = decoder.decode(CompressedImage(format=still.format_of("rgb8"), data=data))
        assert bytes(back.data) == rgb.tobytes(), f"picture {index}"


# --- rejections ------------------------------------------------------------------------------------------------
def test_16_bit_depth_and_codecs_that_cannot_hold_it_are_refused_with_the_way_out() -> None:
    depth, colour = image("16UC1", depth_frame(0).tobytes()), image("rgb8", colourful(0).tobytes())
    with pytest.raises(codecs.EncodeError, match=r"^a 64x48 16UC1 image .*JPEG cannot.* png or compressedDepth"):
        encoded("jpeg", [depth])
    with pytest.raises(codecs.EncodeError, match=r"^a 64x48 16UC1 image .*video cannot.* png or compressedDepth"):
        encoded("h264", [depth])
    with pytest.raises(codecs.EncodeError, match=r"^a 64x48 rgb8 image is not 16-bit depth: compressedDepth takes"):
        encoded("compressedDepth", [colour])


ENCODINGS = [*FORMATS, "rgb16", "32FC1", "", "RGB8", "nv21"]


def malformed(rng: random.Random, preferred: list[str]) -> Image:
    """One image of a seeded stream: mostly well formed and small, half of them in one of the ``preferred``
    encodings (sizes and encodings change from one to the next), else with an unknown encoding, short or long data,
    a short or padded step, no pixels, an odd size, or the other byte order."""
    encoding = rng.choice(preferred if rng.random() < 0.5 else ENCODINGS)
    width, height = rng.choice([2, 4, 16, 64]), rng.choice([2, 4, 16, 48])
    if rng.random() < 0.3:
        width, height = rng.choice([0, 1, 3, 17, width]), rng.choice([0, 1, 3, 17, height])
    row = width * (FORMATS[encoding].bytes_per_pixel if encoding in FORMATS else rng.choice([1, 3]))
    step = rng.choice([row, row, row + rng.randint(1, 9), max(0, row - 1), 0])
    size = rng.choice([step * height, step * height, step * height + 7, max(0, step * height - 1), 0])
    message = image(encoding or "rgb8", rng.randbytes(size), width, height, step, bigendian=rng.choice([0, 0, 1]))
    message.encoding = encoding
    return message


@pytest.mark.parametrize("codec", ["jpeg", "png", "h264", "compressedDepth"])
def test_a_seeded_stream_of_malformed_images_is_rejected_with_reasons_that_name_the_image(codec: str) -> None:
    """Each rejection's reason (logged once per kind) begins with the image it is about: a 0-pixel-wide JPEG
    leaked simplejpeg's 'broadcasting rows is not supported', and others libjpeg-turbo's and FFmpeg's errors."""
    reasons: list[str] = []
    stream = EncodeStream("/fuzz", codecs.choose(codec, "", -1, 0, 30), 0, lambda message, keyframe: None,
                          reasons.append)
    rng = random.Random(35)
    preferred = ["16UC1", "mono16"] if codec == "compressedDepth" else ["rgb8", "mono8", "yuyv", "bayer_gbrg8"]
    try:
        for number in range(150):
            message = malformed(rng, preferred)
            before = (stream.stats()["rejected"], len(reasons))
            stream.offer(message)
            assert wait_until(lambda: stream.stats()["waiting"] == 0, 20.0, interval=0.001)
            counts = stream.stats()
            if len(reasons) > before[1]:
                assert counts["rejected"] == before[0] + 1
                prefix = f"Cannot encode an image of /fuzz: a {message.width}x{message.height} "
                assert reasons[-1].startswith(prefix), f"image {number}: {reasons[-1]}"
        assert counts["received"] == counts["published"] + counts["rejected"] == 150
        assert counts["published"] > 10 and counts["rejected"] > 10
    finally:
        stream.stop(10.0)


def test_an_encoder_without_a_preset_says_so_in_its_load_error() -> None:
    """h264_nvenc has no default preset; on a machine without an NVIDIA encoder the error said (or 'preset' '')."""
    with pytest.raises(ValueError) as refused:
        codecs.check_codec(codecs.choose("h264_nvenc", "", -1, 0, 30))
    assert str(refused.value).startswith("parameter 'codec': encoder 'h264_nvenc' cannot be opened on this machine: ")
    assert "''" not in str(refused.value)
    with pytest.raises(ValueError, match=r"^parameter 'codec' \(or its 'preset' 'p4'\): encoder 'h264_nvenc'"):
        codecs.check_codec(codecs.choose("h264_nvenc", "p4", -1, 0, 30))


# --- in-process, through the ImageEncoder ------------------------------------------------------------------------
def stamp_of(message: Any) -> int:
    """The stamp of an Image or CompressedImage (header) or a CompressedVideo (timestamp), in ns."""
    stamp = message.timestamp if isinstance(message, CompressedVideo) else message.header.stamp
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def test_a_depth_camera_comes_back_bit_exact_from_compressed_depth(manager: ComponentManager) -> None:
    topic = "/pix_depth/image_raw"
    encoder = load(manager, "ImageEncoder", "pix_depth_enc", topics=[topic], codec="compressedDepth")
    assert encoder.output_topic(topic) == f"{topic}/compressedDepth"  # known before any frame: the recorder's need
    depth = probe(manager, CompressedImage, f"{topic}/compressedDepth")
    raw = probe(manager, Image, topic)
    camera = load(manager, "CameraDriver", "pix_depth", width=320, height=240, encoding="16UC1", content="photo",
                  fps=60.0)
    assert wait_until(lambda: len(depth.messages) >= 12, 30.0)
    manager.unload(next(c.unique_id for c in manager.components() if c.node is camera))
    sent = {stamp_of(message): message for message in raw.messages}
    decoder = StillDecoder()
    for message in depth.messages:
        assert message.format == "16UC1; compressedDepth png"
        back = decoder.decode(message)
        original = sent[stamp_of(message)]
        assert (back.encoding, back.width, back.height, back.step) == ("16UC1", 320, 240, 640)
        assert bytes(back.data) == bytes(original.data)
    assert encoder.stats()["topics"][topic]["rejected"] == 0


def test_a_bayer_camera_gives_an_h264_stream_that_ffmpeg_decodes(manager: ComponentManager) -> None:
    topic = "/pix_bayer/image_raw"
    load(manager, "ImageEncoder", "pix_bayer_enc", topics=[topic], codec="h264")
    video = probe(manager, CompressedVideo, f"{topic}/video")
    raw = probe(manager, Image, topic)
    camera = load(manager, "CameraDriver", "pix_bayer", width=320, height=240, encoding="bayer_rggb8",
                  content="photo", fps=60.0)
    assert wait_until(lambda: len(video.messages) >= 12, 30.0)
    manager.unload(next(c.unique_id for c in manager.components() if c.node is camera))
    frames = list(video.messages)
    decoded = decode(b"".join(bytes(m.data) for m in frames), "h264", 320, 240)
    assert len(decoded) == len(frames)
    sent = {stamp_of(message): message for message in raw.messages}
    originals = b"".join(bytes(sent[stamp_of(message)].data) for message in frames)
    reference = np.frombuffer(ffmpeg_raw(originals, "bayer_rggb8", "rgb24", 320, 240), np.uint8).reshape(decoded.shape)
    assert min(psnr(decoded[i], reference[i]) for i in range(len(frames))) > 30




def test_a_recorder_with_compress_depth_records_the_depth_camera_bit_exact(manager: ComponentManager,
                                                                           tmp_path: Path) -> None:
    """``record.compress:=compressedDepth``: the recorder learns the output topic from the encoder before any
    frame (ImageEncoder.output_topic) and records ``<image>/compressedDepth`` in place of the raw topic; the bag's
    messages, read by rosbags, decode to the camera's very frames."""
    topic = "/pix_rec_depth/image_raw"
    recorder = load(manager, "Recorder", "pix_rec", **{
        "storage.uri": str(tmp_path / "depth"), "record.compress": "compressedDepth",
        "record.compress_topics": [topic], "record.topics": [topic]})
    output = f"{topic}/compressedDepth"
    assert wait_until(lambda: output in recorder._topics, 20.0), "the recorder never took the encoder's output"
    raw = probe(manager, Image, topic)
    camera = load(manager, "CameraDriver", "pix_rec_cam", width=160, height=120, encoding="16UC1",
                  content="photo", fps=30.0, topic=topic)
    assert wait_until(lambda: len(raw.messages) >= 10, 30.0)
    manager.unload(next(c.unique_id for c in manager.components() if c.node is camera))
    encoder = next(c.node for c in manager.components() if isinstance(c.node, ImageEncoder))
    assert wait_until(lambda: encoder.stats()["topics"][topic]["waiting"] == 0, 20.0)
    published = encoder.stats()["topics"][topic]["published"]  # all but what a loaded machine made it skip
    # the recorder counts the camera's frames as received, the encoder's skips among its drops (encoder_behind)
    assert wait_until(lambda: (counts := recorder.stats()["current"]["topics"][output])["received"]
                      - counts["dropped"] == published, 20.0), recorder.stats()["current"]["topics"][output]
    stats = recorder.stop_recording()
    assert topic not in stats["topics"] and set(stats["drop_reasons"].get(output, {})) <= {"encoder_behind"}
    assert stats["topics"][output]["written"] == published
    recorded = bag_messages(tmp_path / "depth")[output]
    sent = {stamp_of(message): bytes(message.data) for message in raw.messages}
    assert len(recorded) == published >= 5
    for message in recorded:
        assert message.format == "16UC1; compressedDepth png"
        back = StillDecoder().decode(CompressedImage(format=message.format, data=bytes(message.data)))
        assert bytes(back.data) == sent[stamp_ns(message.header.stamp)]
    # bag export writes each message's PNG (after the header): 16-bit grey files any program opens
    report = export_topic(tmp_path / "depth", output, tmp_path / "pngs")
    assert (report.written, report.kind) == (len(recorded), "compressedDepth")
    files = sorted((tmp_path / "pngs").iterdir())
    assert [f.suffix for f in files] == [".png"] * len(recorded)
    assert ffmpeg_png(files[0].read_bytes(), 160, 120) == sent[stamp_ns(recorded[0].header.stamp)]
