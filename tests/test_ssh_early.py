"""A direct connection's route opened before paramiko's import (fetchsync.link.early),
against the real sshd: used only where the config, resolved afresh, gives that very
route; the host key still checked; the memory refused where anyone else could write it."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any, Iterator

import pytest
from helpers import fetchsync, ssh_env
from sshd import SSHHome
from test_ssh import extra_config, run

from fetchsync.errors import ConnectError, HostKeyError
from fetchsync.link import early
from fetchsync.link.ssh import SSHTransport

pytestmark = pytest.mark.ssh


@pytest.fixture(autouse=True)
def _own_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """This test's memories only (the session's laptop cache holds other tests')."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))


@pytest.fixture
def settled(monkeypatch: pytest.MonkeyPatch) -> None:
    """A config written by the test counts as settled at once (else 2 s must pass)."""
    monkeypatch.setattr(early, "SETTLED_NS", 0)


@pytest.fixture
def opened() -> Iterator[list[Any]]:
    things: list[Any] = []
    yield things
    for thing in things:
        thing.close()


def _proxy_config(home: SSHHome, log: Path, name: str = "viaproxy") -> None:
    extra_config(
        home,
        f"Host {name}\n    HostName {{host}}\n    Port {{port}}\n{{common}}"
        f"    ProxyCommand sh -c 'echo started >> {log}; exec ssh -F {{sshd_config}} "
        "-o BatchMode=yes -W %h:%p robot 2>/dev/null'\n",
    )


def _memories(cache: Path) -> list[Path]:
    return sorted((cache / "fetchsync").glob("route-*"))


def _cache() -> Path:
    return Path(os.environ["XDG_CACHE_HOME"])


def _starts(log: Path) -> int:
    return len(log.read_text().splitlines()) if log.exists() else 0


def test_the_next_direct_connection_runs_the_remembered_proxy_command_early_and_uses_it(
    ssh_home: SSHHome, settled: None, opened: list[Any], tmp_path: Path
) -> None:
    log = tmp_path / "proxy.log"
    _proxy_config(ssh_home, log)
    first = SSHTransport.connect("viaproxy", connect_timeout=10.0)
    opened.append(first)
    assert _starts(log) == 1
    link = early.start("viaproxy")
    assert link is not None and link.route[2] is not None and "proxy.log" in link.route[2]
    deadline = time.monotonic() + 10
    while _starts(log) < 2 and time.monotonic() < deadline:  # started now, before any connect
        time.sleep(0.01)
    assert _starts(log) == 2
    second = SSHTransport.connect("viaproxy", connect_timeout=10.0, early=link)
    opened.append(second)
    assert run(second, "echo early") == (b"early\n", b"", 0)
    assert _starts(log) == 2  # the connection went through the early one: none started


def test_a_tcp_route_is_connected_early_and_its_socket_used(
    ssh_home: SSHHome, settled: None, opened: list[Any]
) -> None:
    opened.append(SSHTransport.connect("robot", connect_timeout=10.0))
    link = early.start("robot")
    assert link is not None
    sshd = ssh_home.sshd
    assert link.route == (sshd.host, sshd.port, None)
    assert link._done.wait(10)
    sock = link._sock
    assert sock is not None
    transport = SSHTransport.connect("robot", connect_timeout=10.0, early=link)
    opened.append(transport)
    assert transport._transport.sock is sock
    assert run(transport, "echo tcp") == (b"tcp\n", b"", 0)


def test_a_changed_config_opens_no_remembered_route(
    ssh_home: SSHHome, settled: None, opened: list[Any], tmp_path: Path
) -> None:
    log = tmp_path / "proxy.log"
    _proxy_config(ssh_home, log)
    opened.append(SSHTransport.connect("viaproxy", connect_timeout=10.0))
    link = early.start("viaproxy")
    assert link is not None
    link.close()
    time.sleep(0.3)
    before = _starts(log)
    # a rewrite of the config, even of another host's block: its identity moved
    ssh_home.config.write_text(ssh_home.config.read_text() + "\nHost other\n    Port 2\n")
    assert early.start("viaproxy") is None
    time.sleep(0.3)
    assert _starts(log) == before  # nothing started


def test_a_route_the_fresh_resolution_does_not_give_is_closed_unused(
    ssh_home: SSHHome, settled: None, opened: list[Any], tmp_path: Path
) -> None:
    """A memory that says another route than the config (written by hand: the config's
    identity matches) starts that route early, but the connection is made the fresh way
    and the other route's process is ended."""
    log = tmp_path / "proxy.log"
    _proxy_config(ssh_home, log)
    opened.append(SSHTransport.connect("viaproxy", connect_timeout=10.0))
    (memory,) = _memories(_cache())
    stale = json.loads(memory.read_text())
    other = tmp_path / "other.log"
    stale["route"][2] = f"sh -c 'echo $$ >> {other}; exec sleep 30'"
    memory.write_text(json.dumps(stale))
    link = early.start("viaproxy")
    assert link is not None and link.process is not None
    process = link.process
    transport = SSHTransport.connect("viaproxy", connect_timeout=10.0, early=link)
    opened.append(transport)
    assert run(transport, "echo fresh") == (b"fresh\n", b"", 0)
    assert _starts(log) == 2  # the fresh route: the config's command ran again
    assert process.wait(5) is not None  # the other one was ended
    # and the memory says the config's route again
    assert json.loads(memory.read_text())["route"][2] != stale["route"][2]


