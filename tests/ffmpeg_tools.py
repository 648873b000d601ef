"""Debian's ``ffmpeg`` and ``ffprobe`` programs, for tests that check encoded video with a decoder the project does
not use (PyAV is the encoder's library)."""
from __future__ import annotations

import json
import shutil
import subprocess
from typing import Any

import pytest


def ffmpeg(program: str = "ffmpeg") -> str:
    """The ffmpeg (or ffprobe) program; the tests fail (never skip) without it: `make test` installs Debian's
    package."""
    path = shutil.which(program)
    if path is None:
        pytest.fail(f"the {program} command-line program is missing: `apt-get install -y ffmpeg` (`make test` "
                    "does this)")
    return path


def probe_h264(data: bytes) -> dict[str, Any]:
    """What ffprobe reads from an Annex B H.264 stream: ``stream`` (width, height, frames decoded) and
    ``packets`` (one per access unit, in order, with its flags: ``K`` for a keyframe)."""
    result = subprocess.run([ffmpeg("ffprobe"), "-v", "error", "-f", "h264", "-count_frames",
                             "-show_entries", "stream=width,height,nb_read_frames:packet=flags", "-of", "json",
                             "pipe:0"], input=data, capture_output=True, timeout=60, check=True)
    report = json.loads(result.stdout)
    return {"stream": report["streams"][0], "packets": report.get("packets", []), "errors": result.stderr.decode()}
