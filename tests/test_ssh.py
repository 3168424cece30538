"""SSHTransport against a real OpenSSH sshd (the ``sshd`` / ``ssh_home`` fixtures)."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import paramiko
import pytest
from helpers import check_ready
from sshd import SSHD, SSHHome

from fetchsync.errors import ConfigError, ConnectError, HostKeyError, LinkLostError
from fetchsync.link.ssh import (
    SSHTransport,
    env_prefix,
    load_ssh_config,
    parse_jump,
    resolve_host,
)
from fetchsync.link.transport import Channel

pytestmark = pytest.mark.ssh


def read_all(recv: Callable[[int], bytes]) -> bytes:
    out = b""
    while True:
        chunk = recv(65536)
        if not chunk:
            return out
        out += chunk


def run(transport: SSHTransport, command: str, **kwargs: Any) -> tuple[bytes, bytes, int | None]:
    chan = transport.exec(command, **kwargs)
    try:
        out = read_all(chan.recv)
        err = read_all(chan.recv_stderr)
        return out, err, chan.exit_status(10)
    finally:
        chan.close()


Connect = Callable[..., SSHTransport]


@pytest.fixture
def connect() -> Iterator[Connect]:
    """SSHTransport.connect that closes what it opened at the end of the test."""
    opened: list[SSHTransport] = []

    def _connect(host: str = "robot", **kwargs: Any) -> SSHTransport:
        transport = SSHTransport.connect(host, connect_timeout=5.0, **kwargs)
        opened.append(transport)
        return transport

    yield _connect
    for transport in opened:
        transport.close()


def extra_config(home: SSHHome, text: str) -> Path:
    """Prepend ``text`` to the home's ssh config (first match wins in ssh config)."""
    sshd = home.sshd
    common = (
        f"    User {sshd.user}\n"
        f"    IdentityFile {home.identity}\n"
        f"    UserKnownHostsFile {home.known_hosts}\n"
        "    GlobalKnownHostsFile /dev/null\n"
    )
    body = text.format(host=sshd.host, port=sshd.port, common=common, sshd_config=sshd.ssh_config)
    home.config.write_text(body + home.config.read_text())
    return home.config


def robot_config(home: SSHHome, identity: Path) -> Path:
    """Replace the home's ssh config by ``Host robot`` with only ``identity``."""
    sshd = home.sshd
    home.config.write_text(
        f"Host robot\n    HostName {sshd.host}\n    Port {sshd.port}\n    User {sshd.user}\n"
        f"    IdentityFile {identity}\n    IdentitiesOnly yes\n"
        f"    UserKnownHostsFile {home.known_hosts}\n    GlobalKnownHostsFile /dev/null\n"
    )
    return home.config


# -- connect and exec ------------------------------------------------------


def test_connect_through_config_alias_and_run_a_command(
    ssh_home: SSHHome, connect: Connect
) -> None:
    transport = connect()  # ~/.ssh/config of the fixture's HOME
    assert transport.name == "robot"
    s = transport.settings
    assert (s.hostname, s.port, s.user) == (
        ssh_home.sshd.host,
        ssh_home.sshd.port,
        ssh_home.sshd.user,
    )
    assert s.identity_files == (str(ssh_home.identity),)
    out, err, status = run(transport, "echo hi; echo oops >&2; exit 3")
    assert (out, err, status) == (b"hi\n", b"oops\n", 3)


def test_explicit_config_path(sshd: SSHD, connect: Connect) -> None:
    transport = connect(config_path=sshd.ssh_config)
    assert run(transport, "echo hi") == (b"hi\n", b"", 0)


def test_channel_is_a_byte_stream_both_ways(ssh_home: SSHHome, connect: Connect) -> None:
    transport = connect()
    chan: Channel = transport.exec("cat; echo done >&2")
    payload = bytes(range(256)) * 1000
    chan.send_all(payload)
    chan.shutdown_write()
    assert read_all(chan.recv) == payload
    assert read_all(chan.recv_stderr) == b"done\n"
    assert chan.exit_status(10) == 0
    chan.close()


