"""A TCP proxy on 127.0.0.1 that injects link faults between laptop and robot.

Point the client at ``proxy.port`` instead of the robot's, then change the
link while it is in use:

- ``pass_through()``: forward (the default); ``throttle()`` still applies.
- ``blackhole()``: stop forwarding without closing anything, as a dead Wi-Fi
  link does: data waits in the proxy and the kernel buffers, and flows again
  after ``pass_through()``.
- ``cut()``: reset every connection and refuse new ones (the port is closed);
  ``pass_through()`` listens on the same port again.
- ``throttle(bytes_per_second=..., latency=...)``: limit each direction's
  rate and delay every chunk by a one-way latency.

One thread runs a selector loop over non-blocking sockets, so a fault takes
effect between two chunks and closing never races a blocked call. It only
listens on 127.0.0.1, forwards only to a loopback address, and holds at most
``max_connections`` connections and ``_MAX_QUEUED`` bytes per direction.
"""

from __future__ import annotations

import collections
import enum
import ipaddress
import selectors
import socket
import struct
import threading
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from typing_extensions import Self

__all__ = ["FaultProxy", "Mode"]

_LOOPBACK = "127.0.0.1"
_CHUNK = 64 * 1024
_MAX_QUEUED = 256 * 1024
_TICK = 0.05


class Mode(enum.Enum):
    PASS = "pass"
    BLACKHOLE = "blackhole"
    CUT = "cut"


def _reset(sock: socket.socket) -> None:
    """Close with RST rather than FIN, as a peer that lost its state would."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    except OSError:
        pass
    sock.close()


class _Pipe:
    """One direction of one connection: bytes read from src, waiting for dst."""

    def __init__(self, src: socket.socket, dst: socket.socket, *, upstream: bool) -> None:
        self.src = src
        self.dst = dst
        self.upstream = upstream
        self.blocked = False
        """dst's send buffer was full: wait until it is writable."""
        self.queue: collections.deque[tuple[float, bytes]] = collections.deque()
        self.queued = 0
        self.src_eof = False
        self.dst_shut = False
        self.tokens = 0.0
        self.tokens_at = time.monotonic()

    def done(self) -> bool:
        return self.src_eof and not self.queue


class _Conn:
    def __init__(self, client: socket.socket, server: socket.socket) -> None:
        self.client = client
        self.server = server
        self.up = _Pipe(client, server, upstream=True)
        self.down = _Pipe(server, client, upstream=False)


