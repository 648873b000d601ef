"""The bridge's listening socket: clients that offer either name of the Foxglove WebSocket protocol get in.

The Foxglove SDK's server (foxglove-sdk 0.30, the newest release; ``rust/foxglove/src/websocket/handshake.rs``)
accepts only the WebSocket subprotocol ``foxglove.sdk.v1`` and answers ``HTTP 400 Missing expected
sec-websocket-protocol header`` to a client that offers ``foxglove.websocket.v1``: the older name of the same
protocol, and the only one that Foxglove's published client ``@foxglove/ws-protocol``, Lichtblick and Foxglove
before the SDK offer. The SDK has no option for the name.

So the SDK's server listens on an ephemeral loopback port, and :class:`SubprotocolProxy` listens where the bridge
was asked to (``address``, ``port``). For each connection it reads the HTTP upgrade request only; where the
request offers ``foxglove.websocket.v1`` and not ``foxglove.sdk.v1``, it names ``foxglove.sdk.v1`` instead, and
names ``foxglove.websocket.v1`` again in the server's ``101`` answer (a client checks that the server chose a
name it offered). Every other byte, in both directions, is passed on untouched: the messages are the SDK's.

The bytes are moved by the kernel (``splice(2)`` through a pipe, in blocking calls that release the GIL): a
camera frame is never copied into Python, so the extra hop costs little CPU (docs/foxglove.md has the
measurement). Flow control is the sockets': a client that stops reading fills its socket, then the pipe, then the
SDK's socket, and the SDK's per-client outbox drops its oldest messages, as without the proxy.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import selectors
import socket
import threading

#: The name the SDK's server accepts.
SDK_SUBPROTOCOL = "foxglove.sdk.v1"
#: The name of the same protocol that @foxglove/ws-protocol, Lichtblick and older Foxglove offer.
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
#: The largest HTTP request or response head read (a browser's upgrade request is well under 4 KiB).
MAX_HEAD = 16 * 1024
#: s a new connection has to send its whole upgrade request (and the server to answer it).
HANDSHAKE_TIMEOUT = 10.0
#: Bytes moved by one splice call; the pipe between the sockets is sized to this where the system allows.
CHUNK = 1 << 20

_HEADER_NAME = b"sec-websocket-protocol"


def _head_lines(head: bytes) -> list[bytes]:
    """The request or status line and the header lines of an HTTP head (which ends in an empty line)."""
    return head.removesuffix(b"\r\n\r\n").split(b"\r\n")


def _protocol_value(line: bytes) -> bytes | None:
    """The value of a ``Sec-WebSocket-Protocol`` header line (names are case-insensitive), else None."""
    name, colon, value = line.partition(b":")
    return value if colon and name.strip().lower() == _HEADER_NAME else None


def offered_subprotocols(head: bytes) -> list[str]:
    """The subprotocol names an HTTP upgrade request offers (in every ``Sec-WebSocket-Protocol`` header)."""
    values = [value for value in map(_protocol_value, _head_lines(head)) if value is not None]
    return [name.strip().decode("latin-1") for value in values for name in value.split(b",") if name.strip()]


def rename_subprotocol(head: bytes, name: str) -> bytes:
    """``head`` with its ``Sec-WebSocket-Protocol`` headers replaced by one that names only ``name``."""
    kept = [line for line in _head_lines(head) if _protocol_value(line) is None]
    return b"\r\n".join([*kept, b"Sec-WebSocket-Protocol: " + name.encode("latin-1")]) + b"\r\n\r\n"


def _read_head(sock: socket.socket) -> tuple[bytes, bytes]:
    """An HTTP head read from ``sock`` (up to its empty line), and the bytes that came after it in the same reads.

    Raises:
        ConnectionError: the peer closed first, or the head is larger than :data:`MAX_HEAD`.
        TimeoutError: not within the socket's timeout.
    """
    data = b""
    while b"\r\n\r\n" not in data:
        if len(data) > MAX_HEAD:
            raise ConnectionError(f"HTTP head larger than {MAX_HEAD} bytes")
        chunk = sock.recv(4096)
        if not chunk:
            raise ConnectionError("closed during the WebSocket handshake")
        data += chunk
    end = data.index(b"\r\n\r\n") + 4
    return data[:end], data[end:]


def _splice(source: socket.socket, destination: socket.socket) -> None:
    """Move every byte from ``source`` to ``destination`` in the kernel until ``source`` ends or either fails;
    then end ``destination``'s sending side so its peer sees the end too."""
    read_end, write_end = os.pipe()
    with contextlib.suppress(OSError):
        fcntl.fcntl(write_end, fcntl.F_SETPIPE_SZ, CHUNK)  # fewer calls per frame; the default (64 KiB) works too
    try:
        while True:
            pending = os.splice(source.fileno(), write_end, CHUNK)
            if pending == 0:
                break
            while pending:
                pending -= os.splice(read_end, destination.fileno(), pending)
    except OSError:
        pass  # a reset or a shutdown by stop(): the connection is over either way
    finally:
        os.close(read_end)
        os.close(write_end)
        with contextlib.suppress(OSError):
            destination.shutdown(socket.SHUT_WR)