def test_ready_tells_when_output_is_waiting(ssh_home: SSHHome, connect: Connect) -> None:
    """Channel.ready(): not before the command writes, then at once, and at its end."""
    check_ready(connect().exec("sleep 1; echo hi; sleep 0.5"))


def test_exit_status_waits_and_times_out(ssh_home: SSHHome, connect: Connect) -> None:
    transport = connect()
    chan = transport.exec("read x; exit 7")
    assert chan.exit_status(0.1) is None
    chan.send_all(b"go\n")
    assert chan.exit_status(10) == 7
    chan.close()


def test_env_is_exported_by_the_command_prefix(ssh_home: SSHHome, connect: Connect) -> None:
    transport = connect()
    out, _, status = run(transport, 'printf %s "$FOO|$BAR"', env={"FOO": "a b'c", "BAR": "$HOME"})
    assert (out, status) == (b"a b'c|$HOME", 0)
    with pytest.raises(ValueError):
        env_prefix({"A;rm": "x"})


def test_pty_requests_a_terminal(ssh_home: SSHHome, connect: Connect) -> None:
    transport = connect()
    out, _, status = run(transport, "test -t 0 && echo tty", pty=True)
    assert out.strip() == b"tty" and status == 0


def test_keepalive_is_set_and_link_reported_alive(ssh_home: SSHHome, connect: Connect) -> None:
    transport = connect(keepalive=2.0)
    assert transport.is_alive(timeout=5)
    assert transport.is_alive(timeout=0)
    transport.close()
    assert not transport.is_alive()


# -- host keys -------------------------------------------------------------


def test_unknown_host_key_is_refused_with_its_fingerprint(
    ssh_home: SSHHome, connect: Connect
) -> None:
    ssh_home.known_hosts.write_text("")
    sshd = ssh_home.sshd
    with pytest.raises(HostKeyError) as info:
        connect()
    message = str(info.value)
    assert sshd.host_key_fingerprint in message
    assert "ED25519" in message
    assert f"ssh -p {sshd.port} {sshd.user}@robot once to accept it" in message
    assert f"--accept-host-key {sshd.host_key_fingerprint}" in message
    assert "\n" not in message
    assert ssh_home.known_hosts.read_text() == ""


def test_accepted_fingerprint_is_recorded(ssh_home: SSHHome, connect: Connect) -> None:
    ssh_home.known_hosts.write_text("# no keys yet")  # no final newline
    sshd = ssh_home.sshd
    transport = connect(accept_fingerprint=sshd.host_key_fingerprint)
    assert run(transport, "echo ok")[0] == b"ok\n"
    lines = ssh_home.known_hosts.read_text().splitlines()
    assert lines == ["# no keys yet", f"{sshd.known_hosts_name} {sshd.host_key_pub}"]
    connect()  # known from now on


def test_accepted_key_is_hashed_when_the_config_says_so(
    ssh_home: SSHHome, connect: Connect
) -> None:
    ssh_home.known_hosts.write_text("")
    extra_config(ssh_home, "Host robot\n    HashKnownHosts yes\n")
    connect(accept_fingerprint=ssh_home.sshd.host_key_fingerprint)
    text = ssh_home.known_hosts.read_text()
    assert text.startswith("|1|") and ssh_home.sshd.host not in text
    connect()


def test_wrong_accept_fingerprint_is_refused(ssh_home: SSHHome, connect: Connect) -> None:
    ssh_home.known_hosts.write_text("")
    with pytest.raises(HostKeyError, match="not the SHA256:nope"):
        connect(accept_fingerprint="SHA256:nope")
    assert ssh_home.known_hosts.read_text() == ""


def _other_ed25519_line(tmp_path: Path, name: str) -> str:
    path = tmp_path / "other_host_key"
    subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(path)], check=True)
    key_type, data = path.with_suffix(".pub").read_text().split()[:2]
    return f"{name} {key_type} {data}\n"


