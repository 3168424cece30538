"""The connection begun before paramiko is imported (fetchsync.preconnect), against the
real sshd: used when the ssh config still says what it said, discarded when not."""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path

import pytest
from sshd import SSHD, SSHHome

from fetchsync import preconnect, session, ssh
from fetchsync.config import Target
from fetchsync.errors import ConnectError

pytestmark = pytest.mark.ssh


@pytest.fixture(autouse=True)
def _cache(ssh_home: SSHHome, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(ssh_home.home / ".cache"))
    monkeypatch.setenv("FETCHSYNC_PERSIST", "0")  # a direct connection every time


def target(host: str) -> Target:
    return Target(robot=host, host=host, user=None, workspace=Path("/nonexistent"),
                  remote_workspace="~/ws", is_local=False)


def proxied(home: SSHHome, log: Path, name: str = "viaproxy") -> None:
    """Add host ``name``, reached through a ProxyCommand that notes each start in ``log``."""
    sshd = home.sshd
    home.config.write_text(
        f"Host {name}\n    HostName {sshd.host}\n    Port {sshd.port}\n    User {sshd.user}\n"
        f"    IdentityFile {home.identity}\n    UserKnownHostsFile {home.known_hosts}\n"
        "    GlobalKnownHostsFile /dev/null\n"
        f"    ProxyCommand sh -c 'echo $$ >> {log}; exec ssh -F {sshd.ssh_config} -o BatchMode=yes "
        "-W %h:%p robot 2>/dev/null'\n" + home.config.read_text())


def echo(transport: ssh.SSHTransport) -> bytes:
    chan = transport.exec("echo ok")
    try:
        out = b""
        while chunk := chan.recv(100):
            out += chunk
        return out
    finally:
        chan.close()