class FaultProxy:
    """Forward 127.0.0.1:``port`` to a loopback target, with faults on demand."""

    def __init__(self, target_host: str, target_port: int, *, max_connections: int = 32) -> None:
        if not ipaddress.ip_address(socket.gethostbyname(target_host)).is_loopback:
            raise ValueError(f"FaultProxy only forwards to loopback, not {target_host}")
        self.target = (target_host, target_port)
        self.max_connections = max_connections
        self.host = _LOOPBACK
        self.port = 0
        self.bytes_up = 0
        """Bytes forwarded client → target."""
        self.bytes_down = 0
        """Bytes forwarded target → client."""
        self.accepted = 0
        self._mode = Mode.PASS
        self._rate: float | None = None
        self._latency = 0.0
        self._lock = threading.Lock()
        self._requested = 0
        self._applied = 0
        self._stopping = False
        self._conns: list[_Conn] = []
        self._listener: socket.socket | None = None
        self._selector = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._thread: threading.Thread | None = None

    # -- control (any thread) ------------------------------------------------

    @property
    def mode(self) -> Mode:
        return self._mode

    @property
    def active_connections(self) -> int:
        return len(self._conns)

    def start(self) -> Self:
        self._listen()
        self._thread = threading.Thread(target=self._run, name="FaultProxy", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        with self._lock:
            self._stopping = True
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def pass_through(self) -> None:
        self._set(mode=Mode.PASS)

    def blackhole(self) -> None:
        self._set(mode=Mode.BLACKHOLE)

    def cut(self) -> None:
        self._set(mode=Mode.CUT)

    def throttle(self, *, bytes_per_second: float | None = None, latency: float = 0.0) -> None:
        """Limit each direction to ``bytes_per_second`` and add one-way ``latency`` (s).

        ``throttle()`` with no arguments removes both.
        """
        if bytes_per_second is not None and bytes_per_second <= 0:
            raise ValueError("bytes_per_second must be positive")
        if latency < 0:
            raise ValueError("latency must not be negative")
        with self._lock:
            self._rate = bytes_per_second
            self._latency = latency
        self._await_applied()

    def _set(self, *, mode: Mode) -> None:
        with self._lock:
            self._mode = mode
        self._await_applied()

    def _await_applied(self) -> None:
        """Return once the loop runs with the new setting, so a test can rely on it."""
        with self._lock:
            self._requested += 1
            wanted = self._requested
        self._wake()
        deadline = time.monotonic() + 5
        while self._thread is not None and self._applied < wanted:
            if time.monotonic() > deadline:
                raise RuntimeError("FaultProxy loop did not apply the change")
            time.sleep(0.002)

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass

    # -- loop (proxy thread) ---------------------------------------------------

    def _listen(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((_LOOPBACK, self.port))
        sock.listen(16)
        sock.setblocking(False)
        self.port = sock.getsockname()[1]
        self._listener = sock

    def _run(self) -> None:
        self._wake_r.setblocking(False)
        try:
            while True:
                with self._lock:
                    stopping = self._stopping
                    mode, rate, latency = self._mode, self._rate, self._latency
                    requested = self._requested
                if stopping:
                    return
                self._apply_mode(mode)
                self._applied = requested
                timeout = self._pump(mode, rate, latency)
                self._poll(timeout, mode, latency)
        finally:
            self._shutdown()

    def _apply_mode(self, mode: Mode) -> None:
        if mode is Mode.CUT:
            with self._lock:
                conns, self._conns = self._conns, []
                listener, self._listener = self._listener, None
            for conn in conns:
                self._close(conn, reset=True)
            if listener is not None:
                self._forget(listener)
                listener.close()
        elif self._listener is None:
            self._listen()

    def _poll(self, timeout: float, mode: Mode, latency: float) -> None:
        interest: dict[socket.socket, int] = {self._wake_r: selectors.EVENT_READ}
        if self._listener is not None:
            interest[self._listener] = selectors.EVENT_READ
        if mode is Mode.PASS:
            for conn in self._conns:
                for pipe in (conn.up, conn.down):
                    if not pipe.src_eof and pipe.queued < _MAX_QUEUED:
                        interest[pipe.src] = interest.get(pipe.src, 0) | selectors.EVENT_READ
                    if pipe.blocked:
                        interest[pipe.dst] = interest.get(pipe.dst, 0) | selectors.EVENT_WRITE
        sel = self._selector
        for key in list(sel.get_map().values()):
            if key.fileobj not in interest:
                sel.unregister(key.fileobj)
        for sock, events in interest.items():
            try:
                key = sel.get_key(sock)
            except KeyError:
                sel.register(sock, events)
                continue
            if key.events != events:
                sel.modify(sock, events)
        for key, events in sel.select(timeout):
            ready = key.fileobj
            if ready is self._wake_r:
                try:
                    while self._wake_r.recv(4096):
                        pass
                except OSError:
                    pass
            elif ready is self._listener:
                self._accept()
            elif isinstance(ready, socket.socket):
                if events & selectors.EVENT_WRITE:
                    self._writable(ready)
                if events & selectors.EVENT_READ:
                    self._read(ready, latency)

    def _accept(self) -> None:
        assert self._listener is not None
        try:
            client, _ = self._listener.accept()
        except OSError:
            return
        self.accepted += 1
        if len(self._conns) >= self.max_connections:
            _reset(client)
            return
        try:
            server = socket.create_connection(self.target, timeout=5)
        except OSError:
            _reset(client)
            return
        for sock in (client, server):
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._lock:
            self._conns.append(_Conn(client, server))

    def _writable(self, sock: socket.socket) -> None:
        for conn in self._conns:
            for pipe in (conn.up, conn.down):
                if pipe.dst is sock:
                    pipe.blocked = False

    def _read(self, sock: socket.socket, latency: float) -> None:
        for conn in self._conns:
            for pipe in (conn.up, conn.down):
                if pipe.src is sock:
                    try:
                        data = sock.recv(_CHUNK)
                    except BlockingIOError:
                        return
                    except OSError:
                        self._drop(conn)
                        return
                    if data:
                        pipe.queue.append((time.monotonic() + latency, data))
                        pipe.queued += len(data)
                    else:
                        pipe.src_eof = True
                    return

    def _pump(self, mode: Mode, rate: float | None, latency: float) -> float:
        """Send what is due; return how long the loop may sleep."""
        timeout = _TICK
        if mode is not Mode.PASS:
            return timeout
        now = time.monotonic()
        for conn in list(self._conns):
            for pipe in (conn.up, conn.down):
                try:
                    wait = self._send_due(pipe, now, rate)
                except OSError:
                    self._drop(conn)
                    break
                timeout = min(timeout, wait)
                if pipe.done() and not pipe.dst_shut:
                    pipe.dst_shut = True
                    try:
                        pipe.dst.shutdown(socket.SHUT_WR)
                    except OSError:
                        pass
            else:
                if conn.up.done() and conn.down.done():
                    self._drop(conn, reset=False)
        return max(timeout, 0.0)

    def _send_due(self, pipe: _Pipe, now: float, rate: float | None) -> float:
        while pipe.queue:
            due, data = pipe.queue[0]
            if due > now:
                return due - now
            budget = len(data)
            if rate is not None:
                # Token bucket holding at most a tick's worth, so bursts stay small.
                pipe.tokens = min(
                    pipe.tokens + (now - pipe.tokens_at) * rate, max(rate * _TICK, 1.0)
                )
                pipe.tokens_at = now
                if pipe.tokens < 1.0:
                    return (1.0 - pipe.tokens) / rate
                budget = min(budget, int(pipe.tokens))
            if pipe.blocked:
                return _TICK
            try:
                sent = pipe.dst.send(data[:budget])
            except BlockingIOError:
                sent = 0
            if rate is not None:
                pipe.tokens -= sent
            if pipe.upstream:
                self.bytes_up += sent
            else:
                self.bytes_down += sent
            pipe.queued -= sent
            if sent == len(data):
                pipe.queue.popleft()
                continue
            pipe.queue[0] = (due, data[sent:])
            if sent < budget:
                pipe.blocked = True  # the kernel buffer is full
                return _TICK
        pipe.tokens_at = now
        return _TICK

    def _forget(self, sock: socket.socket) -> None:
        # Before close: epoll would otherwise keep a key for a reused fd number.
        try:
            self._selector.unregister(sock)
        except (KeyError, ValueError):
            pass

    def _close(self, conn: _Conn, *, reset: bool) -> None:
        for sock in (conn.client, conn.server):
            self._forget(sock)
            if reset:
                _reset(sock)
            else:
                sock.close()

    def _drop(self, conn: _Conn, *, reset: bool = True) -> None:
        with self._lock:
            if conn in self._conns:
                self._conns.remove(conn)
        self._close(conn, reset=reset)

    def _shutdown(self) -> None:
        with self._lock:
            conns, self._conns = self._conns, []
            listener, self._listener = self._listener, None
        for conn in conns:
            self._close(conn, reset=True)
        if listener is not None:
            self._forget(listener)
            listener.close()
        self._selector.close()
        self._wake_r.close()
        self._wake_w.close()
