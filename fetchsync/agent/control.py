"""The agent's control socket: ``status``, ``flush`` and ``push`` for other processes.

One JSON object per line each way, over an owner-only unix socket in the
user's runtime directory. ``flush`` with ``skip_offline`` gives up on a robot that is
offline (a fleet's flush, which must not wait on one robot out of range). :func:`call` is the client side used by the CLI;
it returns None when no agent is running for the target.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

from fetchsync.agent.quick import agent_paths, runtime_paths
from fetchsync.trace import mark

__all__ = ["agent_paths", "runtime_paths"]  # kept light in quick.py (a push's fast path)

log = logging.getLogger(__name__)

MAX_REQUEST = 1 << 20
OFFLINE_CHECK = 1.0  # seconds between looks at whether the robot went offline during a push


class ControlServer:
    def __init__(
        self,
        path: Path,
        agent: Any,
        *,
        handler: Callable[[dict[str, Any], socket.socket], dict[str, Any] | None] | None = None,
    ) -> None:
        """``handler``: answers the requests instead of :meth:`handle` (the resident's);
        None from it closes the connection without an answer."""
        self.path = path
        self.agent = agent
        self.handler = handler
        self.clients: list[threading.Thread] = []  # the requests' threads, for a clean exit
        self.sock: socket.socket | None = None
        self.thread: threading.Thread | None = None

    def start(self) -> None:
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass  # the agent lock is held: any socket file left is stale
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)
        try:
            sock.bind(str(self.path))
        finally:
            os.umask(old)
        os.chmod(self.path, 0o600)
        sock.listen(16)
        sock.settimeout(0.2)
        self.sock = sock
        self.thread = threading.Thread(target=self._serve, name="fetchsync-control", daemon=True)
        self.thread.start()

    def stop(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass

    def _serve(self) -> None:
        while self.sock is not None and not self.agent.stop_event.is_set():
            try:
                conn, _ = self.sock.accept()
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            if not _ours(conn):
                conn.close()
                continue
            client = threading.Thread(target=self._client, args=(conn,), daemon=True)
            self.clients = [t for t in self.clients if t.is_alive()] + [client]
            client.start()

    def _client(self, conn: socket.socket) -> None:
        try:
            with conn, conn.makefile("rwb") as f:
                line = f.readline(MAX_REQUEST)
                try:
                    req = json.loads(line)
                    if not isinstance(req, dict):
                        raise ValueError("not an object")
                    # the resident's handler sees the caller's socket: a caller gone
                    # (Ctrl-C) stops the push it asked for
                    reply = self.handler(req, conn) if self.handler else self.handle(req)
                except (ValueError, TypeError, KeyError) as exc:
                    reply = {"ok": False, "error": f"bad request: {exc}"}
                if reply is None:
                    return
                f.write(json.dumps(reply).encode() + b"\n")
                f.flush()
        except OSError:
            pass  # the client went away

    def handle(self, req: dict[str, Any]) -> dict[str, Any]:
        cmd = req.get("cmd")
        timeout = float(req.get("timeout", 60))
        if cmd == "status":
            return {"ok": True, "status": self.agent.status()}
        if cmd == "flush":
            paths = req.get("paths") or []
            if not isinstance(paths, list) or not all(isinstance(p, str) for p in paths):
                raise ValueError("paths must be a list of strings")
            if req.get("skip_offline") and self.agent.status().get("offline_since"):
                return self._offline()  # a fleet's flush: the agent catches it up once back
            seq = self.agent.request(paths=set(paths)) if paths else self.agent.request(full=True)
            if req.get("skip_offline"):
                ok, why, offline = self._wait(seq, timeout)
                if offline:
                    return self._offline()
            else:
                ok, why = self.agent.wait_for(seq, timeout)
            return {"ok": ok, "error": why, "status": self.agent.status()}
        if cmd == "push":
            mark("agent: push asked")
            if self.agent.status().get("offline_since"):
                return self._offline()
            seq = self.agent.request(full=True)
            ok, why, offline = self._wait(seq, timeout)
            if offline:
                return self._offline()
            report = self.agent.status().get("last_report")
            mark("agent: pushed")
            return {"ok": ok, "error": why, "report": report, "raise": _raised(report)}
        raise ValueError(f"unknown command {cmd!r}")

    def _wait(self, seq: int, timeout: float) -> tuple[bool, str, bool]:
        """Wait for request ``seq`` as the agent does, but give up as soon as the robot is
        offline: (done, error, offline). A push does not wait for a robot's return."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            ok, why = self.agent.wait_for(seq, max(0.0, min(left, OFFLINE_CHECK)))
            waiting = why == "timed out" or why.startswith("the robot is offline")
            if ok or not waiting or left <= OFFLINE_CHECK:
                return ok, why, False
            if self.agent.status().get("offline_since"):
                return False, why, True

    def _offline(self) -> dict[str, Any]:
        since = self.agent.status().get("offline_since")
        when = time.strftime("%H:%M:%S", time.localtime(since)) if since else "now"
        return {"ok": False, "offline": True, "error": f"the robot is offline since {when}"}


def _raised(report: dict[str, Any] | None) -> dict[str, Any] | None:
    """The error a push here raises for ``report`` (engine.raise_for), said for the
    client: a push's fast path (fetchsync.agent.quick) prints it without the engine."""
    if not report:
        return None
    from fetchsync.errors import FetchsyncError
    from fetchsync.sync.engine import Report, raise_for

    fields = Report.__dataclass_fields__
    try:
        raise_for(Report(**{k: v for k, v in report.items() if k in fields}), strict=False)
    except FetchsyncError as exc:
        return {"error": exc.message, "hint": exc.hint, "exit_code": exc.exit_code}
    return None


def _ours(sock: socket.socket) -> bool:
    """Whether the process at the other end of ``sock`` runs as us (SO_PEERCRED)."""
    from fetchsync.link.mux import peer_uid

    try:
        return peer_uid(sock) == os.getuid()
    except OSError:
        return False


def call(path: Path, payload: dict[str, Any], *, timeout: float = 60.0) -> dict[str, Any] | None:
    """Send one request to the agent at ``path``; None if no agent answers there."""
    if not path.exists():
        return None
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout + 5)
    try:
        sock.connect(str(path))
    except OSError:
        sock.close()
        return None
    if not _ours(sock):
        sock.close()
        log.warning("fetchsync: %s is served by another user; ignoring it", path)
        return None
    try:
        with sock, sock.makefile("rwb") as f:
            f.write(json.dumps(dict(payload, timeout=timeout)).encode() + b"\n")
            f.flush()
            line = f.readline(MAX_REQUEST)
    except OSError:
        return None
    if not line:
        return None
    reply = json.loads(line)
    return reply if isinstance(reply, dict) else None


def push(path: Path, *, timeout: float = 3600.0) -> dict[str, Any] | None:
    """Ask the agent at ``path`` for a full push: its reply, or None when no agent runs
    there or its robot is offline (said on stderr at once: the caller then pushes
    directly, which reaches the robot or fails within the connect timeout)."""
    reply = call(path, {"cmd": "push"}, timeout=timeout)
    if reply is not None and reply.get("offline"):
        print(
            f"fetchsync: the watch agent cannot reach its robot ({reply.get('error')}); "
            "pushing directly",
            file=sys.stderr,
            flush=True,
        )
        return None
    return reply
