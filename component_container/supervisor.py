"""What the container does when something goes wrong: the ``--on-component-error`` policy and the exit rule.

The invariant it keeps: if ListNodes lists a component, the component is running. A component callback that
raises is taken out of the list at once (by the manager) and handed here; the policy then either unloads just
that component (``unload``, the default: a recorder finalizes its bag, the others keep running) or ends the
container with status 1 (``exit``, what an rclcpp container does when a callback throws, so that launch can
respawn it). A container thread that dies (an executor, the manager's service thread) always ends the
container with status 1: it finalizes what it can rather than listing components nobody runs.

Teardown happens on the supervisor's own thread, never in the failing callback's thread, because unloading
drains the component's callbacks and would otherwise wait for itself.
"""
from __future__ import annotations

import queue
import threading
import time
import traceback
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

ERROR_POLICIES = ("unload", "exit")
#: Failed components stay visible on /diagnostics (as errors) until this many newer failures push them out.
FAILURES_KEPT = 16
#: How often the main thread looks up from a wait: the longest a signal's Python handler can be held back.
MAIN_THREAD_POLL = 0.1


@dataclass(frozen=True)
class ComponentFailure:
    """A component that raised: which, and why (first line of the exception)."""

    unique_id: int
    full_name: str
    reason: str


class ExitRequest:
    """The container's main thread waits on this; signals, the exit policy and dying threads set it.

    :meth:`request` runs in signal handlers, which Python runs in the main thread between two bytecodes, wherever
    that thread is: so the main thread must never hold, outside a handler, a lock that :meth:`request` takes. It
    polls (:meth:`wait_in_main_thread`) rather than waiting on a ``threading.Event``, whose internal lock it holds
    while it checks the flag: a signal handled at that moment blocked for good on that lock, and every later
    signal's handler then blocked on the first one's; the container ignored SIGTERM and SIGINT until SIGKILL.
    """

    def __init__(self) -> None:
        self._lock = threading.RLock()  # a second signal's handler may run inside the first one's request()
        self.status = 0
        self.reason = ""
        self.count = 0

    def request(self, status: int, reason: str) -> int:
        """Ask the container to exit (the worst status asked for wins); returns how many times it was asked."""
        with self._lock:
            self.status = max(self.status, status)
            self.reason = self.reason or reason
            self.count += 1
            return self.count

    def wait_in_main_thread(self, poll: float = MAIN_THREAD_POLL) -> None:
        """Return once an exit was requested, looking every ``poll`` s (a sleep, during which signals are
        handled at once)."""
        while not self.count:
            time.sleep(poll)

    @property
    def requested(self) -> bool:
        return self.count > 0


def join_in_main_thread(thread: threading.Thread, timeout: float, poll: float = MAIN_THREAD_POLL) -> None:
    """``thread.join(timeout)`` in slices of ``poll`` s, so that the main thread runs a signal's Python handler
    within ``poll`` s of the signal, wherever the signal landed.

    One long ``join`` is not enough: Python runs handlers in the main thread, which a signal wakes only if the
    kernel gives the signal to that thread, and only if it comes while the thread sleeps. A process-directed
    signal may go to any thread that does not block it (a Fast DDS thread, say), and one that comes while the
    main thread is between releasing the GIL and sleeping is spent before the sleep; either way the handler
    waited out the whole join (a second SIGTERM ignored for the 60 s of ``--shutdown-timeout``)."""
    deadline = time.monotonic() + timeout
    while thread.is_alive() and (remaining := deadline - time.monotonic()) > 0:
        thread.join(min(poll, remaining))


class Supervisor:
    """Applies the error policy to failed components and turns dead container threads into an exit."""

    def __init__(self, policy: str, logger: Any, unload: Callable[[int, str], Any], exit_request: ExitRequest):
        if policy not in ERROR_POLICIES:
            raise ValueError(f"Unknown error policy '{policy}': choose one of {', '.join(ERROR_POLICIES)}")
        self.policy = policy
        self._logger = logger
        self._unload = unload
        self._exit = exit_request
        self._failed: queue.Queue[ComponentFailure | None] = queue.Queue()
        self.failures: deque[ComponentFailure] = deque(maxlen=FAILURES_KEPT)
        self._thread = threading.Thread(target=self._run, name="supervisor", daemon=True)
        self._thread.start()

    def component_failed(self, failure: ComponentFailure, exc: BaseException) -> None:
        """A component's callback raised ``exc`` (the component is already out of ListNodes)."""
        details = "".join(traceback.format_exception(exc)).rstrip()
        self._logger.error(f"Component {failure.full_name} (id {failure.unique_id}) failed: {failure.reason}\n"
                           f"{details}")
        self.failures.append(failure)
        self._failed.put(failure)

    def thread_died(self, name: str, exc: BaseException) -> None:
        """A container thread ended with ``exc``: nothing runs what it ran, so the container must end."""
        details = "".join(traceback.format_exception(exc)).rstrip()
        self._logger.fatal(f"Container thread '{name}' died; shutting the container down\n{details}")
        self._exit.request(1, f"thread {name} died: {exc!r}")

    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self) -> None:
        self._failed.put(None)

    def _run(self) -> None:
        while (failure := self._failed.get()) is not None:
            try:
                if self.policy == "exit":
                    self._exit.request(1, f"component {failure.full_name} failed: {failure.reason}")
                else:
                    self._unload(failure.unique_id, failure.reason)
            except Exception as exc:  # noqa: BLE001 - the supervisor itself must not die quietly
                self.thread_died("supervisor", exc)
