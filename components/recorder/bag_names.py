"""Where a recorder's bags go: ``storage.uri`` for the first, then names that never overwrite a bag.

Two ways to start a bag after a stop, each naming it as its model does:

* ``~/start_recording`` (this project's, std_srvs/Trigger): ``<uri>_1``, ``<uri>_2``, ... skipping existing names;
* ``~/record`` (rosbag2_interfaces/Record, rosbag2 Jazzy 0.26.10): the requested uri, or the previous bag's when
  the request's is empty; when that exists, rosbag2's ``(1)``, ``(2)``, ... appended (``RecorderImpl::record``).
  Like rosbag2's ``storage_options.uri``, the name used becomes the one an empty uri means next time.

Every name, the default ``rosbag2_<time>`` one included, goes through the node's ``resolve_path``: with a bag root
each must lie inside it (a ``<uri>_1`` symlink planted there after the first bag is refused too).
"""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Callable


class BagNames:
    """The names of one recorder's bags (see module docstring)."""

    def __init__(self, uri: str, resolve: Callable[[str], Path]) -> None:
        self.base = uri or time.strftime("rosbag2_%Y_%m_%d-%H_%M_%S")
        self._resolve = resolve
        self._count = 0  # bags named so far: the first is the base itself

    def next(self) -> Path:
        """The first bag's path (the base, even if it exists: the writer refuses it then); after that
        ``<base>_<n>``, the first n not taken."""
        while True:
            name = self.base if self._count == 0 else f"{self.base}_{self._count}"
            self._count += 1
            path = self._resolve(name)
            if self._count == 1 or not os.path.lexists(path):
                return path

    def record(self, uri: str) -> Path:
        """``~/record``: ``uri`` or, empty, the previous bag's; ``(n)`` appended while the name is taken."""
        name = (uri or self.base).rstrip("/") or "/"
        path = self._resolve(name)
        attempt = 0
        while os.path.lexists(path):
            attempt += 1
            path = self._resolve(f"{name}({attempt})")
        self.base = name if attempt == 0 else f"{name}({attempt})"
        self._count = 1  # a later ~/start_recording goes on from this base: <base>_1, ...
        return path
