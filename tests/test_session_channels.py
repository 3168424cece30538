"""Commands side by side on one SSH connection, against the real sshd: a robot that
refuses sessions past its MaxSessions, and a command that ends while we send its EOF,
lose no command and not the connection (fetchsync/link/channels.py)."""

from __future__ import annotations

import contextlib
import json
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import sshd as sshd_module
from click.testing import CliRunner
from paramiko.ssh_exception import ChannelException
from sshd import SSHHome, make_ssh_home, running_sshd
from test_snapshot import _why, by_name, only_archive, read_archive

from fetchsync.cli import cli
from fetchsync.errors import LinkLostError, TransportError
from fetchsync.link import channels
from fetchsync.link.ssh import SSHTransport

pytestmark = pytest.mark.ssh


def run(transport: SSHTransport, command: str) -> tuple[int | None, bytes]:
    chan = transport.exec(command)
    chan.shutdown_write()
    out = b""
    while data := chan.recv(1 << 16):
        out += data
    status = chan.exit_status(30)
    chan.close()
    return status, out


class _HeldBack(threading.Event):
    """paramiko's clear_to_send, holding back one thread's next message until ``release``
    is set: the moment a busy machine preempts a sender between building and sending."""

    def __init__(self, held: threading.Thread, release: threading.Event) -> None:
        super().__init__()
        self.held, self.release = held, release

    def wait(self, timeout: float | None = None) -> bool:
        if threading.current_thread() is self.held and not self.release.is_set():
            assert self.release.wait(30)
        return super().wait(timeout)


@contextlib.contextmanager
def held_until_closed(
    transport: SSHTransport,
    chan: Any,
    closed: Callable[[Any, Any], None] | None = None,
) -> Iterator[None]:
    """This thread's next message (built inside the block) is sent only once the robot's
    CLOSE of ``chan`` was handled and ours sent (``closed(t, raw)`` waits for that; by
    default until paramiko unlinks the channel): the order a busy machine can make."""
    t: Any = transport._transport
    raw = chan._chan
    release = threading.Event()
    held = _HeldBack(threading.current_thread(), release)
    if t.clear_to_send.is_set():
        held.set()
    t.clear_to_send = held

    def when_closed() -> None:
        if closed is None:
            while t._channels.get(raw.get_id()) is raw:
                threading.Event().wait(0.01)
        else:
            closed(t, raw)
        release.set()

    try:
        threading.Thread(target=when_closed, daemon=True).start()
        yield
    finally:
        release.set()


def test_an_eof_sent_as_the_command_ends_keeps_the_connection(robot_transport: SSHTransport):
    """The EOF of a command that has already ended, built before the robot's CLOSE came
    and sent after paramiko answered it with ours: sshd would drop the connection
    ("ieof packet referred to nonexistent channel") with every command on it."""
    chan = robot_transport.exec("true")
    with held_until_closed(robot_transport, chan):
        chan.shutdown_write()
    assert chan.exit_status(10) == 0
    chan.close()
    assert run(robot_transport, "echo still here") == (0, b"still here\n")
    assert robot_transport.is_alive(10)


def test_data_sent_as_the_command_ends_keeps_the_connection(robot_transport: SSHTransport):
    """The same race with data (a password written to a command that ended at once, a
    master forwarding bytes to an endpoint that just exited): built before the robot's
    CLOSE came, it must not follow ours."""
    chan = robot_transport.exec("true")
    with held_until_closed(robot_transport, chan):
        chan.send_all(b"a password\n")
    chan.close()
    assert run(robot_transport, "echo still here") == (0, b"still here\n")
    assert robot_transport.is_alive(10)


def test_commands_past_the_robots_max_sessions_wait_for_a_session(limited_home):
    """A robot whose sshd allows 2 sessions per connection, 8 commands at once on one
    connection: each gets its session in turn (none fails, the link stays)."""
    limited_home(sessions=2)
    transport = SSHTransport.connect("robot", connect_timeout=10.0)
    try:
        results: dict[int, Any] = {}

        def one(i: int) -> None:
            try:
                results[i] = run(transport, f"sleep 0.2; echo {i}")
            except Exception as exc:  # noqa: BLE001 - the assertion shows it
                results[i] = exc

        threads = [threading.Thread(target=one, args=(i,)) for i in range(8)]
        for th in threads:
            th.start()
        for th in threads:
            th.join(120)
        assert results == {i: (0, f"{i}\n".encode()) for i in range(8)}
        assert transport.is_alive(10)
    finally:
        transport.close()


