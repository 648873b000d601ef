"""A compressed topic's frame account, kept in a bag's ``metadata.yaml`` ``custom_data``.

A topic recorded compressed (an ImageEncoder of the recorder's container publishes it) loses frames before the
recorder sees them: the encoder was behind, could not take a frame, was stopped, or a rate limit thinned its
input. The recorder writes, per such topic, how the raw frames the encoder received during the bag ended:
``custom_data`` key ``recorder.frames.<topic>``, value ``received=N written=N <reason>=N ...`` (space-separated
``name=count`` pairs; ``received`` equals ``written`` plus every other count). ``bag info`` prints it, so a
reader of the bag alone can tell that frames are missing, and why.
"""
from __future__ import annotations

from collections.abc import Mapping

PREFIX = "recorder.frames."


def key(topic: str) -> str:
    """The ``custom_data`` key of ``topic``'s account."""
    return PREFIX + topic


def encode(counts: Mapping[str, int]) -> str:
    return " ".join(f"{name}={count}" for name, count in counts.items())


def accounts(custom_data: Mapping[str, str]) -> dict[str, dict[str, int]]:
    """Every frame account in a bag's ``custom_data``, by topic; a malformed value is left out."""
    found = {}
    for name, value in custom_data.items():
        if not name.startswith(PREFIX):
            continue
        try:
            found[name[len(PREFIX):]] = {part.partition("=")[0]: int(part.partition("=")[2])
                                         for part in value.split()}
        except ValueError:
            continue
    return found