def test_changed_host_key_is_refused_even_with_the_new_fingerprint(
    ssh_home: SSHHome, connect: Connect, tmp_path: Path
) -> None:
    sshd = ssh_home.sshd
    ssh_home.known_hosts.write_text(_other_ed25519_line(tmp_path, sshd.known_hosts_name))
    for accept in (None, sshd.host_key_fingerprint):
        with pytest.raises(HostKeyError, match="REMOTE HOST IDENTIFICATION HAS CHANGED") as info:
            connect(accept_fingerprint=accept)
        assert sshd.host_key_fingerprint in str(info.value)
        assert "known_hosts:1" in str(info.value)
    assert sshd.host_key_pub not in ssh_home.known_hosts.read_text()


def test_known_key_of_another_type_counts_as_changed(ssh_home: SSHHome, connect: Connect) -> None:
    sshd = ssh_home.sshd
    other = paramiko.ECDSAKey.generate()
    ssh_home.known_hosts.write_text(
        f"{sshd.known_hosts_name} {other.get_name()} {other.get_base64()}\n"
    )
    with pytest.raises(HostKeyError, match="CHANGED"):
        connect(accept_fingerprint=sshd.host_key_fingerprint)


def test_hashed_and_pattern_entries_match(
    ssh_home: SSHHome, connect: Connect, tmp_path: Path
) -> None:
    sshd = ssh_home.sshd
    hashed = paramiko.HostKeys.hash_host(sshd.known_hosts_name)
    ssh_home.known_hosts.write_text(f"{hashed} {sshd.host_key_pub}\n")
    connect()
    ssh_home.known_hosts.write_text(f"[127.0.0.*]:{sshd.port},other {sshd.host_key_pub}\n")
    connect()
    # A negated pattern excludes the host even though the wildcard matches it.
    ssh_home.known_hosts.write_text(
        f"[127.0.0.*]:{sshd.port},!{sshd.known_hosts_name} {sshd.host_key_pub}\n"
    )
    with pytest.raises(HostKeyError, match="not known"):
        connect()


def test_revoked_host_key_is_refused(ssh_home: SSHHome, connect: Connect) -> None:
    sshd = ssh_home.sshd
    ssh_home.known_hosts.write_text(
        f"@revoked * {sshd.host_key_pub}\n{sshd.known_hosts_name} {sshd.host_key_pub}\n"
    )
    with pytest.raises(HostKeyError, match="revoked"):
        connect()


def test_global_known_hosts_file_is_read(ssh_home: SSHHome, connect: Connect) -> None:
    glob = ssh_home.home / "global_known_hosts"
    glob.write_text(ssh_home.known_hosts.read_text())
    ssh_home.known_hosts.write_text("")
    extra_config(ssh_home, f"Host robot\n    GlobalKnownHostsFile {glob}\n")
    connect()


# -- authentication --------------------------------------------------------


def test_key_the_robot_does_not_know_is_permission_denied(
    ssh_home: SSHHome, connect: Connect, tmp_path: Path
) -> None:
    stranger = tmp_path / "stranger"
    subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(stranger)], check=True)
    robot_config(ssh_home, stranger)
    prompts: list[str] = []

    def no_password(prompt: str) -> str | None:
        prompts.append(prompt)
        return None

    with pytest.raises(ConnectError) as info:
        connect(password_callback=no_password)
    assert not isinstance(info.value, HostKeyError)
    message = str(info.value)
    user = ssh_home.sshd.user
    assert message.startswith(f"permission denied for {user}@robot")
    assert str(stranger) in message and "password" in message
    assert prompts == [f"{user}@robot's password: "]


def test_default_keys_are_used_without_identity_file(ssh_home: SSHHome, connect: Connect) -> None:
    # The fixture's key is also ~/.ssh/id_ed25519: a config without IdentityFile finds it.
    sshd = ssh_home.sshd
    ssh_home.config.write_text(
        f"Host bare\n    HostName {sshd.host}\n    Port {sshd.port}\n    User {sshd.user}\n"
        f"    UserKnownHostsFile {ssh_home.known_hosts}\n"
    )
    assert run(connect("bare"), "echo ok")[0] == b"ok\n"


