"""FaultProxy forwards, blackholes, cuts and throttles a loopback link."""

from __future__ import annotations

import socket
import subprocess
import threading
import time
from typing import Iterator

import pytest
from faultproxy import FaultProxy, Mode
from sshd import SSHHome


class _EchoServer:
    """A loopback TCP echo server, one thread per connection."""

    def __init__(self) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._echo, args=(conn,), daemon=True).start()

    @staticmethod
    def _echo(conn: socket.socket) -> None:
        with conn:
            try:
                while data := conn.recv(65536):
                    conn.sendall(data)
            except OSError:
                pass

    def close(self) -> None:
        self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()
        self._thread.join(timeout=5)


@pytest.fixture
def proxy() -> Iterator[FaultProxy]:
    echo = _EchoServer()
    try:
        with FaultProxy("127.0.0.1", echo.port) as proxy:
            yield proxy
    finally:
        echo.close()


def _connect(proxy: FaultProxy) -> socket.socket:
    return socket.create_connection((proxy.host, proxy.port), timeout=5)


def _recv_exactly(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            break
        data += chunk
    return data


def test_pass_forwards_both_ways_and_counts(proxy: FaultProxy) -> None:
    payload = bytes(range(256)) * 1024
    with _connect(proxy) as sock:
        sock.sendall(payload)
        assert _recv_exactly(sock, len(payload)) == payload
    # the proxy counts a block after forwarding it: give the last count a moment
    deadline = time.monotonic() + 5
    while proxy.bytes_down < len(payload) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert proxy.bytes_up == len(payload)
    assert proxy.bytes_down == len(payload)
    assert proxy.accepted == 1


def test_client_eof_is_forwarded(proxy: FaultProxy) -> None:
    with _connect(proxy) as sock:
        sock.sendall(b"bye")
        sock.shutdown(socket.SHUT_WR)
        assert _recv_exactly(sock, 4) == b"bye"  # then EOF, not a hang


def test_blackhole_holds_data_without_closing(proxy: FaultProxy) -> None:
    with _connect(proxy) as sock:
        sock.sendall(b"ping")
        assert _recv_exactly(sock, 4) == b"ping"
        proxy.blackhole()
        assert proxy.mode is Mode.BLACKHOLE
        sock.sendall(b"lost?")
        sock.settimeout(0.3)
        with pytest.raises(socket.timeout):
            sock.recv(16)
        proxy.pass_through()
        sock.settimeout(5)
        assert _recv_exactly(sock, 5) == b"lost?"


def test_cut_resets_connections_and_refuses_new_ones(proxy: FaultProxy) -> None:
    sock = _connect(proxy)
    with sock:
        sock.sendall(b"x")
        assert _recv_exactly(sock, 1) == b"x"
        proxy.cut()
        with pytest.raises(OSError):
            # A reset shows either on the next recv or the send after it.
            if sock.recv(1) == b"":
                raise ConnectionResetError
    assert proxy.active_connections == 0
    with pytest.raises(ConnectionRefusedError):
        _connect(proxy)
    proxy.pass_through()
    with _connect(proxy) as again:
        again.sendall(b"back")
        assert _recv_exactly(again, 4) == b"back"


def test_throttle_limits_the_rate(proxy: FaultProxy) -> None:
    proxy.throttle(bytes_per_second=200_000)
    payload = b"r" * 60_000
    with _connect(proxy) as sock:
        start = time.monotonic()
        sock.sendall(payload)
        assert _recv_exactly(sock, len(payload)) == payload
        elapsed = time.monotonic() - start
    # 60 kB at 200 kB/s is 0.3 s each way, pipelined: at least ~0.3 s in all.
    assert elapsed >= 0.25


def test_throttle_adds_latency_each_way(proxy: FaultProxy) -> None:
    proxy.throttle(latency=0.3)
    with _connect(proxy) as sock:
        start = time.monotonic()
        sock.sendall(b"rtt")
        assert _recv_exactly(sock, 3) == b"rtt"
        elapsed = time.monotonic() - start
    assert 0.6 <= elapsed < 3.0
    proxy.throttle()
    with _connect(proxy) as sock:
        start = time.monotonic()
        sock.sendall(b"rtt")
        assert _recv_exactly(sock, 3) == b"rtt"
        assert time.monotonic() - start < 0.3


def test_only_loopback_targets() -> None:
    with pytest.raises(ValueError, match="loopback"):
        FaultProxy("192.0.2.1", 22)


def test_stop_ends_the_thread_and_connections() -> None:
    echo = _EchoServer()
    try:
        proxy = FaultProxy("127.0.0.1", echo.port).start()
        sock = _connect(proxy)
        sock.sendall(b"x")
        assert _recv_exactly(sock, 1) == b"x"
        proxy.stop()
        assert not any(t.name == "FaultProxy" and t.is_alive() for t in threading.enumerate())
        with sock, pytest.raises(OSError):
            if sock.recv(1) == b"":
                raise ConnectionResetError
    finally:
        echo.close()


@pytest.mark.ssh
def test_ssh_through_the_proxy_and_cut(proxied_home: SSHHome, fault_proxy: FaultProxy) -> None:
    ok = subprocess.run(
        proxied_home.ssh_argv("echo", "hello"),
        check=False,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        timeout=20,
    )
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout == "hello\n"
    assert fault_proxy.bytes_down > 0
    long = subprocess.Popen(
        proxied_home.ssh_argv("echo started; sleep 30"),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert long.stdout is not None
        assert long.stdout.readline() == "started\n"
        fault_proxy.cut()
        assert long.wait(timeout=5) == 255
    finally:
        if long.poll() is None:
            long.kill()
            long.wait()
