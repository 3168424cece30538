"""The connection to a robot, begun before paramiko is imported.

Importing paramiko and cryptography takes ~40 ms of every call that connects
over SSH. Meanwhile the robot's name can resolve (an mDNS ``NAME.local`` takes
tens of ms), TCP can connect, the robot's sshd can start its process and send
its banner, and a ProxyCommand can start (the benchmark's, a Python script,
takes ~28 ms to reach the banner; sshd itself ~6 ms).

What needs the ssh config (HostName, Port, ProxyCommand) comes from a note of
what it said for this host the last time: :func:`remember` writes it once a
connection succeeded, in the cache directory, keyed by the config file's
identity, the host and the user and port asked for, and the home directory and
login name the config's tokens expand to. A config with ``Match`` blocks or
hostname canonicalisation is never noted (its answer depends on more than the
file), nor is a host reached through ProxyJump (its hop needs paramiko).
Once paramiko has read the config, :meth:`Early.matches` compares; the caller
uses the early connection only if it agrees, and :meth:`Early.close` discards
it otherwise. A note is used only if it is the user's own and nobody else can
write it, the bar ssh sets for its config, since a ProxyCommand in it runs
before the config is read.
"""

from __future__ import annotations

import getpass
import hashlib
import json
import os
import socket
import stat
import subprocess
import tempfile
import threading
from typing import IO, Any

from fetchsync.protocol.loader import cache_dir
from fetchsync.protocol.wire import widen_pipe

_NOT_NOTED = ("match", "canonicalizehostname")


def spawn_proxy(command_line: str) -> tuple[subprocess.Popen[bytes], IO[bytes]]:
    """Start ``command_line`` as ssh starts a ProxyCommand (``/bin/sh -c "exec ..."``),
    in a session of its own, with its stderr kept in a temporary file. OSError if
    it cannot start."""
    errors: IO[bytes] = tempfile.TemporaryFile()  # noqa: SIM115 - the caller closes it
    try:
        process = subprocess.Popen(
            ["/bin/sh", "-c", "exec " + command_line],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=errors,
            bufsize=0,
            start_new_session=True,
        )
    except OSError:
        errors.close()
        raise
    for pipe in (process.stdin, process.stdout):
        if pipe is not None:
            widen_pipe(pipe.fileno())
    return process, errors


class Early:
    """A TCP connection under way, or a ProxyCommand started, for noted settings."""

    def __init__(self, hostname: str, port: int, proxy_command: str | None, *,
                 timeout: float) -> None:
        self.hostname, self.port, self.proxy_command = hostname, port, proxy_command
        self.process: subprocess.Popen[bytes] | None = None
        self.errors: IO[bytes] | None = None
        self._sock: socket.socket | None = None
        self._failure: OSError | None = None
        self._done = threading.Event()
        self._lock = threading.Lock()
        self._closed = False
        if proxy_command is not None:
            try:
                self.process, self.errors = spawn_proxy(proxy_command)
            except OSError:
                pass  # the usual path starts it again and says why it cannot
            self._done.set()
        else:
            threading.Thread(target=self._connect, args=(timeout,), name="fetchsync-preconnect",
                             daemon=True).start()

    def _connect(self, timeout: float) -> None:
        try:
            sock = socket.create_connection((self.hostname, self.port), timeout=timeout)
        except OSError as exc:
            self._failure = exc
            sock = None
        with self._lock:
            if self._closed and sock is not None:
                sock.close()
            else:
                self._sock = sock
        self._done.set()

    def matches(self, hostname: str, port: int, proxy_command: str | None) -> bool:
        """Whether this is a connection to what the config says now."""
        return (hostname, port, proxy_command) == (self.hostname, self.port, self.proxy_command)

    def take_socket(self, timeout: float) -> socket.socket | None:
        """The connected socket, now the caller's; raises the connect's OSError. None if
        it is still connecting after ``timeout`` (the caller connects again)."""
        if not self._done.wait(timeout):
            return None
        if self._failure is not None:
            raise self._failure
        with self._lock:
            sock, self._sock = self._sock, None
        return sock

    def take_process(self) -> tuple[subprocess.Popen[bytes], IO[bytes]] | None:
        """The started ProxyCommand and its stderr file, now the caller's; None if it
        did not start."""
        if self.process is None or self.errors is None:
            return None
        taken = (self.process, self.errors)
        self.process = self.errors = None
        return taken

    def close(self) -> None:
        """Discard what was not taken."""
        with self._lock:
            self._closed = True
            sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()
        if self.process is not None:
            for pipe in (self.process.stdin, self.process.stdout):
                if pipe is not None:
                    pipe.close()
            if self.process.poll() is None:
                self.process.terminate()
            self.process = None
        if self.errors is not None:
            self.errors.close()
            self.errors = None


def _config_path(config_path: str | os.PathLike[str] | None) -> str:
    return os.fspath(config_path) if config_path is not None else os.path.expanduser("~/.ssh/config")


def _note(alias: str, user: str | None, port: int | None, config_path: str) -> str:
    """Where the settings for these inputs are noted (the config file's identity included:
    an edited config has other notes)."""
    try:
        st = os.stat(config_path)
        identity: Any = [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns]
    except OSError:
        identity = None
    try:
        login = getpass.getuser()
    except (KeyError, OSError):
        login = ""
    key = json.dumps([alias, user, port, config_path, identity, os.path.expanduser("~"), login])
    return os.path.join(cache_dir(), "connect-" + hashlib.sha256(key.encode()).hexdigest()[:32])


def begin(alias: str, *, user: str | None = None, port: int | None = None,
          config_path: str | os.PathLike[str] | None = None, timeout: float = 10.0) -> Early | None:
    """Start connecting as the note for these inputs says, if there is one."""
    path = _note(alias, user, port, _config_path(config_path))
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:
        return None
    try:
        st = os.fstat(fd)
        if st.st_uid != os.getuid() or st.st_mode & (stat.S_IWGRP | stat.S_IWOTH) \
                or not stat.S_ISREG(st.st_mode):
            return None
        with os.fdopen(fd, "rb") as fh:
            fd = -1
            noted = json.loads(fh.read(8192))
    except (OSError, ValueError):
        return None
    finally:
        if fd >= 0:
            os.close(fd)
    if not isinstance(noted, dict):
        return None
    hostname, nport, proxy = noted.get("hostname"), noted.get("port"), noted.get("proxy_command")
    if not isinstance(hostname, str) or type(nport) is not int or not (proxy is None or isinstance(proxy, str)):
        return None
    return Early(hostname, nport, proxy, timeout=timeout)


def remember(alias: str, *, user: str | None, port: int | None,
             config_path: str | os.PathLike[str] | None,
             hostname: str, resolved_port: int, proxy_command: str | None) -> None:
    """Note what the config said for these inputs, for the next :func:`begin`; only a
    cache, so a failure passes."""
    config = _config_path(config_path)
    path = _note(alias, user, port, config)
    text = json.dumps({"hostname": hostname, "port": resolved_port, "proxy_command": proxy_command},
                      sort_keys=True)
    try:
        with open(path, encoding="utf-8") as fh:
            if fh.read() == text:
                return
    except (OSError, UnicodeDecodeError):
        pass
    try:
        with open(config, "rb") as fh:
            lines = fh.read().lower().splitlines()
    except FileNotFoundError:
        lines = []
    except OSError:
        return
    if any(line.strip().startswith(word.encode()) for line in lines for word in _NOT_NOTED):
        return
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path}.{os.getpid()}.tmp"
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except OSError:
        pass