@pytest.fixture
def agent(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[[Path], None]]:
    """A private ssh-agent as SSH_AUTH_SOCK; call it with a key file to add the key."""
    sock = tmp_path / "agent.sock"
    proc = subprocess.Popen(
        ["ssh-agent", "-D", "-a", str(sock)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    try:
        deadline = time.monotonic() + 5
        while not sock.exists():
            assert time.monotonic() < deadline, "ssh-agent did not start"
            time.sleep(0.01)
        monkeypatch.setenv("SSH_AUTH_SOCK", str(sock))

        def add(key: Path) -> None:
            env = dict(os.environ, SSH_AUTH_SOCK=str(sock))
            subprocess.run(["ssh-add", "-q", str(key)], check=True, env=env, capture_output=True)

        yield add
    finally:
        proc.terminate()
        proc.wait(5)


def test_agent_key_is_used(
    ssh_home: SSHHome, connect: Connect, agent: Callable[[Path], None], tmp_path: Path
) -> None:
    # Only the agent holds the private key; IdentitiesOnly picks it by the .pub beside the name.
    only_pub = tmp_path / "in_agent"
    only_pub.write_bytes(ssh_home.identity.read_bytes())
    only_pub.chmod(0o600)
    (tmp_path / "in_agent.pub").write_bytes(ssh_home.identity.with_suffix(".pub").read_bytes())
    agent(only_pub)
    only_pub.unlink()
    robot_config(ssh_home, only_pub)
    assert run(connect(), "echo agent")[0] == b"agent\n"


def test_agent_keys_are_listed_when_refused(
    ssh_home: SSHHome, connect: Connect, agent: Callable[[Path], None], tmp_path: Path
) -> None:
    stranger = tmp_path / "stranger"
    subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(stranger)], check=True)
    agent(stranger)
    robot_config(ssh_home, stranger)
    with pytest.raises(ConnectError, match=r"\(tried: agent \(1 key\)\)"):
        connect()


def test_encrypted_key_asks_for_its_passphrase(
    ssh_home: SSHHome, connect: Connect, tmp_path: Path
) -> None:
    locked = tmp_path / "locked"
    locked.write_bytes(ssh_home.identity.read_bytes())
    locked.chmod(0o600)
    subprocess.run(["ssh-keygen", "-q", "-p", "-N", "s3cret", "-f", str(locked)], check=True)
    robot_config(ssh_home, locked)
    prompts: list[str] = []

    def passphrase(prompt: str) -> str | None:
        prompts.append(prompt)
        return "s3cret"

    connect(password_callback=passphrase)
    assert prompts == [f"Enter passphrase for key '{locked}': "]
    with pytest.raises(ConnectError, match="has a passphrase; skipped"):
        connect()


# -- proxies ---------------------------------------------------------------


def test_proxy_command(ssh_home: SSHHome, connect: Connect) -> None:
    extra_config(
        ssh_home,
        "Host viaproxy\n    HostName {host}\n    Port {port}\n{common}"
        "    ProxyCommand ssh -F {sshd_config} -o BatchMode=yes -W %h:%p robot 2>/dev/null\n",
    )
    transport = connect("viaproxy")
    assert run(transport, "echo through") == (b"through\n", b"", 0)
    # a push streams through the command's pipes: 1 MiB each, not 64 KiB
    import fcntl

    proxy = transport._transport.sock  # type: ignore[attr-defined]
    limit = int(Path("/proc/sys/fs/pipe-max-size").read_text())
    for pipe in (proxy.process.stdin, proxy.process.stdout):
        assert fcntl.fcntl(pipe.fileno(), fcntl.F_GETPIPE_SZ) == min(1 << 20, limit)


def test_failing_proxy_command_shows_its_error(ssh_home: SSHHome, connect: Connect) -> None:
    extra_config(
        ssh_home,
        "Host badproxy\n    HostName {host}\n    Port {port}\n{common}"
        "    ProxyCommand sh -c 'echo proxy says no >&2; exit 1'\n",
    )
    with pytest.raises(ConnectError, match="proxy says no"):
        connect("badproxy")


def test_proxy_jump_through_the_robot(ssh_home: SSHHome, connect: Connect) -> None:
    extra_config(
        ssh_home,
        "Host jumped\n    HostName {host}\n    Port {port}\n{common}    ProxyJump robot\n",
    )
    transport = connect("jumped")
    assert run(transport, "echo jumped") == (b"jumped\n", b"", 0)