class SubprotocolProxy:
    """Listens on ``host``:``port`` and passes each connection to the SDK's server at 127.0.0.1:``server_port``,
    renaming the legacy subprotocol in the handshake (module docstring).

    Raises:
        OSError: ``host``:``port`` cannot be bound.
    """

    def __init__(self, host: str, port: int, server_port: int, name: str) -> None:
        self._server_port = server_port
        self._listener = socket.create_server((host, port), family=socket.AF_INET6 if ":" in host else socket.AF_INET,
                                              backlog=64)
        self._wake_read, self._wake_write = socket.socketpair()
        self._lock = threading.Lock()
        self._connections: set[socket.socket] = set()
        self._threads: set[threading.Thread] = set()
        self._stopped = False
        self._name = name
        self._acceptor = threading.Thread(target=self._accept, name=f"{name}:accept", daemon=True)
        self._acceptor.start()

    @property
    def port(self) -> int:
        """The port listened on (the one chosen by the system when 0 was asked for)."""
        return int(self._listener.getsockname()[1])

    def _accept(self) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self._listener, selectors.EVENT_READ)
            selector.register(self._wake_read, selectors.EVENT_READ)
            while True:
                ready = {key.fileobj for key, _ in selector.select()}
                if self._wake_read in ready:
                    return
                with contextlib.suppress(OSError):  # a client that reset before it was accepted
                    client, _ = self._listener.accept()
                    self._start(client)

    def _start(self, client: socket.socket) -> None:
        """Serve ``client`` on a thread of its own, tracked until it ends; refused once stopped."""
        with self._lock:
            if self._stopped:
                client.close()
                return
            thread = threading.Thread(target=self._run, args=(client,), name=f"{self._name}:client", daemon=True)
            self._threads.add(thread)
            thread.start()

    def _run(self, client: socket.socket) -> None:
        try:
            self._serve(client)
        finally:
            with self._lock:
                self._threads.discard(threading.current_thread())

    def _serve(self, client: socket.socket) -> None:
        """One connection: the handshake (renamed where needed), then the bytes both ways until both ends close."""
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        for sock in (client, server):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._lock:
            if self._stopped:
                client.close()
                server.close()
                return
            self._connections.update((client, server))
        try:
            client.settimeout(HANDSHAKE_TIMEOUT)
            server.settimeout(HANDSHAKE_TIMEOUT)
            request, early = _read_head(client)
            offered = offered_subprotocols(request)
            legacy = LEGACY_SUBPROTOCOL in offered and SDK_SUBPROTOCOL not in offered
            server.connect(("127.0.0.1", self._server_port))
            server.sendall((rename_subprotocol(request, SDK_SUBPROTOCOL) if legacy else request) + early)
            if legacy:
                response, early = _read_head(server)
                if response.startswith(b"HTTP/1.1 101") and SDK_SUBPROTOCOL in offered_subprotocols(response):
                    response = rename_subprotocol(response, LEGACY_SUBPROTOCOL)
                client.sendall(response + early)
            client.settimeout(None)
            server.settimeout(None)
            upstream = threading.Thread(target=_splice, args=(client, server), name=f"{self._name}:upstream",
                                        daemon=True)
            upstream.start()
            _splice(server, client)
            upstream.join()
        except (OSError, ConnectionError):
            pass  # a client that left mid-handshake, or a server that stopped: nothing to pass on
        finally:
            with self._lock:
                self._connections.difference_update((client, server))
            client.close()
            server.close()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop listening, end every connection, and wait (at most ``timeout`` s) for the threads to end."""
        with self._lock:
            self._stopped = True
            connections, threads = list(self._connections), list(self._threads)
        self._wake_write.send(b"x")
        self._acceptor.join(timeout)
        for sock in connections:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
        for thread in threads:
            thread.join(timeout)
        self._listener.close()
        self._wake_read.close()
        self._wake_write.close()