def test_the_host_key_is_checked_on_an_early_route(
    ssh_home: SSHHome, settled: None, opened: list[Any]
) -> None:
    opened.append(SSHTransport.connect("robot", connect_timeout=10.0))
    link = early.start("robot")
    assert link is not None
    # known_hosts now lists another key for the robot (its config file is untouched)
    line = ssh_home.known_hosts.read_text().split("\n")[0].split()
    import paramiko

    other = paramiko.Ed25519Key.from_private_key_file(str(ssh_home.identity))
    ssh_home.known_hosts.write_text(f"{line[0]} {other.get_name()} {other.get_base64()}\n")
    with pytest.raises(HostKeyError, match="CHANGED"):
        SSHTransport.connect("robot", connect_timeout=10.0, early=link)


@pytest.mark.parametrize(
    "block",
    [
        "Match host viaproxy exec true\n    Port {port}\n",
        "Include /dev/null\n",
        "Host jumped\n    HostName {host}\n    Port {port}\n{common}    ProxyJump robot\n",
    ],
    ids=["match", "include", "proxyjump"],
)
def test_no_route_is_remembered_where_it_may_depend_on_more_than_the_text(
    ssh_home: SSHHome, settled: None, opened: list[Any], block: str
) -> None:
    extra_config(ssh_home, block)
    host = "jumped" if "jumped" in block else "robot"
    opened.append(SSHTransport.connect(host, connect_timeout=10.0))
    assert _memories(_cache()) == []
    assert early.start(host) is None


def test_no_route_is_remembered_from_a_config_younger_than_two_seconds(
    ssh_home: SSHHome, opened: list[Any]
) -> None:
    ssh_home.config.write_text(ssh_home.config.read_text() + "\n")
    opened.append(SSHTransport.connect("robot", connect_timeout=10.0))
    assert early.start("robot") is None


@pytest.mark.parametrize("how", ["group-writable", "symlink", "dir-group-writable"])
def test_a_memory_anyone_else_could_write_is_not_used(
    ssh_home: SSHHome, settled: None, opened: list[Any], tmp_path: Path, how: str
) -> None:
    opened.append(SSHTransport.connect("robot", connect_timeout=10.0))
    (memory,) = _memories(_cache())
    assert early.start("robot") is not None
    directory = memory.parent
    if how == "group-writable":
        memory.chmod(0o620)
    elif how == "symlink":
        elsewhere = tmp_path / "elsewhere"
        elsewhere.write_bytes(memory.read_bytes())
        memory.unlink()
        memory.symlink_to(elsewhere)
    else:
        directory.chmod(0o770)
    try:
        assert early.start("robot") is None
        if how == "dir-group-writable":  # nor is one written there
            memory.unlink()
            opened.append(SSHTransport.connect("robot", connect_timeout=10.0))
            assert _memories(_cache()) == []
    finally:
        directory.chmod(0o700)
        if memory.is_symlink():
            memory.unlink()


def test_a_push_opens_the_remembered_route_before_importing_paramiko(
    ssh_home: SSHHome, remote_dir: Path, tmp_path: Path
) -> None:
    """The CLI end to end: the second direct push (no master) opens its route first."""
    env = ssh_env(
        ssh_home.home,
        remote_dir,
        tmp_path,
        FETCHSYNC_PERSIST="0",
        XDG_CACHE_HOME=os.environ["XDG_CACHE_HOME"],
    )
    trace = tmp_path / "trace"
    env["FETCHSYNC_TRACE"] = str(trace)
    time.sleep(early.SETTLED_NS / 1e9 + 0.1)  # the fixture's config, settled
    fetchsync("push", env=env)
    first = trace.read_text().splitlines()
    assert not any("early: route opened" in line for line in first)
    trace.unlink()
    (Path(env["FETCHSYNC_WORKSPACE"]) / "src" / "new.txt").write_text("new\n")
    fetchsync("push", env=env)
    marks = [line.split(" ", 2)[2] for line in trace.read_text().splitlines()]
    assert "early: route opened" in marks
    assert marks.index("early: route opened") < marks.index("ssh: paramiko imported")
    assert (remote_dir / "src" / "new.txt").read_text() == "new\n"


def test_an_early_route_that_fails_is_reported_as_the_connection_failing(
    proxied_home: SSHHome, fault_proxy: Any, settled: None, opened: list[Any]
) -> None:
    """The early connect's own failure is the connection's (one attempt, one line)."""
    opened.append(SSHTransport.connect("robot", connect_timeout=10.0))
    fault_proxy.cut()
    link = early.start("robot")
    assert link is not None and link.route[1] == fault_proxy.port
    with pytest.raises(ConnectError, match="refused"):
        SSHTransport.connect("robot", connect_timeout=10.0, early=link)
