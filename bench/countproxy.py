#!/usr/bin/env python3
"""Count the bytes of SSH connections: ``countproxy.py HOST PORT COUNTDIR``.

Used as the ssh ``ProxyCommand`` of both OpenSSH (rsync's transport) and
paramiko (fetchsync's), so both tools' bytes on the wire are counted the same
way: the encrypted SSH stream, key exchange and authentication included.

It connects to HOST:PORT and copies stdin to the socket and the socket to
stdout. Each connection keeps its counters in ``COUNTDIR/<pid>.count``: three
little-endian u64, *up* (client to server), *down* (server to client) and
*done* (1 once the proxy has stopped), updated in place (mmap) as bytes pass.

Counters are live rather than written at exit because a connection may outlive
the command that opened it: fetchsync leaves a connection master holding its
SSH connection between calls (``fetchsync/agent/mux.py``). The bytes one push
costs are then the growth of the sum over all connections while it ran,
counted until the counters are quiet (:func:`Counter.settle`), so a master's
handshake, its re-warmed endpoint and channel closes count to the push that
caused them.

The proxy stops on EOF from the server, EOF from the client once the server
closes, or the SIGHUP / SIGTERM its client sends when it closes the connection
(OpenSSH sends SIGHUP, paramiko SIGTERM).
"""

from __future__ import annotations

import mmap
import os
import select
import signal
import socket
import struct
import sys
import time
from pathlib import Path

__all__ = ["Counter", "Totals"]

_CHUNK = 256 * 1024
_REC = struct.Struct("<QQQ")


class _Stop(Exception):
    pass


def _on_signal(signum: int, frame: object) -> None:
    raise _Stop()


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def proxy(host: str, port: int, countdir: str) -> int:
    for sig in (signal.SIGHUP, signal.SIGTERM, signal.SIGINT, signal.SIGPIPE):
        signal.signal(sig, _on_signal)
    os.makedirs(countdir, exist_ok=True)
    path = os.path.join(countdir, f"{os.getpid()}.count")
    fd = os.open(path + ".tmp", os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
    os.ftruncate(fd, _REC.size)
    counts = mmap.mmap(fd, _REC.size)
    os.close(fd)
    os.replace(path + ".tmp", path)  # readers never see a short file
    up = down = 0
    try:
        sock = socket.create_connection((host, port))
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        stdin, stdout = sys.stdin.fileno(), sys.stdout.fileno()
        reading = {stdin, sock.fileno()}
        while reading:
            ready, _, _ = select.select(list(reading), [], [])
            if stdin in ready:
                data = os.read(stdin, _CHUNK)
                if data:
                    up += len(data)
                    _REC.pack_into(counts, 0, up, down, 0)
                    sock.sendall(data)
                else:
                    reading.discard(stdin)
                    sock.shutdown(socket.SHUT_WR)
            if sock.fileno() in ready:
                data = sock.recv(_CHUNK)
                if data:
                    down += len(data)
                    _REC.pack_into(counts, 0, up, down, 0)
                    _write_all(stdout, data)
                else:
                    break  # the server is done: nothing more can be said to it
    except (_Stop, OSError):
        pass
    finally:
        _REC.pack_into(counts, 0, up, down, 1)
        counts.close()
    return 0


class Totals:
    """Bytes over all connections in a count directory at one moment."""

    def __init__(self, per_conn: dict[str, tuple[int, int, bool]]) -> None:
        self.per_conn = per_conn

    @property
    def up(self) -> int:
        return sum(u for u, _d, _e in self.per_conn.values())

    @property
    def down(self) -> int:
        return sum(d for _u, d, _e in self.per_conn.values())

    @property
    def live(self) -> int:
        return sum(not e for _u, _d, e in self.per_conn.values())

    def key(self) -> tuple[int, int, int, int]:
        return (len(self.per_conn), self.up, self.down, self.live)


class Counter:
    """Reads the counters the proxies of one count directory keep."""

    def __init__(self, countdir: Path) -> None:
        self.dir = Path(countdir)
        self.dir.mkdir(parents=True, exist_ok=True)

    def read(self) -> Totals:
        out: dict[str, tuple[int, int, bool]] = {}
        for p in self.dir.glob("*.count"):
            try:
                up, down, done = _REC.unpack(p.read_bytes()[: _REC.size])
            except (OSError, struct.error):
                continue
            out[p.stem] = (up, down, bool(done))
        return Totals(out)

    def settle(
        self, *, quiet: float = 0.3, timeout: float = 10.0, live: int | None = None
    ) -> Totals:
        """The totals once nothing has moved for ``quiet`` seconds.

        With ``live`` given, also wait until that many connections are still
        open (0: every proxy has stopped).
        """
        deadline = time.monotonic() + timeout
        last = self.read()
        since = time.monotonic()
        while True:
            time.sleep(0.02)
            now = self.read()
            if now.key() != last.key():
                last, since = now, time.monotonic()
            elif time.monotonic() - since >= quiet and (live is None or now.live <= live):
                return now
            if time.monotonic() > deadline:
                if live is not None and now.live > live:
                    raise TimeoutError(
                        f"{self.dir}: {now.live} connection(s) still open, expected at most {live}"
                    )
                return now


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit("usage: countproxy.py HOST PORT COUNTDIR")
    sys.exit(proxy(sys.argv[1], int(sys.argv[2]), sys.argv[3]))