def test_a_snapshot_on_a_robot_allowing_two_sessions_collects_everything(
    limited_home, clean_process_env, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """The debug snapshot runs 8 collectors at once on one connection; a robot allowing 2
    sessions per connection still gives every one of them its output."""
    limited_home(sessions=2)
    monkeypatch.setenv("FETCHSYNC_ROBOT", "robot")
    config = tmp_path / "many.json"
    names = [f"c{i}" for i in range(12)]
    config.write_text(
        json.dumps(
            {
                "defaults": False,
                "collectors": [{"name": n, "command": f"sleep 0.1; echo {n}"} for n in names],
            }
        )
    )
    out = tmp_path / "out"
    out.mkdir()
    result = CliRunner().invoke(cli, ["snapshot", "--output", str(out), "--config", str(config)])
    assert result.exit_code == 0, _why(result)
    manifest, files = read_archive(only_archive(out))
    entries = by_name(manifest)
    assert {n: entries[n]["status"] for n in names} == {n: "ok" for n in names}
    assert {n: files[f"{n}.txt"] for n in names} == {n: f"{n}\n".encode() for n in names}


def test_a_robot_refusing_every_session_is_a_refusal_not_a_lost_link(
    limited_home, monkeypatch: pytest.MonkeyPatch
):
    """MaxSessions 0: the opens are refused a few times, then that is the answer; the
    connection itself was never lost."""
    limited_home(sessions=0)
    monkeypatch.setattr(channels, "BACKOFF", 0.01)
    transport = SSHTransport.connect("robot", connect_timeout=10.0)
    try:
        with pytest.raises(TransportError) as caught:
            transport.exec("true")
        assert not isinstance(caught.value, LinkLostError)
        assert "refused" in str(caught.value)
        assert transport.is_alive(10)
    finally:
        transport.close()


@pytest.fixture
def limited_home(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[Callable[..., SSHHome]]:
    """make(sessions=N): a HOME reaching, as ``robot``, an sshd of its own that allows N
    session channels per connection (sshd takes a keyword's first value: the line goes
    first)."""
    real = sshd_module._sshd_config
    stack = contextlib.ExitStack()

    def make(*, sessions: int) -> SSHHome:
        def config(*args: Any, **kwargs: Any) -> str:
            return f"MaxSessions {sessions}\n" + real(*args, **kwargs)

        monkeypatch.setattr(sshd_module, "_sshd_config", config)
        server = stack.enter_context(running_sshd(tmp_path / f"sshd-{sessions}"))
        home = make_ssh_home(tmp_path / "home", sshd=server)
        monkeypatch.setenv("HOME", str(home.home))
        monkeypatch.delenv("SSH_AUTH_SOCK", raising=False)
        return home

    with stack:
        yield make


class _FakeChannel:
    def __init__(self, n: int) -> None:
        self.n = n

    def get_id(self) -> int:
        return self.n


class _Sshd:
    """A paramiko transport's channel bookkeeping, over a server allowing ``cap`` sessions
    (a unit test of SessionSlots' arithmetic; the real sshd's tests are above)."""

    def __init__(self, cap: int) -> None:
        self.cap, self._channels_d, self.n = cap, {}, 0
        self.refused = 0
        self._channels = self  # SessionSlots reads transport._channels.get(id)

    def get(self, n: int) -> Any:
        return self._channels_d.get(n)

    def is_active(self) -> bool:
        return True

    def open_session(self, timeout: float | None = None) -> _FakeChannel:
        if len(self._channels_d) >= self.cap:
            self.refused += 1
            raise ChannelException(1, "open failed")
        self.n += 1
        chan = self._channels_d[self.n] = _FakeChannel(self.n)
        return chan

    def close(self, chan: _FakeChannel) -> None:
        del self._channels_d[chan.n]


def test_a_lowered_session_limit_recovers(monkeypatch: pytest.MonkeyPatch):
    """A refusal lowers the limit to what the robot held; one channel held for hours (a
    watch agent's endpoint) does not make every later open wait: past the wait the open
    is tried, and once it succeeds the limit follows; RELEARN after the refusal it is
    forgotten."""
    server = _Sshd(cap=1)
    slots = channels.SessionSlots(server)  # type: ignore[arg-type]
    long_lived = slots.open(timeout=1.0)
    monkeypatch.setattr(channels, "BACKOFF", 0.001)
    with pytest.raises(ChannelException):
        slots.open(timeout=0.05)  # the robot allows one: refused, a few times
    assert slots.limit == 1 and server.refused == channels.REFUSALS
    server.cap = 3  # its sessions freed
    second = slots.open(timeout=0.2)  # waits 0.2 s for a slot, then the robot's answer
    assert slots.limit == 2
    monkeypatch.setattr(channels, "RELEARN", 0.0)
    third = slots.open(timeout=30.0)  # the refusal forgotten: no wait
    assert slots.limit == channels.MAX_SESSIONS
    for chan in (long_lived, second, third):
        server.close(chan)