def test_proxy_jump_chain_and_inline_spec(ssh_home: SSHHome, connect: Connect) -> None:
    sshd = ssh_home.sshd
    extra_config(
        ssh_home,
        "Host chained\n    HostName {host}\n    Port {port}\n{common}"
        f"    ProxyJump robot,{sshd.user}@{sshd.host}:{sshd.port}\n"
        "Host {host}\n{common}",
    )
    transport = connect("chained")
    assert run(transport, "echo chained")[0] == b"chained\n"


def test_proxy_jump_to_an_unreachable_target(ssh_home: SSHHome, connect: Connect) -> None:
    extra_config(
        ssh_home,
        f"Host nowhere\n    HostName {{host}}\n    Port {_closed_port()}\n{{common}}    ProxyJump robot\n",
    )
    with pytest.raises(ConnectError, match="through jump host robot"):
        connect("nowhere")


def test_proxy_jump_loop_is_a_config_error(ssh_home: SSHHome, connect: Connect) -> None:
    extra_config(ssh_home, "Host loop\n    ProxyJump loop\n")
    with pytest.raises(ConfigError, match="ProxyJump"):
        connect("loop")


# -- failures mapped at the boundary ---------------------------------------


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_connection_refused_names_address_and_port(ssh_home: SSHHome, connect: Connect) -> None:
    port = _closed_port()
    with pytest.raises(ConnectError, match=f"refused by 127.0.0.1 port {port}") as info:
        connect(port=port)
    assert isinstance(info.value.__cause__, ConnectionRefusedError)


