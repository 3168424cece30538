"""Keeping the SSH connection open between calls, as OpenSSH's ControlPersist does.

The first one-shot verb that reaches a robot over SSH leaves a *connection
master* behind: a background process that holds the authenticated SSH
connection, keeps one robot-side endpoint started and waiting, and serves
later calls over an owner-only unix socket. A later ``fetchsync push`` then
pays neither the SSH handshake nor sshd's session start-up nor the endpoint's
Python start-up. The master exits after ``FETCHSYNC_PERSIST`` idle seconds
(default 600; 0 disables it) or as soon as its link dies.

Socket protocol (one connection per remote command): the client sends one
JSON line ``{"exec": COMMAND}`` and then the command's stdin as raw bytes
(half-close = EOF); the master answers with frames ``u8 kind | u32 len |
data``: 1 stdout, 2 stderr, 3 exit status (i32), 4 error message.

The master also keeps the *local* side warm: asked ``{"scan": ROOT, "rules":
RULES}``, it answers (one stdout frame, :mod:`marshal`) with the entries a
fresh scan of ROOT would give, from a scan it made once and keeps current
with inotify (``fetchsync.protocol.watched``). The first request only starts
that scan; until it is ready, and whenever the events may be incomplete or
the tree has entries a scan would report as skipped, the answer is an error
frame and the caller scans for itself.
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
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from fetchsync.errors import ConnectError, LinkLostError

log = logging.getLogger(__name__)

K_STDOUT, K_STDERR, K_EXIT, K_ERROR = 1, 2, 3, 4
_HDR = struct.Struct(">BI")
DEFAULT_PERSIST = 600.0
SCAN_VERSION = 1
MAX_TREES = 2  # local workspaces kept watched by one master
UNWATCHABLE_FOR = 600.0  # seconds before watching a tree that could not be watched is tried again
DRAIN_EVERY = 0.25  # seconds between looks at the watched trees while no call comes


def persist_seconds() -> float:
    try:
        return float(os.environ.get("FETCHSYNC_PERSIST", DEFAULT_PERSIST))
    except ValueError:
        return DEFAULT_PERSIST


MAX_SOCKET_PATH = 100  # AF_UNIX paths are limited to 108 bytes on Linux


def runtime_dir(*, short: bool = False) -> Path:
    base = os.environ.get("XDG_RUNTIME_DIR")
    path = Path(base) / "fetchsync" if base and not short else Path(f"/tmp/fetchsync-{os.getuid()}")
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = path.stat()
    if st.st_uid != os.getuid() or stat.S_IMODE(st.st_mode) & 0o077:
        raise ConnectError(f"{path} is not private to you; refusing to use it for sockets")
    return path


def socket_path(host: str, user: str | None) -> Path:
    key = f"{user or ''}@{host}\0{os.environ.get('HOME', '')}"
    name = f"mux-{hashlib.sha256(key.encode()).hexdigest()[:20]}.sock"
    path = runtime_dir() / name
    if len(os.fsencode(path)) > MAX_SOCKET_PATH:
        path = runtime_dir(short=True) / name
    return path


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
        while len(self._buf) < _HDR.size or len(self._buf) < _HDR.size + _HDR.unpack_from(self._buf)[1]:
            try:
                chunk = self.sock.recv(1 << 16)
            except OSError as exc:
                raise LinkLostError("the connection master went away") from exc
            if not chunk:
                self._eof = True
                return False
            self._buf += chunk
        kind, n = _HDR.unpack_from(self._buf)
        data = bytes(self._buf[_HDR.size:_HDR.size + n])
        del self._buf[:_HDR.size + n]
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
        self.sock.close()


class MuxTransport:
    """A transport whose commands run through a connection master's socket."""

    def __init__(self, path: Path, name: str) -> None:
        self.path = path
        self.name = name

    @classmethod
    def attach(cls, path: Path, name: str) -> MuxTransport | None:
        """The master at ``path`` if one answers, else None (a stale socket is removed)."""
        if not path.exists():
            return None
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(str(path))
        except OSError:
            try:
                path.unlink()
            except OSError:
                pass
            return None
        finally:
            probe.close()
        return cls(path, name)

    def exec(self, command: str, *, env: dict[str, str] | None = None, pty: bool = False) -> MuxChannel:
        if env or pty:
            raise ConnectError("the connection master runs plain commands only")
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.connect(str(self.path))
            sock.sendall(json.dumps({"exec": command}).encode() + b"\n")
        except OSError as exc:
            sock.close()
            raise ConnectError(f"the connection master for {self.name} did not answer") from exc
        return MuxChannel(sock)

    def local_scan(self, root: str, rules: list[Any], timeout: float = 5.0) -> dict[str, Any] | None:
        """The entries under ``root`` as the master keeps them current, or None (scan yourself)."""
        import marshal

        from fetchsync.protocol.tree import Entry

        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.settimeout(timeout)
        try:
            sock.connect(str(self.path))
            sock.sendall(json.dumps({"scan": root, "rules": rules, "v": SCAN_VERSION}).encode() + b"\n")
            sock.shutdown(socket.SHUT_WR)
            buf = bytearray()
            while True:
                chunk = sock.recv(1 << 20)
                if not chunk:
                    break
                buf += chunk
        except OSError:
            return None
        finally:
            sock.close()
        if len(buf) < _HDR.size:
            return None
        kind, n = _HDR.unpack_from(buf)
        if kind != K_STDOUT or len(buf) != _HDR.size + n:
            return None
        try:
            reply = marshal.loads(bytes(buf[_HDR.size:]))
            if reply.get("v") != SCAN_VERSION or reply.get("root") != root:
                return None
            make = Entry._make
            return {path: make(t) for path, t in reply["entries"].items()}
        except (ValueError, EOFError, TypeError, AttributeError, KeyError):
            return None

    def close(self) -> None:
        pass


