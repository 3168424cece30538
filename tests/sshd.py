"""A real OpenSSH ``sshd`` on 127.0.0.1 that plays the robot in tests.

Everything it needs lives in one work directory: generated ed25519 host and
client keys, a private ``sshd_config`` (started with ``-f``, so the system's
configuration is never read), the authorized keys, a pid file and the log.
The robot is this machine: a login lands in the real home of the login user
(root on CI and the dev machines, else the current user).

``running_sshd()`` starts one and yields an :class:`SSHD` that describes how to
reach it; ``make_ssh_home()`` lays out a laptop-side HOME whose ``~/.ssh``
reaches it as ``robot`` (:class:`SSHHome`).

OpenSSH's ``ssh`` finds ``~/.ssh`` through the password database, not
``$HOME``: give it ``-F <config>`` (see :meth:`SSHD.ssh_argv`). paramiko and the
rest of Python follow ``$HOME``.
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import hashlib
import os
import pwd
import re
import shutil
import socket
import subprocess
import time
from pathlib import Path
from typing import Iterator

__all__ = [
    "HOST_ALIAS",
    "SSHD",
    "SSHDStartError",
    "SSHHome",
    "find_sshd",
    "fingerprint",
    "make_ssh_home",
    "running_sshd",
    "write_client_config",
]

HOST_ALIAS = "robot"
_LOOPBACK = "127.0.0.1"
_PORT_TRIES = 3


class SSHDStartError(RuntimeError):
    """sshd did not come up; the message carries its log."""


@dataclasses.dataclass(frozen=True)
class SSHD:
    """How to reach the running test sshd (the robot)."""

    host: str
    port: int
    user: str
    client_key: Path
    """Private ed25519 key (no passphrase) that the server accepts; ``.pub`` beside it."""
    host_key_pub: str
    """The server's public host key as one OpenSSH line: ``ssh-ed25519 AAAA...``."""
    host_key_fingerprint: str
    """``SHA256:...`` as ``ssh-keygen -l`` and ``ssh`` print it."""
    known_hosts: Path
    """known_hosts with the host key for ``[127.0.0.1]:PORT``."""
    ssh_config: Path
    """Client configuration with ``Host robot`` (HostName, Port, User, IdentityFile, ...)."""
    log: Path
    """sshd's own log (``-e``, LogLevel VERBOSE)."""
    workdir: Path

    @property
    def alias(self) -> str:
        return HOST_ALIAS

    @property
    def known_hosts_name(self) -> str:
        """The host name known_hosts and paramiko's HostKeys use for this server."""
        return f"[{self.host}]:{self.port}"

    def ssh_argv(self, *command: str, config: Path | None = None) -> list[str]:
        """argv for the OpenSSH client running ``command`` on the robot, never prompting."""
        cfg = self.ssh_config if config is None else config
        return ["ssh", "-F", str(cfg), "-o", "BatchMode=yes", HOST_ALIAS, *command]

    def log_text(self) -> str:
        return self.log.read_text(errors="replace")


@dataclasses.dataclass(frozen=True)
class SSHHome:
    """A laptop-side HOME whose ``~/.ssh`` reaches the robot as ``robot``."""

    sshd: SSHD
    home: Path
    ssh_dir: Path
    config: Path
    """``~/.ssh/config``; pass it to OpenSSH as ``-F`` (ssh ignores ``$HOME``)."""
    known_hosts: Path
    """``~/.ssh/known_hosts`` with the robot's key; empty it to test an unknown host."""
    identity: Path
    """``~/.ssh/id_ed25519``; ``.pub`` beside it."""

    def ssh_argv(self, *command: str) -> list[str]:
        """argv for the OpenSSH client with this home's config, never prompting."""
        return self.sshd.ssh_argv(*command, config=self.config)