def test_unknown_host_name_is_named(
    ssh_home: SSHHome, connect: Connect, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The resolver's answer, without depending on the network's DNS being quick.
    real = socket.getaddrinfo

    def getaddrinfo(host: str, *args: Any, **kwargs: Any) -> Any:
        if host == "no-such-host.invalid":
            raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")
        return real(host, *args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)
    extra_config(ssh_home, "Host ghost\n    HostName no-such-host.invalid\n")
    with pytest.raises(ConnectError, match="'no-such-host.invalid' \\(for ghost\\)"):
        connect("ghost")


def test_silent_server_times_out(ssh_home: SSHHome, connect: Connect) -> None:
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        port = listener.getsockname()[1]
        start = time.monotonic()
        with pytest.raises(ConnectError, match="timed out"):
            SSHTransport.connect("robot", port=port, connect_timeout=0.5)
        assert time.monotonic() - start < 3


def test_no_common_algorithm_is_named(
    ssh_home: SSHHome, connect: Connect, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The robot only has an ed25519 host key.
    monkeypatch.setattr(paramiko.Transport, "_preferred_keys", ("rsa-sha2-512",))
    with pytest.raises(ConnectError, match="no acceptable host key"):
        connect()


def test_stalled_link_is_detected_and_reported_lost(ssh_home: SSHHome, connect: Connect) -> None:
    pidfile = ssh_home.home / "proxy.pid"
    extra_config(
        ssh_home,
        "Host stalls\n    HostName {host}\n    Port {port}\n{common}"
        f"    ProxyCommand sh -c 'echo $$ > {pidfile}; "
        "exec ssh -F {sshd_config} -o BatchMode=yes -W %h:%p robot'\n",
    )
    transport = connect("stalls", keepalive=1.0)
    chan = transport.exec("cat")
    chan.send_all(b"x")
    assert chan.recv(1) == b"x"
    pid = int(pidfile.read_text())
    os.kill(pid, signal.SIGSTOP)
    try:
        assert not transport.is_alive(timeout=0.5)
        with pytest.raises(LinkLostError):
            chan.recv(1)
        with pytest.raises(LinkLostError):
            chan.exit_status(1)
    finally:
        # Closing the link has ended the proxy already (TERM, then KILL when stopped).
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)


# -- pure helpers ----------------------------------------------------------


def test_proxy_command_close_is_safe_from_two_threads_and_twice() -> None:
    """paramiko's transport thread and the caller's both close the proxy at the end of
    a session; a close racing another's flush raised ValueError out of a push that had
    succeeded."""
    import threading

    from fetchsync.link.ssh import _ProxyCommand

    proxy = _ProxyCommand("cat")
    real = proxy._stderr.close
    calls = []

    def close_racing() -> None:  # the other thread got there while this one flushed
        calls.append(1)
        real()
        raise ValueError("I/O operation on closed file")

    proxy._stderr.close = close_racing  # type: ignore[method-assign]
    errors: list[BaseException] = []

    def close() -> None:
        try:
            proxy.close()
        except BaseException as exc:  # noqa: BLE001 - what the test looks for
            errors.append(exc)

    threads = [threading.Thread(target=close) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    proxy.close()
    assert errors == []
    assert calls and proxy.closed
    assert proxy.process.stdin is not None and proxy.process.stdin.closed


def test_proxy_command_close_does_not_wait_for_it_yet_it_is_reaped_or_killed() -> None:
    """Closing returns at once, as ssh does (SIGHUP, no wait); the command is reaped in
    the background, and one that ignores SIGTERM is killed a second later."""
    from fetchsync.link.ssh import _ProxyCommand

    stubborn = _ProxyCommand("sh -c \"trap '' TERM; exec sleep 30\"")
    polite = _ProxyCommand("cat")
    time.sleep(0.2)  # the trap is set
    stubborn.close()
    polite.close()
    assert stubborn.closed and polite.closed
    assert stubborn.process.returncode is None  # still there: not waited for
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and (
        stubborn.process.returncode is None or polite.process.returncode is None
    ):
        time.sleep(0.05)
    assert stubborn.process.returncode == -signal.SIGKILL
    assert polite.process.returncode is not None


def test_parse_jump() -> None:
    assert parse_jump("bastion") == (None, "bastion", None)
    assert parse_jump("alice@bastion:2222") == ("alice", "bastion", 2222)
    assert parse_jump("ssh://bob@10.0.0.1:22") == ("bob", "10.0.0.1", 22)
    assert parse_jump("[fe80::1]:2200") == (None, "fe80::1", 2200)
    with pytest.raises(ConfigError):
        parse_jump("host:port")


def test_resolve_host_overrides_and_defaults(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("HOME", str(tmp_path))
    cfg = tmp_path / "cfg"
    cfg.write_text(
        "Host fetch7\n    HostName 10.0.0.7\n    Port 2222\n    User fetch\n"
        "    IdentityFile ~/.ssh/robot_%h\n    ProxyCommand none\n    HostKeyAlias fetch7\n"
        "    UserKnownHostsFile ~/kh1 ~/kh2\n"
    )
    config = load_ssh_config(cfg)
    s = resolve_host("fetch7", config=config)
    assert (s.hostname, s.port, s.user, s.proxy_command) == ("10.0.0.7", 2222, "fetch", None)
    assert s.identity_files == (f"{tmp_path}/.ssh/robot_10.0.0.7",)
    assert s.known_hosts_files == (f"{tmp_path}/kh1", f"{tmp_path}/kh2")
    assert s.known_hosts_name == "fetch7"
    o = resolve_host("fetch7", config=config, user="root", port=22)
    assert (o.user, o.port) == ("root", 22)
    plain = resolve_host("Other.Local", config=config)
    assert plain.known_hosts_name == "other.local" and plain.port == 22
    assert plain.known_hosts_files == (f"{tmp_path}/.ssh/known_hosts",)


def test_unreadable_config_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError):
        load_ssh_config(tmp_path / "missing")


def test_match_exec_in_the_ssh_config_runs_its_command(tmp_path: Path) -> None:
    """paramiko runs ``Match exec`` itself (with invoke): a config using it resolves.
    In a new interpreter: invoke reads its stdin, which pytest holds."""
    config = tmp_path / "config"
    config.write_text(
        'Match host robot exec "true"\n    HostName 10.1.2.3\n'
        'Match host robot exec "false"\n    User nobody-here\n'
        "Host robot\n    User fetch\n"
    )
    code = (
        "from fetchsync.link.ssh import load_ssh_config; "
        f"found = load_ssh_config({str(config)!r}).lookup('robot'); "
        "print(found['hostname'], found['user'])"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    assert out.stdout.split() == ["10.1.2.3", "fetch"]
