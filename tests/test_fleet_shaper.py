"""bench/countproxy.py --serve, the fleet bench's links (issue 27): one shaper per robot
that the laptop reaches over TCP, shaping every connection as the per-connection proxy
does (tests/test_bench_smoke.py): intact, never faster than the link, counted, and its
outages (blackhole, cut)."""

from __future__ import annotations

import hashlib
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parent.parent / "bench"
sys.path.insert(0, str(BENCH))

from countproxy import LINKS, Counter, set_link_state  # noqa: E402 - bench/ on the path first


class _Echo:
    """A TCP server on 127.0.0.1 that sends back whatever it receives, any number of clients."""

    def __init__(self) -> None:
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.port = self.srv.getsockname()[1]
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.srv.accept()
            except OSError:
                return
            threading.Thread(target=self._one, args=(conn,), daemon=True).start()

    @staticmethod
    def _one(conn: socket.socket) -> None:
        with conn:
            while data := conn.recv(1 << 16):
                conn.sendall(data)


@pytest.fixture
def served(tmp_path: Path, request: pytest.FixtureRequest):
    echo = _Echo()
    wire = tmp_path / "wire"

    def start(link: str) -> int:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-S",
                str(BENCH / "countproxy.py"),
                "--serve",
                "127.0.0.1",
                str(echo.port),
                str(wire),
                link,
            ],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            text=True,
        )
        procs.append(proc)
        assert proc.stdout is not None
        return int(proc.stdout.readline())

    procs: list[subprocess.Popen[str]] = []
    yield start, wire, procs
    for proc in procs:
        proc.terminate()
        assert proc.wait(5) is not None
    echo.srv.close()


def _exactly(sock: socket.socket, n: int) -> bytes:
    out = b""
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        assert chunk, "the link closed early"
        out += chunk
    return out


@pytest.mark.parametrize("name", ["weak", "loopback"])
def test_a_served_link_delivers_intact_and_never_faster_than_the_link(served, name):
    start, wire, procs = served
    port = start(name)
    link = LINKS[name]
    for _ in range(2):  # one shaper, several connections, each shaped and counted
        with socket.create_connection(("127.0.0.1", port)) as s:
            s.sendall(b"?")
            assert _exactly(s, 1) == b"?"
            t0 = time.monotonic()
            for i in range(3):
                s.sendall(bytes([65 + i]))
                assert _exactly(s, 1) == bytes([65 + i])
            ping_pong = (time.monotonic() - t0) / 3
            data = hashlib.shake_256(b"seed").digest(1 << 19)
            t0 = time.monotonic()
            writer = threading.Thread(target=s.sendall, args=(data,))
            writer.start()
            back = _exactly(s, len(data))
            bulk = time.monotonic() - t0
            writer.join()
            assert back == data
        if link is not None:
            assert ping_pong >= 2 * link.delay
            assert bulk >= len(data) / link.rate + 2 * link.delay
    totals = Counter(wire).settle(live=0, timeout=5)
    assert len(totals.per_conn) == 2
    assert (totals.up, totals.down) == (2 * (4 + len(data)), 2 * (4 + len(data)))
    assert procs[0].poll() is None  # still serving


def test_a_served_links_outages_hold_then_deliver_and_cuts_end_connections(served):
    start, wire, procs = served
    port = start("wifi")
    s = socket.create_connection(("127.0.0.1", port))
    s.sendall(b"a")
    assert _exactly(s, 1) == b"a"
    set_link_state(wire, "blackhole")
    time.sleep(0.2)
    s.sendall(b"b")
    s.settimeout(0.5)
    with pytest.raises(TimeoutError):
        s.recv(1)  # held while the link is a blackhole
    s.settimeout(5)
    set_link_state(wire, "up")
    assert _exactly(s, 1) == b"b"
    set_link_state(wire, "cut")
    assert s.recv(1) == b""  # the open connection ended
    s.close()
    with socket.create_connection(("127.0.0.1", port)) as new:
        new.settimeout(5)
        assert new.recv(1) == b""  # a new one is closed at once while cut
    set_link_state(wire, "up")
    with socket.create_connection(("127.0.0.1", port)) as again:
        again.sendall(b"c")
        assert _exactly(again, 1) == b"c"
