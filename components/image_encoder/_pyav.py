"""PyAV, imported at its first use.

Importing PyAV loads FFmpeg's libraries: about 50 ms of CPU. The recorder, the player and the Foxglove bridge import
the codec modules for their parameters and checks, and most of them never encode or decode a frame, so the
modules here call :func:`av` where they need it instead of importing it at the top.
"""
from __future__ import annotations

import functools
import importlib
from types import ModuleType


@functools.cache
def av() -> ModuleType:
    """The ``av`` module, imported once."""
    return importlib.import_module("av")
