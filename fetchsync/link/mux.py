"""Keeping the SSH connection open between calls, as OpenSSH's ControlPersist does.

The first one-shot verb that reaches a robot over SSH leaves a *connection
master* behind: a background process that holds the authenticated SSH
connection and serves later calls over an owner-only unix socket. A later
``fetchsync push`` then pays no SSH handshake (several round trips and a key
exchange: on a Wi-Fi link, the larger part of a small push's time). The master
exits after ``FETCHSYNC_PERSIST`` idle seconds (default 600; 0 disables it) or
as soon as its link dies. While a master connects it holds a lock beside the
socket (``mux-*.sock.starting``): a call that comes meanwhile waits for it
rather than connecting on its own, and a second master leaves it to the first.
The master stamps the lock (its mtime) at each step of its start (its Python up,
paramiko imported, the socket made, the key exchange, the host key, the login):
a call waits only while those steps come, so a master stuck in its handshake (a
robot whose TCP accepts but whose sshd never speaks) costs a call at most
``MASTER_STALL`` seconds, and none once its last step is older than that.

The master also keeps one *spare* robot endpoint started: the endpoint's
command (the loader line a push runs) is run ahead of the call and
left waiting right after the endpoint's hello (or its request for the loader or
the endpoint's archive), so the next push does not wait for sshd's session start,
the robot's Python start and the loader (0.4-0.5 s of a one-edit push's 0.7 s
on the shaped Wi-Fi link). The spare only starts: an endpoint opens no
workspace and reads nothing before the client's own requests, so it checks
everything at open as a fresh one does, and the loader verifies its cache as
for any start. A spare that has ended meanwhile (it said more than its hello,
its channel closed, it exited) is noticed when a call takes it, closed, and
replaced by a fresh start in that same call; the next spare is started once
the call that took one has ended (or a few seconds into it), so its start does
not compete with that call for the robot's CPU and the link.

Socket protocol (one connection per remote command): the client sends one
JSON line ``{"exec": COMMAND}`` and then the command's stdin as raw bytes
(half-close = EOF); the master answers with frames ``u8 kind | u32 len |
data``: 1 stdout, 2 stderr, 3 exit status (i32), 4 error message.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import select
import socket
import stat
import struct
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from fetchsync.environ import inheritable
from fetchsync.errors import ConnectError, LinkLostError
from fetchsync.link.transport import Capabilities
from fetchsync.places import MAX_SOCKET_PATH
from fetchsync.places import runtime_path as _runtime_path
from fetchsync.trace import mark

if TYPE_CHECKING:
    from fetchsync.link.ssh import SSHTransport

log = logging.getLogger(__name__)

K_STDOUT, K_STDERR, K_EXIT, K_ERROR = 1, 2, 3, 4
_HDR = struct.Struct(">BI")
DEFAULT_PERSIST = 600.0
CHECK_TIMEOUT = 5.0  # seconds a master may take to re-check the robot's host key
IDLE_CHECK = 0.5  # seconds between looks at the link and the idle time while no call comes
REFILL_AFTER = 2.0  # seconds into a call that took the spare when the next one starts anyway
SPARE_WAIT = (
    5.0  # seconds a call waits for a spare endpoint still starting before it starts its own
)


def persist_seconds() -> float:
    try:
        return float(os.environ.get("FETCHSYNC_PERSIST", DEFAULT_PERSIST))
    except ValueError:
        return DEFAULT_PERSIST


def runtime_dir(*, short: bool = False) -> Path:
    """The directory of our local sockets (connection masters, the watch agent's control).

    ``$XDG_RUNTIME_DIR/fetchsync``, or with ``short`` or without that variable
    ``fetchsync-UID`` in the temporary directory (``$TMPDIR``, else ``/tmp``): a
    place other users can write, so the directory is checked without following a
    symlink (``lstat``): a directory of ours, mode 0700. Anything else there
    (another user's directory, a symlink) is refused with a ConnectError naming
    it: only the master and the agent need sockets, and a call goes direct
    without them.
    """
    return private_dir(_runtime_path(short=short))


def private_dir(path: Path) -> Path:
    """``path`` as a directory only we can use: made 0700 if missing, else checked with lstat."""
    try:
        os.mkdir(path, 0o700)
    except FileExistsError:
        pass
    except OSError as exc:
        raise ConnectError(f"cannot make {path} for fetchsync's sockets: {exc.strerror}") from exc
    try:
        st = os.lstat(path)
    except OSError as exc:
        raise ConnectError(f"cannot use {path} for fetchsync's sockets: {exc.strerror}") from exc
    if stat.S_ISLNK(st.st_mode):
        why = "it is a symlink"
    elif not stat.S_ISDIR(st.st_mode):
        why = "it is not a directory"
    elif st.st_uid != os.getuid():
        why = f"it belongs to uid {st.st_uid}"
    elif stat.S_IMODE(st.st_mode) & 0o077:
        why = f"its mode is {stat.S_IMODE(st.st_mode):04o}, not 0700"
    else:
        return path
    raise ConnectError(f"{path} is not private to you ({why}); refusing to use it for sockets")


def peer_uid(sock: socket.socket) -> int:
    """The uid of the process at the other end of a unix socket (SO_PEERCRED)."""
    creds = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    return int(struct.unpack("3i", creds)[1])


def socket_path(host: str, user: str | None) -> Path:
    """Where the master for this robot listens; ConnectError if no private place is usable."""
    key = f"{user or ''}@{host}\0{os.environ.get('HOME', '')}"
    name = f"mux-{hashlib.sha256(key.encode()).hexdigest()[:20]}.sock"
    path = _runtime_path(short=False) / name
    if len(os.fsencode(path)) > MAX_SOCKET_PATH:
        path = _runtime_path(short=True) / name
    return private_dir(path.parent) / name


def _connect(path: Path) -> socket.socket:
    """A connection to the master at ``path``; OSError if none answers there or it is not ours."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.connect(str(path))
        uid = peer_uid(sock)
        if uid != os.getuid():
            raise PermissionError(f"the process listening on {path} is uid {uid}, not us")
    except BaseException:
        sock.close()
        raise
    return sock


MASTER_WAIT = 5.0  # seconds a call waits for a master that is connecting before going direct
# seconds without a step of a connecting master after which calls stop waiting for it: a
# step is at most the master's Python start or paramiko's import (~0.3 s of CPU quiet) or
# one round trip of its handshake; a master stuck in its handshake holds no call longer
MASTER_STALL = 2.0


def _lock_path(path: Path) -> Path:
    return path.with_name(path.name + ".starting")


def _starting(path: Path) -> int | None:
    """Hold the lock that says a master for ``path`` is connecting: its descriptor, to
    close once the master listens (or never: its exit releases it); None if another
    master holds it (that one serves) or the lock cannot be made (we start anyway: -1)."""
    import fcntl

    try:
        fd = os.open(_lock_path(path), os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    except OSError:
        return -1
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    stamp(fd)
    return fd


def stamp(fd: int) -> None:
    """Say, on the connecting lock ``fd`` (its mtime), that the master made a step."""
    if fd >= 0:
        try:
            os.utime(fd)
        except OSError:
            pass


def wait_while_starting(path: Path, timeout: float = MASTER_WAIT) -> None:
    """Return once no master for ``path`` is connecting, once the one connecting has
    made no step for ``MASTER_STALL`` seconds, or after ``timeout`` seconds.

    A call that comes while the master left by the call before it is still connecting
    (the push right after a first one: the master's Python, paramiko and handshake take
    ~0.5-1 s) waits for it instead of connecting on its own: the master's handshake
    started first, so it ends first, and no second master is started beside it. A
    master stuck in its handshake (the robot's TCP accepts, its sshd never answers)
    stamps no step: the call goes direct (it leaves no second master: the stuck one
    still holds the lock).
    """
    import fcntl

    try:
        fd = os.open(_lock_path(path), os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:
        return  # no master was ever started here
    try:
        deadline = time.monotonic() + timeout
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
                return
            except BlockingIOError:
                if time.monotonic() > deadline:
                    return
                try:
                    still = time.time() - os.fstat(fd).st_mtime
                except OSError:
                    return
                if still > MASTER_STALL:
                    mark(f"session: the master connecting made no step for {still:.1f} s")
                    log.info("the connection master connecting made no step for %.1f s", still)
                    return
                time.sleep(0.01)
            except OSError:
                return
    finally:
        os.close(fd)


# --------------------------------------------------------------------------- client side
class MuxChannel:
    """A remote command run by the master; implements transport.Channel."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self._buf = bytearray()
        self._out = bytearray()
        self._err = bytearray()
        self._status: int | None = None
        self._eof = False

    def _pump(self) -> bool:
        """Read one more frame; False at end of stream."""
        while (
            len(self._buf) < _HDR.size
            or len(self._buf) < _HDR.size + _HDR.unpack_from(self._buf)[1]
        ):
            try:
                chunk = self.sock.recv(1 << 16)
            except OSError as exc:
                raise LinkLostError("the connection master went away") from exc
            if not chunk:
                self._eof = True
                return False
            self._buf += chunk
        kind, n = _HDR.unpack_from(self._buf)
        data = bytes(self._buf[_HDR.size : _HDR.size + n])
        del self._buf[: _HDR.size + n]
        if kind == K_STDOUT:
            self._out += data
        elif kind == K_STDERR:
            self._err += data
        elif kind == K_EXIT:
            self._status = struct.unpack(">i", data)[0]
        elif kind == K_ERROR:
            raise LinkLostError(f"connection master: {data.decode('utf-8', 'replace')}")
        return True

    def send_all(self, data: bytes | memoryview) -> None:
        try:
            self.sock.sendall(data)
        except OSError as exc:
            raise LinkLostError("the connection master went away") from exc

    def recv(self, n: int) -> bytes:
        while not self._out and not self._eof and self._status is None:
            self._pump()
        out = bytes(self._out[:n])
        del self._out[:n]
        return out

    def ready(self) -> bool:
        if self._out or self._eof or self._status is not None:
            return True
        try:
            return bool(select.select([self.sock], [], [], 0)[0])  # a frame, maybe of stderr
        except (ValueError, OSError):
            return True

    def recv_stderr(self, n: int) -> bytes:
        while not self._eof and self._status is None:
            self._pump()
        out = bytes(self._err[:n])
        del self._err[:n]
        return out

    def shutdown_write(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_WR)
        except OSError:
            pass

    def exit_status(self, timeout: float | None = None) -> int | None:
        self.sock.settimeout(timeout)
        try:
            while self._status is None and not self._eof:
                self._pump()
        except (TimeoutError, socket.timeout):
            return None
        finally:
            self.sock.settimeout(None)
        return self._status

    def close(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)  # wakes a thread blocked reading it
        except OSError:
            pass
        self.sock.close()


class MuxTransport:
    """A transport whose commands run through a connection master's socket."""

    capabilities = Capabilities()

    def __init__(self, path: Path, name: str) -> None:
        self.path = path
        self.name = name

    @classmethod
    def attach(cls, path: Path, name: str) -> MuxTransport | None:
        """The master at ``path`` if one answers and still trusts the robot, else None.

        The master checks its link and the robot's host key against known_hosts as
        they are now (:meth:`Master.check`); a master that refuses drops itself, and
        the caller connects afresh, which refuses a changed key as usual. A stale
        socket is removed.
        """
        if not path.exists():
            return None
        try:
            sock = _connect(path)
        except PermissionError as exc:
            log.warning("fetchsync: not using the connection master: %s", exc)
            return None
        except OSError:
            try:
                path.unlink()
            except OSError:
                pass
            return None
        try:
            sock.settimeout(CHECK_TIMEOUT)
            sock.sendall(b'{"check": true}\n')
            sock.shutdown(socket.SHUT_WR)
            channel = MuxChannel(sock)
            status = channel.exit_status(timeout=CHECK_TIMEOUT)
        except (OSError, LinkLostError) as exc:
            log.info("the connection master for %s refused: %s", name, exc)
            return None
        finally:
            sock.close()
        if status != 0:
            return None
        return cls(path, name)

    def exec(
        self, command: str, *, env: dict[str, str] | None = None, pty: bool = False
    ) -> MuxChannel:
        if env or pty:
            raise ConnectError("the connection master runs plain commands only")
        try:
            sock = _connect(self.path)
        except OSError as exc:
            raise ConnectError(f"the connection master for {self.name} did not answer") from exc
        try:
            sock.sendall(json.dumps({"exec": command}).encode() + b"\n")
        except OSError as exc:
            sock.close()
            raise ConnectError(f"the connection master for {self.name} did not answer") from exc
        return MuxChannel(sock)

    def is_alive(self, timeout: float | None = None) -> bool:
        return True  # the master watches its link; a dead one ends this channel

    def close(self) -> None:
        pass


def spawn_master(host: str, user: str | None, path: Path, *, spare: bool = False) -> None:
    """Start a connection master in the background (it authenticates on its own);
    with ``spare`` it keeps one spare endpoint (see above), of the command this call's
    environment gives (its FETCHSYNC_REMOTE_PYTHON: the master inherits it)."""
    seconds = persist_seconds()
    if seconds <= 0:
        return
    import subprocess  # only a call that connected directly starts a master

    # the lock that says a master is connecting is taken here and handed to the master,
    # so a call that comes before the master's Python has started waits for it too
    lock = _starting(path)
    if lock is None:
        return  # another master is connecting already
    # not ``-m``: it puts the working directory (where the push was typed: a shared
    # checkout, /tmp) first on the master's path; this process's own path instead
    imports = [os.path.abspath(p) for p in sys.path]
    argv = [
        sys.executable,
        "-c",
        "import sys; sys.path[:] = [p for p in sys.path if p]; import json; "
        "sys.path[:] = json.loads(sys.argv.pop(1)); "
        "from fetchsync.link.mux import main; sys.exit(main())",
        json.dumps(imports),
        "--host",
        host,
        "--socket",
        str(path),
        "--idle",
        str(seconds),
    ]
    if lock >= 0:
        argv += ["--lock-fd", str(lock)]
    if user:
        argv += ["--user", user]
    if spare:
        argv += ["--spare"]
    log_path = os.environ.get("FETCHSYNC_MUX_LOG")
    try:
        with open(log_path or os.devnull, "ab") as err:
            subprocess.Popen(
                argv,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=err,
                start_new_session=True,
                close_fds=True,
                pass_fds=(lock,) if lock >= 0 else (),
                env=inheritable(os.environ),  # no password lingers in it (fetchsync.environ)
            )
    finally:
        if lock >= 0:
            os.close(lock)  # the master holds it now (or, if it did not start, nobody)


# --------------------------------------------------------------------------- master side
class _Spare:
    """An endpoint started ahead of a call, waiting after its hello: its channel and
    what it printed so far (handed to the caller first, as if it had just come)."""

    def __init__(self, channel: Any, said: bytes) -> None:
        self.channel = channel
        self.said = said

    def alive(self) -> bool:
        """Nothing more came since its hello, and its channel is neither at EOF nor
        closed nor exited: an endpoint says nothing before the client's hello."""
        try:
            return not self.channel.ready() and self.channel.exit_status(timeout=0) is None
        except Exception:  # the link went: dead too
            return False


def _until_ready(channel: Any) -> bytes | None:
    """Read a started endpoint's output up to its hello's magic or its request for the
    loader or the archive; None if it ended first or printed too much."""
    from fetchsync.protocol.loader import NEED, NEED_LOADER
    from fetchsync.protocol.wire import MAGIC, MAX_NOISE

    said = bytearray()
    while MAGIC not in said and NEED not in said and NEED_LOADER not in said:
        if len(said) > MAX_NOISE + len(MAGIC):
            return None
        chunk = channel.recv(1 << 16)
        if not chunk:
            return None
        said += chunk
    return bytes(said)


def _spare_dies() -> str:
    """FETCHSYNC_TEST_SPARE_DIES (tests only): "1" closes a taken spare right after the
    master's check, before the caller reads it; "answer" closes it when it first answers
    the caller (our hello read, the ping's answer dropped)."""
    return os.environ.get("FETCHSYNC_TEST_SPARE_DIES", "")


class Master:
    """Serves the commands of later calls over one authenticated SSH connection."""

    def __init__(
        self, transport: SSHTransport, path: Path, idle: float, warm: str | None = None
    ) -> None:
        self.transport = transport
        self.path = path
        self.idle = idle
        self.warm = warm  # the endpoint's command: one spare of it is kept started
        self.spare: _Spare | None = None
        self.starting = False  # a spare is being started
        self.hook_fired = False  # FETCHSYNC_TEST_SPARE_DIES fires once
        self.closing = False
        self.lock = threading.Lock()
        self.started = threading.Condition(self.lock)  # a spare's start ended (either way)
        self.active = 0
        self.last_used = time.monotonic()
        self.refused = threading.Event()  # the robot's host key no longer verifies: exit

    def check(self) -> None:
        """Refuse (ConnectError) unless the link is up and the robot's host key is still the
        one known_hosts lists, read afresh: a key changed or removed since this master
        connected is refused as a new connection would refuse it, and the master exits."""
        if not self.transport.is_alive(timeout=0):
            raise ConnectError("the link to the robot is down")
        try:
            self.transport.verify_host_key()
        except ConnectError:
            self.refused.set()
            raise

    def serve(self, *, listening: Callable[[], None] | None = None) -> None:
        """Serve calls until idle, the link's end, or another master's taking the socket;
        ``listening`` is called once calls can connect."""
        tmp = self.path.with_name(self.path.name + f".{os.getpid()}")
        srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        srv.bind(str(tmp))
        os.chmod(tmp, 0o600)
        own = os.stat(tmp).st_ino
        srv.listen(16)
        os.replace(tmp, self.path)
        if listening is not None:
            listening()
        srv.settimeout(IDLE_CHECK)
        self._start_refill()
        try:
            while True:
                try:
                    conn, _ = srv.accept()
                except (TimeoutError, socket.timeout):
                    if not self.transport.is_alive(timeout=0) or self.refused.is_set():
                        return
                    with self.lock:
                        idle = self.active == 0 and time.monotonic() - self.last_used > self.idle
                    if idle or not self._owns(own):
                        return  # idle, or another master took the socket over
                    continue
                try:
                    uid = peer_uid(conn)
                except OSError:
                    uid = -1
                if uid != os.getuid():
                    log.warning("refused a connection from uid %s", uid)
                    conn.close()
                    continue
                with self.lock:
                    self.active += 1
                threading.Thread(target=self._client, args=(conn,), daemon=True).start()
                if self.refused.is_set():
                    return
        finally:
            if self._owns(own):
                try:
                    self.path.unlink()
                except OSError:
                    pass
            srv.close()
            with self.lock:
                self.closing = True
                spare, self.spare = self.spare, None
            if spare is not None:
                spare.channel.close()
            self.transport.close()

    # ------------------------------------------------------------------ the spare endpoint
    def _start_refill(self) -> None:
        threading.Thread(target=self._refill, daemon=True).start()

    def _refill(self) -> None:
        """Start the spare endpoint, unless one is there or starting."""
        with self.lock:
            if not self.warm or self.spare is not None or self.starting or self.closing:
                return
            self.starting = True
        spare = None
        try:
            channel = self.transport.exec(self.warm)
            said = _until_ready(channel)
            if said is None:
                log.info("a spare endpoint ended before its hello")
                channel.close()
            else:
                spare = _Spare(channel, said)
        except Exception as exc:  # the link may be dying; serve() notices
            log.info("cannot start a spare endpoint: %s", exc)
        with self.lock:
            self.starting = False
            if spare is not None and not self.closing:
                self.spare, spare = spare, None
            self.started.notify_all()
        if spare is not None:
            spare.channel.close()

    def _take(self, command: str) -> tuple[Any, bytes]:
        """A channel running ``command`` and what it printed already: the spare endpoint
        when it is that command and still alive, else a fresh start (a dead spare is
        replaced here, in this call). A spare still starting is waited for (a while): it
        is ahead of a fresh start. The caller starts the next spare (:meth:`_refill_later`)."""
        with self.lock:
            if command == self.warm and self.spare is None and self.starting:
                self.started.wait_for(lambda: not self.starting, SPARE_WAIT)
            spare = self.spare if command == self.warm else None
            if spare is not None:
                self.spare = None
        if spare is not None:
            if spare.alive():
                log.info("took the spare endpoint")
                if _spare_dies() == "1" and not self.hook_fired:
                    # tests only: the spare dies after its check, before the caller reads it
                    self.hook_fired = True
                    spare.channel.close()
                return spare.channel, spare.said
            log.info("the spare endpoint had ended: starting a fresh one for this call")
            spare.channel.close()
        elif command == self.warm:
            log.info("no spare endpoint ready for this call: starting one")
        return self.transport.exec(command), b""

    def _owns(self, ino: int) -> bool:
        try:
            return os.stat(self.path).st_ino == ino
        except OSError:
            return False

    def _client(self, conn: socket.socket) -> None:
        refill: threading.Timer | None = None
        channel: Any = None
        try:
            f = conn.makefile("rb")
            line = f.readline(1 << 16)
            request = json.loads(line)
            self.check()
            if request.get("check") is True:
                conn.sendall(_HDR.pack(K_EXIT, 4) + struct.pack(">i", 0))
                conn.close()
                self._done()
                return
            command = request["exec"]
            if not isinstance(command, str):
                raise ValueError("not a command")
            channel, said = self._take(command)
            if command == self.warm:
                refill = self._refill_later()
            if said:
                conn.sendall(_HDR.pack(K_STDOUT, len(said)) + said)
        except Exception as exc:
            try:
                msg = str(exc).encode()
                conn.sendall(_HDR.pack(K_ERROR, len(msg)) + msg)
            except OSError:
                pass
            conn.close()
            if channel is not None:  # the caller went before its answer: nobody would end it
                channel.close()
            if refill is not None:
                refill.cancel()
                self._start_refill()
            self._done()
            return
        ended = threading.Event()  # set before conn closes: its fd number may be reused then
        threading.Thread(target=self._upstream, args=(conn, f, channel, ended), daemon=True).start()
        send_lock = threading.Lock()

        def send(kind: int, data: bytes) -> None:
            with send_lock:
                conn.sendall(_HDR.pack(kind, len(data)) + data)

        def errpump() -> None:
            try:
                while True:
                    data = channel.recv_stderr(1 << 16)
                    if not data:
                        return
                    send(K_STDERR, data)
            except Exception:
                return

        et = threading.Thread(target=errpump, daemon=True)
        et.start()
        # tests only: a spare that read our hello dies before its first answer (the ping's)
        dies = bool(said) and _spare_dies() == "answer" and not self.hook_fired
        try:
            while True:
                data = channel.recv(1 << 16)
                if not data:
                    break
                if dies:
                    self.hook_fired = True
                    channel.close()
                    break
                send(K_STDOUT, data)
            status = channel.exit_status(timeout=5)
            et.join(2)
            send(K_EXIT, struct.pack(">i", -1 if status is None else status))
        except Exception as exc:
            try:
                send(K_ERROR, str(exc).encode())
            except OSError:
                pass
        finally:
            ended.set()
            channel.close()
            conn.close()
            if refill is not None:
                refill.cancel()
                self._start_refill()
            self._done()

    def _refill_later(self) -> threading.Timer:
        """Start the next spare once this call has ended, or REFILL_AFTER seconds into it if
        it lives on (a watch agent's session): not at once. A spare's start (a session
        opened through the link, sshd's fork, the robot's Python and loader: ~0.1 s of the
        robot's CPU, as much of ours for SSH) started while the call runs competes with it
        for both ends' CPU and the link: the push's listing took 66 instead of ~20 ms on
        the bench's wifi robot (strace of the master, 27 Nov)."""
        timer = threading.Timer(REFILL_AFTER, self._refill)
        timer.daemon = True
        timer.start()
        return timer

    @staticmethod
    def _upstream(conn: socket.socket, f: Any, channel: Any, ended: threading.Event) -> None:
        """The caller's bytes to the robot; the end of them is the command's EOF. A caller
        that hangs up entirely (it gave up, Ctrl-C, killed) closes the command's channel at
        once, so the robot's endpoint ends even when it has nothing to say (stopped, or
        stalled), also while its bytes wait for the robot's window; what it wrote that is
        not sent yet is dropped: carried on after it has gone, a whole request in it would
        be applied late (after a later push; tests/test_killed_push_late.py)."""
        gone = threading.Event()

        def watch() -> None:
            hangup = select.poll()
            hangup.register(conn.fileno(), 0)  # POLLHUP and POLLERR are always reported
            while not ended.is_set():
                if hangup.poll(500) and not ended.is_set():
                    gone.set()
                    channel.close()  # also wakes a send_all waiting for the window
                    return

        threading.Thread(target=watch, daemon=True).start()
        try:
            while not gone.is_set():
                data = f.read1(1 << 16)
                if gone.is_set():
                    break
                if not data:
                    channel.shutdown_write()
                    break
                channel.send_all(data)
        except Exception:
            try:
                channel.close()
            except Exception:
                pass

    def _done(self) -> None:
        with self.lock:
            self.active -= 1
            self.last_used = time.monotonic()


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="fetchsync-mux")
    parser.add_argument("--host", required=True)
    parser.add_argument("--user")
    parser.add_argument("--socket", required=True)
    parser.add_argument("--idle", type=float, default=DEFAULT_PERSIST)
    parser.add_argument("--spare", action="store_true")
    parser.add_argument("--lock-fd", type=int, help="the connecting lock, taken by the caller")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="fetchsync-mux: %(message)s")
    starting = args.lock_fd if args.lock_fd is not None else _starting(Path(args.socket))
    if starting is None:
        log.info("another connection master for %s is starting: leaving it to that one", args.host)
        return 0
    stamp(starting)  # our Python is up
    slow = os.environ.get("FETCHSYNC_TEST_MASTER_SLOW")  # tests only: a slow handshake
    if slow:  # ... that makes its steps: one every half second
        end = time.monotonic() + float(slow)
        while time.monotonic() < end:
            time.sleep(min(0.5, max(0.0, end - time.monotonic())))
            stamp(starting)
    from fetchsync.link.ssh import SSHTransport  # paramiko: while the lock tells calls to wait

    stamp(starting)
    try:
        transport = SSHTransport.connect(
            args.host, user=args.user, progress=lambda: stamp(starting)
        )
    except Exception as exc:
        log.error("cannot connect to %s: %s", args.host, exc)
        return 1
    try:
        warm = None
        if args.spare:
            from fetchsync.link.connection import remote_python
            from fetchsync.protocol.loader import loader_spec

            warm = loader_spec(remote_python())[0]
        Master(transport, Path(args.socket), args.idle, warm).serve(
            listening=lambda: os.close(starting) if starting >= 0 else None
        )
    except OSError as exc:
        log.error("cannot serve on %s: %s", args.socket, exc)
        transport.close()
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
