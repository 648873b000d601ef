"""A full-screen text view redrawn in place, as ``top`` draws one, with ``q`` read from the keyboard.

Plain ANSI sequences (the terminal's alternate screen, cursor home, erase to end of line and of screen), no
curses: each frame is the given lines cut to the terminal's current size, so a resized window is simply drawn
at its new size at the next frame. The keyboard is read unbuffered and without echo (cbreak: Ctrl-C still
interrupts). Leaving, by ``q``, Ctrl-C or an error, restores the terminal and the screen it showed before.
"""
from __future__ import annotations

import os
import select
import shutil
import sys
import termios
import tty
from collections.abc import Sequence
from typing import Any, TextIO

ENTER = "\033[?1049h\033[?25l"   # alternate screen, cursor hidden
LEAVE = "\033[?25h\033[?1049l"   # cursor shown, back to the normal screen
HOME, ERASE_LINE, ERASE_BELOW = "\033[H", "\033[K", "\033[J"
QUIT_KEYS = frozenset("qQ")


class LiveScreen:
    """A context manager: the alternate screen and a cbreak keyboard while inside, restored on the way out."""

    def __init__(self, out: TextIO = sys.stdout, keys: TextIO = sys.stdin) -> None:
        self._out = out
        self._keys_fd = keys.fileno() if keys.isatty() else None
        self._saved: list[Any] | None = None

    def __enter__(self) -> "LiveScreen":
        if self._keys_fd is not None:
            self._saved = termios.tcgetattr(self._keys_fd)
            tty.setcbreak(self._keys_fd)
        self._out.write(ENTER)
        self._out.flush()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._out.write(LEAVE)
        self._out.flush()
        if self._saved is not None:
            termios.tcsetattr(self._keys_fd, termios.TCSADRAIN, self._saved)

    def draw(self, lines: Sequence[str]) -> None:
        """Replace the screen's content with ``lines``, each cut to the width, as many as fit the height."""
        size = shutil.get_terminal_size()
        shown = [line[:size.columns] for line in lines[:max(1, size.lines - 1)]]
        self._out.write(HOME + "".join(line + ERASE_LINE + "\n" for line in shown) + ERASE_BELOW)
        self._out.flush()

    def quit_pressed(self) -> bool:
        """Whether ``q`` was typed since the last call (never waits)."""
        if self._keys_fd is None:
            return False
        typed = ""
        while select.select([self._keys_fd], [], [], 0)[0]:
            chunk = os.read(self._keys_fd, 64)
            if not chunk:
                break
            typed += chunk.decode(errors="replace")
        return bool(QUIT_KEYS.intersection(typed))