def make_ssh_home(home: Path, *, sshd: SSHD, port: int | None = None) -> SSHHome:
    """Create ``home/.ssh`` with a config, known_hosts and key copies for ``sshd``.

    ``port`` reaches the robot on another port of 127.0.0.1 (a FaultProxy in
    front of it); known_hosts then holds the host key under that port.
    """
    ssh_dir = home / ".ssh"
    ssh_dir.mkdir(parents=True, mode=0o700)
    identity = ssh_dir / "id_ed25519"
    shutil.copyfile(sshd.client_key, identity)
    identity.chmod(0o600)
    shutil.copyfile(sshd.client_key.with_suffix(".pub"), ssh_dir / "id_ed25519.pub")
    known_hosts = ssh_dir / "known_hosts"
    port = sshd.port if port is None else port
    known_hosts.write_text(f"[{sshd.host}]:{port} {sshd.host_key_pub}\n")
    config = write_client_config(
        ssh_dir / "config", sshd=sshd, identity=identity, known_hosts=known_hosts, port=port
    )
    return SSHHome(
        sshd=sshd,
        home=home,
        ssh_dir=ssh_dir,
        config=config,
        known_hosts=known_hosts,
        identity=identity,
    )


def find_sshd() -> str | None:
    """Absolute path of sshd (it refuses to run from a relative one), or None."""
    path = os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/usr/local/sbin", "/sbin"])
    found = shutil.which("sshd", path=path)
    return os.path.abspath(found) if found else None


def fingerprint(public_key_line: str) -> str:
    """The ``SHA256:`` fingerprint of an OpenSSH public key line."""
    blob = base64.b64decode(public_key_line.split()[1])
    digest = base64.b64encode(hashlib.sha256(blob).digest()).decode("ascii")
    return "SHA256:" + digest.rstrip("=")


def write_client_config(
    path: Path, *, sshd: SSHD, identity: Path, known_hosts: Path, port: int | None = None
) -> Path:
    """Write an OpenSSH client config with ``Host robot`` pointing at ``sshd``.

    Paths are absolute: OpenSSH would expand ``~`` to the passwd home, paramiko
    to ``$HOME``, and the two differ under the ``ssh_home`` fixture.
    """
    path.write_text(
        f"Host {HOST_ALIAS}\n"
        f"    HostName {sshd.host}\n"
        f"    Port {sshd.port if port is None else port}\n"
        f"    User {sshd.user}\n"
        f"    IdentityFile {identity}\n"
        f"    IdentitiesOnly yes\n"
        f"    UserKnownHostsFile {known_hosts}\n"
        f"    GlobalKnownHostsFile /dev/null\n"
        f"    StrictHostKeyChecking yes\n"
        f"    UpdateHostKeys no\n"
        f"    ConnectTimeout 10\n"
    )
    path.chmod(0o600)
    return path


def _login_user() -> str:
    return "root" if os.geteuid() == 0 else pwd.getpwuid(os.getuid()).pw_name


def _keygen(path: Path, comment: str) -> None:
    subprocess.run(
        ["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", comment, "-f", str(path)],
        check=True,
        stdin=subprocess.DEVNULL,
        capture_output=True,
    )


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((_LOOPBACK, 0))
        return int(s.getsockname()[1])


def _openssh_version(sshd_path: str) -> tuple[int, int]:
    # sshd has no version flag; an unknown one makes it print usage with the version.
    out = subprocess.run(
        [sshd_path, "-V"], check=False, capture_output=True, text=True, stdin=subprocess.DEVNULL
    )
    m = re.search(r"OpenSSH_(\d+)\.(\d+)", out.stdout + out.stderr)
    return (int(m.group(1)), int(m.group(2))) if m else (0, 0)


def _sshd_config(workdir: Path, port: int, version: tuple[int, int]) -> str:
    as_root = os.geteuid() == 0
    lines = [
        f"ListenAddress {_LOOPBACK}",
        f"Port {port}",
        f"HostKey {workdir / 'host_key'}",
        f"PidFile {workdir / 'sshd.pid'}",
        # Our file first; created accounts (create-account tests) log in with their own.
        f"AuthorizedKeysFile {workdir / 'authorized_keys'} .ssh/authorized_keys",
        # The work dir is under /tmp, which StrictModes would reject.
        "StrictModes no",
        "PermitRootLogin yes",
        "PubkeyAuthentication yes",
        "PasswordAuthentication yes",
        "KbdInteractiveAuthentication yes",
        "PermitEmptyPasswords no",
        # PAM checks passwords of real accounts; only root can read /etc/shadow.
        f"UsePAM {'yes' if as_root else 'no'}",
        "PrintMotd no",
        "PrintLastLog no",
        # Reconnect and benchmark tests open many connections and channels at once.
        "MaxStartups 64:30:128",
        "MaxSessions 64",
        "LogLevel VERBOSE",
        "Subsystem sftp internal-sftp",
    ]
    if version >= (9, 8):
        # Failed logins and cut connections are what the tests do on purpose;
        # penalising 127.0.0.1 for them would make later tests flaky.
        lines.append("PerSourcePenalties no")
    return "\n".join(lines) + "\n"