def spawn_master(host: str, user: str | None, path: Path, *, warm: str | None = None,
                 prescan: tuple[str, Any] | None = None) -> None:
    """Start a connection master in the background (it authenticates on its own).

    ``prescan`` (a local root and its rules' wire form, as a push asks for them)
    is a tree the master starts watching at once, so the next call's scan request
    finds it ready instead of starting it and scanning for itself meanwhile."""
    seconds = persist_seconds()
    if seconds <= 0:
        return
    argv = [sys.executable, "-m", "fetchsync.agent.mux", "--host", host, "--socket", str(path),
            "--idle", str(seconds)]
    if user:
        argv += ["--user", user]
    if warm:
        argv += ["--warm", warm]
    if prescan is not None:
        argv += ["--prescan", json.dumps(list(prescan))]
    log_path = os.environ.get("FETCHSYNC_MUX_LOG")
    if log_path:
        with open(log_path, "ab") as err:
            subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                             start_new_session=True, close_fds=True)
    else:
        subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL, start_new_session=True, close_fds=True)


# --------------------------------------------------------------------------- master side
class _Warm:
    """One started command whose output so far is buffered, ready to hand over."""

    def __init__(self, command: str, channel: Any) -> None:
        self.command = command
        self.channel = channel


class Master:
    WARM = 2  # endpoints kept started: back-to-back calls need not wait for sshd

    def __init__(self, transport: Any, path: Path, idle: float, warm: str | None,
                 prescan: tuple[str, Any] | None = None) -> None:
        self.transport = transport
        self.prescan = prescan
        self.path = path
        self.idle = idle
        self.warm_command = warm
        self.pool: list[_Warm] = []
        self.starting = 0
        self.lock = threading.Lock()
        self.active = 0
        self.last_used = time.monotonic()
        self.trees: dict[str, Any] = {}  # scan key -> WatchedTree, or None while being built
        self.scan_replies: dict[str, tuple[int, bytes]] = {}  # scan key -> (tree version, reply)
        self.unwatchable: dict[str, float] = {}  # scan key -> when watching it last failed
        self.trees_lock = threading.Lock()

    def _refill(self) -> None:
        with self.lock:
            command = self.warm_command
            if not command or len(self.pool) + self.starting >= self.WARM:
                return
            self.starting += 1
        try:
            channel = self.transport.exec(command)
        except Exception as exc:  # the link may be dying; serve() notices
            log.debug("cannot warm an endpoint: %s", exc)
            channel = None
        with self.lock:
            self.starting -= 1
            if channel is not None:
                if command == self.warm_command:
                    self.pool.append(_Warm(command, channel))
                else:
                    channel.close()
        if channel is not None:
            self._refill()

    def _take(self, command: str) -> Any:
        with self.lock:
            found = next((w for w in self.pool if w.command == command), None)
            if found is not None:
                self.pool.remove(found)
            elif command != self.warm_command:
                for w in self.pool:
                    w.channel.close()
                self.pool = []
                self.warm_command = command
        threading.Thread(target=self._refill, daemon=True).start()
        if found is not None:
            return found.channel
        log.info("no endpoint started ahead for this call: starting one")
        return self.transport.exec(command)

    def serve(self) -> None:
        tmp = self.path.with_name(self.path.name + f".{os.getpid()}")
        srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        srv.bind(str(tmp))
        os.chmod(tmp, 0o600)
        own = os.stat(tmp).st_ino
        os.replace(tmp, self.path)
        srv.listen(16)
        srv.settimeout(DRAIN_EVERY)
        threading.Thread(target=self._refill, daemon=True).start()
        if self.prescan is not None:
            root, rules = self.prescan
            with self.trees_lock:
                self._watch(json.dumps([root, rules]), root, rules)
        try:
            while True:
                try:
                    conn, _ = srv.accept()
                except (TimeoutError, socket.timeout):
                    if not self.transport.is_alive(timeout=0):
                        return
                    self._drain_trees()
                    with self.lock:
                        idle = self.active == 0 and time.monotonic() - self.last_used > self.idle
                    if idle or not self._owns(own):
                        return  # idle, or another master took the socket over
                    continue
                with self.lock:
                    self.active += 1
                threading.Thread(target=self._client, args=(conn,), daemon=True).start()
        finally:
            if self._owns(own):
                try:
                    self.path.unlink()
                except OSError:
                    pass
            srv.close()
            with self.lock:
                for w in self.pool:
                    w.channel.close()
                self.pool = []
            with self.trees_lock:
                for tree in self.trees.values():
                    if tree is not None:
                        tree.close()
                self.trees = {}
            self.transport.close()

    def _owns(self, ino: int) -> bool:
        try:
            return os.stat(self.path).st_ino == ino
        except OSError:
            return False

    # ------------------------------------------------------------------ local scans
    def _scan(self, request: dict[str, Any]) -> bytes:
        """The marshalled entries of a watched local tree; ValueError if not ready or usable."""
        if request.get("v") != SCAN_VERSION or not isinstance(request.get("scan"), str):
            raise ValueError("unknown scan request")
        root, rules = request["scan"], request.get("rules")
        key = json.dumps([root, rules])
        with self.trees_lock:
            if key not in self.trees:
                if time.monotonic() - self.unwatchable.get(key, -UNWATCHABLE_FOR) < UNWATCHABLE_FOR:
                    raise ValueError("that tree cannot be watched (inotify limit?)")
                self._watch(key, root, rules)
                raise ValueError("starting to watch that tree")
            tree = self.trees[key]
            if tree is None:
                raise ValueError("still scanning that tree")
            if not tree.refresh():
                tree.close()
                del self.trees[key]
                self.scan_replies.pop(key, None)
                raise ValueError("events were lost; watching that tree again")
            if tree.skipped:
                raise ValueError("that tree has entries a scan skips")
            return self._reply(key, tree)

    def _watch(self, key: str, root: str, rules: Any) -> None:
        """Start building the watched tree for ``key`` (with trees_lock; not yet there)."""
        if len(self.trees) >= MAX_TREES:
            oldest = next(iter(self.trees))
            old = self.trees.pop(oldest)
            self.scan_replies.pop(oldest, None)
            if old is not None:
                old.close()
        self.trees[key] = None
        threading.Thread(target=self._build_tree, args=(key, root, rules), daemon=True).start()

    def _reply(self, key: str, tree: Any) -> bytes:
        """The marshalled answer for ``tree`` as it is now (made once per version); with trees_lock."""
        import marshal

        cached = self.scan_replies.get(key)
        if cached is not None and cached[0] == tree.version:
            return cached[1]  # nothing moved since the last answer
        entries = {path: tuple(e) for path, e in tree.entries.items()}
        reply = marshal.dumps({"v": SCAN_VERSION, "root": tree.root, "entries": entries})
        self.scan_replies[key] = (tree.version, reply)
        return reply

    def _build_tree(self, key: str, root: str, rules: Any) -> None:
        from fetchsync.protocol.ignore import IgnoreRules
        from fetchsync.protocol.store import is_temp
        from fetchsync.protocol.watched import Unavailable, WatchedTree

        try:
            tree = WatchedTree(root, IgnoreRules.from_wire(rules) if rules is not None else None,
                               is_temp)
        except (Unavailable, OSError, ValueError) as exc:
            log.debug("cannot watch %s: %s", root, exc)
            tree = None
        if tree is not None and tree.watch.lost:
            # over the user's inotify watch limit: give the watches back (a watch
            # agent needs them more) and let callers scan for themselves a while
            tree.close()
            tree = None
        with self.trees_lock:
            if key in self.trees and tree is not None:
                self.trees[key] = tree
                log.info("watching %s: its scans are ready", root)
                return
            self.trees.pop(key, None)
            if tree is None:
                self.unwatchable[key] = time.monotonic()
        if tree is not None:
            tree.close()

    def _drain_trees(self) -> None:
        """Apply the events queued since the last look, so a burst cannot overflow the queue,
        and have the answer to the next scan request ready: a push after a save then finds
        it made, instead of waiting while 10,000 entries are marshalled again."""
        with self.trees_lock:
            for key, tree in list(self.trees.items()):
                if tree is None:
                    continue
                if not tree.refresh():
                    tree.close()
                    del self.trees[key]
                    self.scan_replies.pop(key, None)
                elif not tree.skipped:
                    self._reply(key, tree)

    def _client(self, conn: socket.socket) -> None:
        try:
            f = conn.makefile("rb")
            line = f.readline(1 << 16)
            request = json.loads(line)
            if "scan" in request:
                self._answer_scan(conn, request)
                return
            command = request["exec"]
            channel = self._take(command)
        except Exception as exc:
            try:
                msg = str(exc).encode()
                conn.sendall(_HDR.pack(K_ERROR, len(msg)) + msg)
            except OSError:
                pass
            conn.close()
            self._done()
            return
        threading.Thread(target=self._upstream, args=(f, channel), daemon=True).start()
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
        try:
            while True:
                data = channel.recv(1 << 16)
                if not data:
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
            channel.close()
            conn.close()
            self._done()

    def _answer_scan(self, conn: socket.socket, request: dict[str, Any]) -> None:
        try:
            try:
                data, kind = self._scan(request), K_STDOUT
            except ValueError as exc:
                data, kind = str(exc).encode(), K_ERROR
            conn.sendall(_HDR.pack(kind, len(data)) + data)
        except OSError:
            pass
        finally:
            conn.close()
            self._done()

    @staticmethod
    def _upstream(f: Any, channel: Any) -> None:
        try:
            while True:
                data = f.read1(1 << 16)
                if not data:
                    channel.shutdown_write()
                    return
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

    from fetchsync.ssh import SSHTransport

    parser = argparse.ArgumentParser(prog="fetchsync-mux")
    parser.add_argument("--host", required=True)
    parser.add_argument("--user")
    parser.add_argument("--socket", required=True)
    parser.add_argument("--idle", type=float, default=DEFAULT_PERSIST)
    parser.add_argument("--warm")
    parser.add_argument("--prescan", type=json.loads)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="fetchsync-mux: %(message)s")
    try:
        transport = SSHTransport.connect(args.host, user=args.user)
    except Exception as exc:
        log.error("cannot connect to %s: %s", args.host, exc)
        return 1
    try:
        prescan = tuple(args.prescan) if isinstance(args.prescan, list) and len(args.prescan) == 2 else None
        Master(transport, Path(args.socket), args.idle, args.warm, prescan).serve()
    except OSError as exc:
        log.error("cannot serve on %s: %s", args.socket, exc)
        transport.close()
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
