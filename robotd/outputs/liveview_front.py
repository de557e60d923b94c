"""The live view's listening socket: a TCP front for the Foxglove SDK's WebSocket server that also
lets in clients offering only the ``foxglove.websocket.v1`` subprotocol (issue 27, item 5).

The SDK's server (foxglove-sdk 0.30: ``rust/foxglove/src/websocket/handshake.rs``) accepts only
``foxglove.sdk.v1`` and answers anything else with HTTP 400. Foxglove renamed the subprotocol when
the SDK replaced ws-protocol, but the messages are the same ones (Foxglove's stated position; the
Lichtblick and Flora viewers added the new name alongside the old without any other change), and
older Foxglove Studio, Lichtblick before it added the name, and the ws-protocol clients offer only
the old name. So the front listens on ``liveview.host:port``, forwards every connection to the
SDK's server on a loopback port of its own, and in the HTTP upgrade alone rewrites an offer of
``foxglove.websocket.v1`` (without ``foxglove.sdk.v1``) to the new name, and the server's answer
back to the name the client asked for. Everything after the handshake (the WebSocket frames) is
passed through byte for byte; a client offering ``foxglove.sdk.v1`` is not touched at all.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading

logger = logging.getLogger(__name__)

SDK_SUBPROTOCOL = b"foxglove.sdk.v1"
LEGACY_SUBPROTOCOL = b"foxglove.websocket.v1"
_HEADER = b"sec-websocket-protocol"
MAX_HEAD_BYTES = 16384  # an HTTP upgrade request or response is a few hundred bytes
HANDSHAKE_TIMEOUT_S = 10.0
CHUNK_BYTES = 1 << 16


def _split_head(head: bytes) -> list[bytes]:
    """The lines of an HTTP head (without the blank line that ends it)."""
    return head[: -len(b"\r\n\r\n")].split(b"\r\n")


def _join_head(lines: list[bytes]) -> bytes:
    return b"\r\n".join(lines) + b"\r\n\r\n"


def _protocol_lines(lines: list[bytes]) -> list[int]:
    return [i for i, ln in enumerate(lines) if i and ln.partition(b":")[0].strip().lower() == _HEADER]


def rewrite_request(head: bytes) -> tuple[bytes, bool]:
    """A client's upgrade request head (ending in the blank line) -> (the head to forward, whether
    the client offered only the old subprotocol name, which is then replaced by the new one)."""
    lines = _split_head(head)
    idx = _protocol_lines(lines)
    offered = {v.strip() for i in idx for v in lines[i].partition(b":")[2].split(b",")}
    if SDK_SUBPROTOCOL in offered or LEGACY_SUBPROTOCOL not in offered:
        return head, False
    lines[idx[0]] = b"Sec-WebSocket-Protocol: " + SDK_SUBPROTOCOL
    for i in reversed(idx[1:]):
        del lines[i]
    return _join_head(lines), True


def rewrite_response(head: bytes) -> bytes:
    """The server's answer to a rewritten request, with the subprotocol the client asked for."""
    lines = _split_head(head)
    for i in _protocol_lines(lines):
        if lines[i].partition(b":")[2].strip() == SDK_SUBPROTOCOL:
            lines[i] = b"Sec-WebSocket-Protocol: " + LEGACY_SUBPROTOCOL
    return _join_head(lines)


def _read_head(sock: socket.socket) -> tuple[bytes, bytes]:
    """Read up to the end of an HTTP head: (head with its blank line, the bytes after it). Raises
    ConnectionError on end of stream or a head longer than MAX_HEAD_BYTES."""
    buf = b""
    while True:
        end = buf.find(b"\r\n\r\n")
        if end >= 0:
            return buf[: end + 4], buf[end + 4 :]
        if len(buf) > MAX_HEAD_BYTES:
            raise ConnectionError(f"HTTP head longer than {MAX_HEAD_BYTES} bytes")
        data = sock.recv(4096)
        if not data:
            raise ConnectionError("closed during the handshake")
        buf += data


class SubprotocolFront:
    """Listens on (host, port) and relays each connection to the SDK's server on
    127.0.0.1:``backend_port`` (see the module docstring). Raises OSError when it cannot listen."""

    def __init__(self, host: str, port: int, backend_port: int) -> None:
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._listener = socket.create_server((host, port), family=family)
        self._listener.settimeout(0.5)  # the accept loop looks at the stop flag this often
        self.port = int(self._listener.getsockname()[1])
        self._backend = ("127.0.0.1", int(backend_port))
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self._sockets: set[socket.socket] = set()
        self.counts = {"connections": 0, "renamed": 0, "refused": 0}
        self._thread = threading.Thread(target=self._accept_loop, name="liveview-front", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._closed.set()
        with contextlib.suppress(OSError):
            self._listener.shutdown(socket.SHUT_RDWR)  # wakes the accept loop at once (Linux)
        self._listener.close()
        with self._lock:
            socks, self._sockets = list(self._sockets), set()
        for s in socks:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()
        self._thread.join(timeout=2.0)

    def _track(self, *socks: socket.socket) -> bool:
        with self._lock:
            if self._closed.is_set():
                return False
            self._sockets.update(socks)
            return True

    def _forget(self, *socks: socket.socket) -> None:
        with self._lock:
            self._sockets.difference_update(socks)
        for s in socks:
            s.close()

    def _accept_loop(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return  # closed
            if not self._track(client):
                client.close()
                return
            threading.Thread(target=self._serve, args=(client,), name="liveview-conn", daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        backend: socket.socket | None = None
        try:
            client.settimeout(HANDSHAKE_TIMEOUT_S)
            head, rest = _read_head(client)
            head, renamed = rewrite_request(head)
            backend = socket.create_connection(self._backend, timeout=HANDSHAKE_TIMEOUT_S)
            if not self._track(backend):
                raise ConnectionError("closing")
            backend.sendall(head + rest)
            answer, rest = _read_head(backend)
            if renamed:
                answer = rewrite_response(answer)
            client.sendall(answer + rest)
            refused = not answer.startswith(b"HTTP/1.1 101")
            with self._lock:
                self.counts["connections"] += 1
                self.counts["renamed"] += renamed
                self.counts["refused"] += refused
            if refused:
                return
            for s in (client, backend):
                s.settimeout(None)
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            up = threading.Thread(target=self._pump, args=(client, backend), name="liveview-up", daemon=True)
            up.start()
            self._pump(backend, client)
            up.join()
        except (OSError, ConnectionError) as exc:
            if not self._closed.is_set():
                logger.debug("live view connection ended: %s", exc)
        finally:
            self._forget(client, *([backend] if backend is not None else []))

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        """Copy src to dst until src ends (then end dst's sending side) or either fails (then
        shut both, which ends the other direction too)."""
        try:
            while data := src.recv(CHUNK_BYTES):
                dst.sendall(data)
            dst.shutdown(socket.SHUT_WR)
        except OSError:
            for s in (src, dst):
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
