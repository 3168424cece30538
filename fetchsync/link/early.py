"""A direct connection's route opened before paramiko is imported.

A call that finds no connection master imports paramiko and parses the ssh config
before it can open its socket (~55-65 ms of CPU here), and only then waits for the
socket's first answer: the TCP connect's round trip and the robot's sshd forking
for the connection and sending its banner, or a ProxyCommand's own start and its
connect (the bench's link shaper: ~50 ms from its exec to the sshd's banner,
OpenSSH's ``ssh -v`` through it). Neither needs the other, so the route of the last
direct connection to this host (the config's HostName, Port and ProxyCommand as
paramiko resolved them) is remembered, and the next direct connection opens that
route at once, before importing paramiko: the banner waits for paramiko instead of
paramiko for the banner. The config is then resolved afresh as always, and the early
route is used only when it is the route the fresh resolution gives (else it is
closed unused and the fresh one opened, as before). Nothing else changes: the host
key is checked against known_hosts, the login is the same.

Remembered only where the route is a function of the config's text and of the names
given (the host, the user, the port, ``$HOME`` and the login's name): not for a
config with ``Match``, ``Include`` or ``CanonicalizeHostname`` (a command's answer, the
network, another file or the DNS can change its result; looked for in the lines as
paramiko reads them) nor ``ProxyJump`` (its hops need paramiko); not while the
config's stamps are younger than 2 s (a rewrite in the same clock tick keeps them).
A memory is used only while the config has the device, inode, size, mtime and ctime
it had when that route was resolved. It is a file in the user's cache directory
(``fetchsync/``, the user's and writable by no one else, checked without following a
symlink and used through its descriptor), written 0600 and read only if it is a
regular file of the user's that no one else can write: what it holds may run a
ProxyCommand, as ~/.ssh/config does.

Measured (bench/firststart.py --link wifi --rclcpp --rounds 7, this change against the
commit before it, interleaved, load 2.6-4.0, medians of each push's own spans): from
"no master" to the key exchange done 126 ms against 175; the socket's start to the key
exchange done 34 ms against 93; the interpreter's start to the first batch sent 601 ms
against 670. The first direct connection to a host (no memory yet) is as before.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import socket
import stat
import threading
import time
from typing import IO, TYPE_CHECKING, Any

from fetchsync.environ import inheritable
from fetchsync.trace import mark

if TYPE_CHECKING:
    import subprocess

SETTLED_NS = 2_000_000_000  # config stamps this old when read are past any write then
_DYNAMIC = frozenset({"match", "include", "canonicalizehostname"})
_KEYWORD = re.compile(r"(\w+)")
_MEMORY_MAX = 64 * 1024

Route = tuple[str, int, "str | None"]
"""(hostname, port, proxy command or None): where a direct connection's socket goes."""


def config_file(path: str | os.PathLike[str] | None = None) -> str:
    """The ssh config a connection reads: ``path``, or ``~/.ssh/config``."""
    return os.fspath(path) if path is not None else os.path.expanduser("~/.ssh/config")


def config_identity(path: str) -> list[int] | None:
    """The config's (device, inode, size, mtime, ctime), ``[]`` when it does not exist
    (no config: the route is the host's name itself), None when it cannot be looked at."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return []
    except OSError:
        return None
    if not stat.S_ISREG(st.st_mode):
        return None
    return [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns]


def _memory_name(host: str, user: str | None, port: int | None, config: str) -> str:
    names = [os.environ.get(k, "") for k in ("LOGNAME", "USER", "LNAME", "USERNAME")]
    key = json.dumps([host, user or "", port or 0, config, os.environ.get("HOME", ""), names])
    return "route-" + hashlib.sha256(key.encode()).hexdigest()[:24]


def _cache_fd() -> int | None:
    """fetchsync's cache directory, opened (made if missing): None unless it is the
    user's and no one else can write it, looked at without following a symlink."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    directory = os.path.join(base, "fetchsync")
    try:
        os.makedirs(directory, mode=0o700, exist_ok=True)
        fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
    except OSError:
        return None
    try:
        st = os.fstat(fd)
    except OSError:
        os.close(fd)
        return None
    if st.st_uid != os.getuid() or st.st_mode & 0o022:
        os.close(fd)
        return None
    return fd


def _read(name: str) -> dict[str, Any] | None:
    directory = _cache_fd()
    if directory is None:
        return None
    try:
        fd = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK, dir_fd=directory)
    except OSError:
        return None
    finally:
        os.close(directory)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o022:
            return None
        data = os.read(fd, _MEMORY_MAX)
    except OSError:
        return None
    finally:
        os.close(fd)
    try:
        memory = json.loads(data)
    except ValueError:
        return None
    return memory if isinstance(memory, dict) else None


def _route(memory: dict[str, Any]) -> Route | None:
    route = memory.get("route")
    if not (isinstance(route, list) and len(route) == 3):
        return None
    hostname, port, proxy = route
    if not isinstance(hostname, str) or not isinstance(port, int) or isinstance(port, bool):
        return None
    if proxy is not None and not isinstance(proxy, str):
        return None
    return hostname, port, proxy


def _dynamic(text: bytes) -> bool:
    """Whether a line of the config, as paramiko reads it, starts with a keyword whose
    route is not the text's alone (Match, Include, CanonicalizeHostname: a command's
    answer, another file, the DNS). paramiko reads the file in text mode (a CR ends a
    line) and strips any whitespace off a line (a form feed, a no-break space) before its
    keyword: the lines are split and stripped at least as finely here, in either
    encoding the file may be read in."""
    for encoding in ("utf-8", "latin-1"):
        for line in text.decode(encoding, "replace").splitlines():
            keyword = _KEYWORD.match(line.strip())
            if keyword is not None and keyword.group(1).lower() in _DYNAMIC:
                return True
    return False


