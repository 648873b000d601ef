"""An idempotent service request sent again until one reply arrives.

Why: Fast DDS drops a service reply when the server has not yet matched the client's reply reader (the
client's participant is brand new); the request was served, only the reply is lost, and nothing resends it.
Waiting a call timeout for such a reply made every fresh ``ipc-component`` pay about a second. An idempotent
request (ListNodes) is simply sent again instead: every 50 ms during the first second (the container matches a
new client's reply reader within ~0.1-0.4 s), then every 0.25 s, so a lost reply costs tens of milliseconds
while a server that is slow to answer is not flooded (and its request queue, keep-last, stays bounded). Every
request stays pending and the first reply wins.
"""
from __future__ import annotations

from typing import Any, Callable

from rclpy.client import Client
from rclpy.task import Future

FAST_RESEND = 0.05   # s, during the first FAST_PHASE s
FAST_PHASE = 1.0     # s
SLOW_RESEND = 0.25   # s, afterwards


class RepeatedCall:
    """Advanced by :meth:`step` from the caller's spin loop; :attr:`reply` is set once any request is answered."""

    def __init__(self, client: Client, make_request: Callable[[], Any]) -> None:
        self.client = client
        self._make_request = make_request
        self._pending: list[Future] = []
        self._next_send = 0.0
        self._first_send: float | None = None

    @property
    def sent(self) -> bool:
        return bool(self._pending)

    @property
    def reply(self) -> Any | None:
        for future in self._pending:
            if future.done() and future.exception() is None:
                return future.result()
        return None

    def step(self, now: float) -> None:
        """Send (again) if no reply came, the resend interval passed and the service is there."""
        if self.reply is not None or now < self._next_send or not self.client.service_is_ready():
            return
        self._pending.append(self.client.call_async(self._make_request()))
        if self._first_send is None:
            self._first_send = now
        self._next_send = now + (FAST_RESEND if now - self._first_send < FAST_PHASE else SLOW_RESEND)

    def close(self) -> None:
        """Forget the requests still unanswered (their late replies are then dropped by rclpy)."""
        for future in self._pending:
            if not future.done():
                future.cancel()
                self.client.remove_pending_request(future)
        self._pending.clear()