def taken_over(monkeypatch: pytest.MonkeyPatch) -> list[bool]:
    """Whether each ProxyCommand the transport made was one started early."""
    seen: list[bool] = []
    real = ssh._ProxyCommand.__init__

    def init(self: ssh._ProxyCommand, command_line: str, **kwargs: object) -> None:
        seen.append(kwargs.get("started") is not None)
        real(self, command_line, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(ssh._ProxyCommand, "__init__", init)
    return seen


def test_the_next_connection_starts_the_noted_proxy_command_before_paramiko(
        ssh_home: SSHHome, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    log = tmp_path / "proxy.log"
    proxied(ssh_home, log)
    seen = taken_over(monkeypatch)
    assert preconnect.begin("viaproxy") is None  # nothing noted yet
    first = session.open_transport(target("viaproxy"))
    assert echo(first) == b"ok\n"
    first.close()
    notes = list((ssh_home.home / ".cache" / "fetchsync").glob("connect-*"))
    assert len(notes) == 1 and notes[0].stat().st_mode & 0o777 == 0o600
    assert "exec ssh" in notes[0].read_text()
    second = session.open_transport(target("viaproxy"))
    assert echo(second) == b"ok\n"
    second.close()
    assert seen == [False, True]  # the second one took over the command started early
    assert len(log.read_text().split()) == 2  # and it ran once per connection


def test_a_note_the_config_no_longer_agrees_with_is_discarded(
        ssh_home: SSHHome, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    log = tmp_path / "proxy.log"
    proxied(ssh_home, log)
    seen = taken_over(monkeypatch)
    stray = tmp_path / "stray.pid"
    # as if the config's answer had changed under the same file (what a Match block
    # could do, and why such configs are never noted)
    preconnect.remember("viaproxy", user=None, port=None, config_path=None, hostname="127.0.0.1",
                        resolved_port=ssh_home.sshd.port,
                        proxy_command=f"sh -c 'echo $$ > {stray}; exec sleep 30'")
    transport = session.open_transport(target("viaproxy"))
    assert echo(transport) == b"ok\n"
    transport.close()
    assert seen == [False]  # the config's own command, started as usual
    pid = int(stray.read_text())
    deadline = time.monotonic() + 5
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(pid)  # the early one was stopped
    # and the note now says what the config says
    assert preconnect.begin("viaproxy") is not None


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(") ")[1][0] != "Z"
    except OSError:
        return False


def test_a_direct_connection_is_begun_and_taken_over(ssh_home: SSHHome, monkeypatch: pytest.MonkeyPatch) -> None:
    connects: list[object] = []
    real = ssh._tcp_connect
    monkeypatch.setattr(ssh, "_tcp_connect", lambda *a, **k: connects.append(a) or real(*a, **k))
    session.open_transport(target("robot")).close()
    assert len(connects) == 1
    early = preconnect.begin("robot")
    assert early is not None and early.matches("127.0.0.1", ssh_home.sshd.port, None)
    early.close()
    transport = session.open_transport(target("robot"))
    assert echo(transport) == b"ok\n"
    transport.close()
    assert len(connects) == 1  # the second connected before paramiko was imported


def test_an_early_connect_that_fails_fails_as_the_usual_one_would(
        ssh_home: SSHHome, tmp_path: Path) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        closed_port = s.getsockname()[1]
    config = tmp_path / "config"
    config.write_text(f"Host gone\n    HostName 127.0.0.1\n    Port {closed_port}\n")
    preconnect.remember("gone", user=None, port=None, config_path=config, hostname="127.0.0.1",
                        resolved_port=closed_port, proxy_command=None)
    early = preconnect.begin("gone", config_path=config)
    assert early is not None
    with pytest.raises(ConnectError) as with_early:
        ssh.SSHTransport.connect("gone", config_path=config, connect_timeout=5, early=early)
    with pytest.raises(ConnectError) as without:
        ssh.SSHTransport.connect("gone", config_path=config, connect_timeout=5)
    assert str(with_early.value) == str(without.value)
    assert f"connection refused by 127.0.0.1 port {closed_port}" in str(without.value)


def test_a_note_others_can_write_is_not_used(ssh_home: SSHHome, tmp_path: Path) -> None:
    config = tmp_path / "config"
    config.write_text("Host r\n    HostName 127.0.0.1\n")
    preconnect.remember("r", user=None, port=None, config_path=config, hostname="127.0.0.1",
                        resolved_port=ssh_home.sshd.port, proxy_command=None)
    (note,) = (ssh_home.home / ".cache" / "fetchsync").glob("connect-*")
    early = preconnect.begin("r", config_path=config)
    assert early is not None
    early.close()
    note.chmod(0o666)
    assert preconnect.begin("r", config_path=config) is None


@pytest.mark.parametrize("line", ["Match host r exec \"true\"", "CanonicalizeHostname yes"])
def test_configs_whose_answer_depends_on_more_than_the_file_are_not_noted(
        ssh_home: SSHHome, tmp_path: Path, line: str) -> None:
    config = tmp_path / "config"
    config.write_text(f"Host r\n    HostName 127.0.0.1\n{line}\n")
    preconnect.remember("r", user=None, port=None, config_path=config, hostname="127.0.0.1",
                        resolved_port=22, proxy_command=None)
    assert preconnect.begin("r", config_path=config) is None


def test_an_edited_config_is_not_answered_by_the_old_note(ssh_home: SSHHome, tmp_path: Path) -> None:
    config = tmp_path / "config"
    config.write_text("Host r\n    HostName 127.0.0.1\n")
    preconnect.remember("r", user=None, port=None, config_path=config, hostname="127.0.0.1",
                        resolved_port=22, proxy_command=None)
    early = preconnect.begin("r", config_path=config)
    assert early is not None
    early.close()
    config.write_text("Host r\n    HostName 127.0.0.2\n")
    os.utime(config, ns=(time.time_ns(), time.time_ns() + 10**9))
    assert preconnect.begin("r", config_path=config) is None
    assert preconnect.begin("r", user="someone", config_path=config) is None