class EarlyLink:
    """A route being opened: a TCP connect on a thread of its own, or a ProxyCommand
    started. :meth:`take_socket` / :meth:`take_process` hand it over; :meth:`close`
    ends what was not taken."""

    def __init__(self, route: Route, *, timeout: float) -> None:
        self.route = route
        self.process: subprocess.Popen[bytes] | None = None
        self.stderr: IO[bytes] | None = None
        self._sock: socket.socket | None = None
        self._error: OSError | None = None
        self._closed = False
        self._done = threading.Event()
        self._lock = threading.Lock()
        hostname, port, proxy = route
        if proxy is not None:
            import subprocess
            import tempfile

            self.stderr = tempfile.TemporaryFile()  # noqa: SIM115 - handed over or closed
            try:
                self.process = subprocess.Popen(
                    ["/bin/sh", "-c", "exec " + proxy],
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    stderr=self.stderr,
                    bufsize=0,
                    start_new_session=True,
                    env=inheritable(os.environ),  # as link/ssh.py's _ProxyCommand
                )
            except OSError as exc:
                self.stderr.close()
                self.stderr = None
                self._error = exc
            self._done.set()
        else:
            threading.Thread(
                target=self._connect, args=(hostname, port, timeout), daemon=True
            ).start()
        mark("early: route opened")

    def _connect(self, hostname: str, port: int, timeout: float) -> None:
        try:
            sock = socket.create_connection((hostname, port), timeout=timeout)
        except OSError as exc:
            self._error = exc
            self._done.set()
            return
        with self._lock:
            if self._closed:
                sock.close()
            else:
                self._sock = sock
        self._done.set()

    def matches(self, route: Route) -> bool:
        return self.route == route

    def take_socket(self, timeout: float) -> socket.socket:
        """The connected socket; the connect's OSError if it failed, TimeoutError if it
        is not connected within ``timeout`` (the caller reports them as its own connect's:
        one attempt, not a second after the early one's timeout)."""
        self._done.wait(timeout)
        with self._lock:
            sock, self._sock = self._sock, None
            self._closed = True
        if sock is not None:
            return sock
        if self._error is not None:
            raise self._error
        raise TimeoutError("timed out")

    def take_process(self) -> tuple[subprocess.Popen[bytes], IO[bytes]] | None:
        """The started ProxyCommand and the file of its stderr, None if it could not start."""
        process, stderr = self.process, self.stderr
        self.process = self.stderr = None
        self._closed = True
        if process is None or stderr is None:
            return None
        return process, stderr

    def close(self) -> None:
        """End what was not taken: the socket (once connected), the ProxyCommand."""
        with self._lock:
            self._closed = True
            sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()
        process, stderr = self.process, self.stderr
        self.process = self.stderr = None
        if process is not None:
            for pipe in (process.stdin, process.stdout):
                if pipe is not None:
                    try:
                        pipe.close()
                    except OSError:
                        pass
            try:
                process.terminate()
            except OSError:
                pass
            threading.Thread(target=_reap, args=(process,), daemon=True).start()
        if stderr is not None:
            stderr.close()


def _reap(process: subprocess.Popen[bytes]) -> None:
    import subprocess

    try:
        process.wait(1.0)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def start(
    host: str,
    *,
    user: str | None = None,
    port: int | None = None,
    config_path: str | os.PathLike[str] | None = None,
    timeout: float = 10.0,
) -> EarlyLink | None:
    """Open the route remembered for ``host`` if the config is the one it was resolved
    from; None otherwise (no memory, another config, no private cache directory)."""
    config = config_file(config_path)
    memory = _read(_memory_name(host, user, port, config))
    if memory is None:
        return None
    identity = config_identity(config)
    if identity is None or memory.get("config") != identity:
        return None
    route = _route(memory)
    if route is None:
        return None
    return EarlyLink(route, timeout=timeout)


def remember(
    host: str,
    route: Route,
    *,
    user: str | None = None,
    port: int | None = None,
    config_path: str | os.PathLike[str] | None = None,
    identity: list[int] | None,
    known: EarlyLink | None = None,
) -> None:
    """Remember that the config with ``identity`` (taken before it was parsed) resolves
    ``host`` to ``route``, when that is all the route depends on (see the module's
    docstring). Nothing is written when ``known`` already went that way from it."""
    if identity is None:
        return
    config = config_file(config_path)
    if identity:
        if config_identity(config) != identity:
            return  # changed while it was parsed: which text gave the route is not known
        if time.time_ns() - max(identity[3], identity[4]) < SETTLED_NS:
            return
        try:
            with open(config, "rb") as fh:
                text = fh.read()
        except OSError:
            return
        if _dynamic(text) or config_identity(config) != identity:
            return
    if known is not None and known.matches(route):
        return  # started from this very memory: it says this already
    directory = _cache_fd()
    if directory is None:
        return
    name = _memory_name(host, user, port, config)
    data = json.dumps({"config": identity, "route": list(route)}).encode()
    tmp = f"{name}.{os.getpid()}.tmp"
    try:
        fd = os.open(
            tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600, dir_fd=directory
        )
        try:
            os.write(fd, data)
        finally:
            os.close(fd)
        os.replace(tmp, name, src_dir_fd=directory, dst_dir_fd=directory)
    except OSError:
        try:
            os.unlink(tmp, dir_fd=directory)
        except OSError:
            pass
    finally:
        os.close(directory)