def _read_banner(port: int, timeout: float) -> bytes:
    with socket.create_connection((_LOOPBACK, port), timeout=timeout) as s:
        data = b""
        while b"\n" not in data and len(data) < 512:
            chunk = s.recv(256)
            if not chunk:
                break
            data += chunk
        return data


def _wait_ready(proc: subprocess.Popen[bytes], port: int, log: Path, deadline: float) -> None:
    while True:
        if proc.poll() is not None:
            raise SSHDStartError(
                f"sshd exited with {proc.returncode}:\n{log.read_text(errors='replace')}"
            )
        try:
            if _read_banner(port, timeout=1.0).startswith(b"SSH-2.0-"):
                return
        except OSError:
            pass
        if time.monotonic() > deadline:
            raise SSHDStartError(
                f"sshd not ready on {_LOOPBACK}:{port} in time:\n{log.read_text(errors='replace')}"
            )
        time.sleep(0.05)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    # Only the listener is ours to stop: per-connection children setsid() and
    # end when their clients disconnect.
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)


def _start(
    sshd_path: str, workdir: Path, version: tuple[int, int], timeout: float
) -> tuple[subprocess.Popen[bytes], int]:
    config = workdir / "sshd_config"
    log = workdir / "sshd.log"
    for attempt in range(_PORT_TRIES):
        port = _free_port()
        config.write_text(_sshd_config(workdir, port, version))
        with open(log, "ab") as log_fd:
            proc = subprocess.Popen(
                [sshd_path, "-D", "-e", "-f", str(config)],
                stdin=subprocess.DEVNULL,
                stdout=log_fd,
                stderr=log_fd,
                start_new_session=True,
            )
        try:
            _wait_ready(proc, port, log, time.monotonic() + timeout)
            return proc, port
        except SSHDStartError:
            _stop(proc)
            # Someone took the port between our probe and sshd's bind: try another.
            if attempt + 1 < _PORT_TRIES and "Address already in use" in log.read_text(
                errors="replace"
            ):
                continue
            raise
    raise AssertionError("unreachable")


@contextlib.contextmanager
def running_sshd(workdir: Path, *, timeout: float = 10.0) -> Iterator[SSHD]:
    """Start sshd with everything under ``workdir``; stop it on exit."""
    sshd_path = find_sshd()
    if sshd_path is None:
        raise SSHDStartError("sshd not found; install openssh-server")
    workdir = workdir.resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    if os.geteuid() == 0:
        # The privilege separation directory; Debian creates it only when the
        # ssh service starts, and nothing starts services in a container.
        os.makedirs("/run/sshd", mode=0o755, exist_ok=True)

    host_key = workdir / "host_key"
    client_key = workdir / "client_key"
    _keygen(host_key, "fetchsync-test-host")
    _keygen(client_key, "fetchsync-test-client")
    shutil.copyfile(client_key.with_suffix(".pub"), workdir / "authorized_keys")

    proc, port = _start(sshd_path, workdir, _openssh_version(sshd_path), timeout)
    try:
        key_type, key_b64 = host_key.with_suffix(".pub").read_text().split()[:2]
        host_key_pub = f"{key_type} {key_b64}"
        known_hosts = workdir / "known_hosts"
        known_hosts.write_text(f"[{_LOOPBACK}]:{port} {host_key_pub}\n")
        server = SSHD(
            host=_LOOPBACK,
            port=port,
            user=_login_user(),
            client_key=client_key,
            host_key_pub=host_key_pub,
            host_key_fingerprint=fingerprint(host_key_pub),
            known_hosts=known_hosts,
            ssh_config=workdir / "ssh_config",
            log=workdir / "sshd.log",
            workdir=workdir,
        )
        write_client_config(
            server.ssh_config, sshd=server, identity=client_key, known_hosts=known_hosts
        )
        yield server
    finally:
        _stop(proc)
