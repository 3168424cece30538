"""The resident: the agent's service without a watcher, for one-shot pushes.

A plain ``fetchsync push`` that went the normal way starts one, detached, once its
own work is done (:func:`fetchsync.agent.quick.start_resident`). It takes the
agent's lock and control socket for the robot and remote workspace (one per target,
as the watch agent), connects through the connection master, and then answers plain
pushes (and ``status``, ``flush``) with everything warm: the interpreter, the
imports, the robot's endpoint. Each push is what a fresh process would do: a fresh
scan of the local tree, the synced state read again from disk (the engine rereads
its rows at every push; the database is opened again when another process replaced
it), the robot asked what changed there since; a fresh guard count, no cached plan.
So a push made without it meanwhile (``--force``, ``--build``, another laptop
process, ``pull``) is neither undone nor skipped.

It answers only pushes of its own install (package place and version), target and
environment; its code files are checked at each request (an upgrade, a ``git
pull`` of an editable install: it then declines and exits). It exits after
``$FETCHSYNC_RESIDENT`` idle seconds (default 600), when its socket is taken away,
when its link to the robot ends, or when asked (``fetchsync watch`` for the same
target takes over).

What it pays for (bench/run.py, 2,000 files / 40 MiB, 7 interleaved rounds against
e947067 at 213ab1a, every small push of this revision made by a resident, checked by
the report's ``connection``; the machine at load 6-9, walls above a quiet run's):
wifi no-op 0.409 vs 0.530 s (0.77x), one edit 0.411 vs 0.527 s (0.78x, rounds'
median 0.89x), a line inserted in a 2 MiB file 0.326 vs 0.648 s (0.50x); loopback
0.78x, 0.67x, 0.69x. The load-independent part, one-edit push of a 2,000-file tree
to the tests' sshd, 8 interleaved: the push's own process CPU 105-115 ms (through
the resident, whose own CPU is ~50 ms) against 243-259 ms (a new process through
the master). Session 22 (issue 24): the scan kept by inotify between pushes
(fetchsync.agent.keptscan) and the fast path's lighter imports: on the wifi bench,
10 interleaved one-edit pushes against the revision before (load 4-9), the
resident's CPU per push 79.5 -> 26.6 ms and the asking process's 89.7 -> 60.7 ms
(medians; every round lower). Session 24: the robot asked for its changes before
the kept scan (both ends work at once: the robot's listing starts ~4 ms after the ask,
not ~14), the state's rows kept between pushes (fetchsync.sync.state.State.entries:
~14 ms of reading less) and the robot's kept drift looking only at what moved
(fetchsync.protocol.store.Store.drift). bench/edittrace.py --link wifi --files 2000
--size-mb 40 --reps 9 --scenarios noop,edit --rev 1157ebc --baseline-rev 9a8639d
(interleaved, load 3-5): one edit 0.110 vs 0.133 s (rsync 0.546 s: 0.20x, rounds'
0.19x); from the ask to the answer 49 vs 73 ms (trace medians); CPU per push of the
resident 25 vs 43 ms, of the robot's endpoint 16 vs 18 (schedstat). What is left runs
at once on both ends: the kept scan's and the robot's listing's ~2,500 stat calls each
(~11 and ~13 ms), then the robot's write and its journal commits.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import queue
import sys
import threading
import time
from pathlib import Path
from typing import Any

from fetchsync.agent import quick
from fetchsync.errors import FetchsyncError, TransportError
from fetchsync.protocol.errors import ProtocolError
from fetchsync.trace import mark

log = logging.getLogger(__name__)

LOOK_EVERY = 0.5  # seconds between looks at the socket, the link and the idle time
CODE_EVERY = 5.0  # seconds between looks at the code files while idle
PUSH_MAX = 3600.0  # seconds an exiting resident waits for the push it is making


def code_stamp(package: str) -> tuple[tuple[str, int, int, int], ...]:
    """Every source file of the package with its size, mtime and inode: a change on disk
    (an upgrade, a ``git pull`` of an editable install) changes it. ~0.5 ms."""
    out = []
    for dirpath, dirnames, filenames in os.walk(package):
        dirnames[:] = [d for d in dirnames if d != "__pycache__"]
        for name in filenames:
            if name.endswith(".py"):
                path = os.path.join(dirpath, name)
                try:
                    st = os.stat(path)
                except OSError:
                    continue
                out.append((path, st.st_size, st.st_mtime_ns, st.st_ino))
    out.sort()
    return tuple(out)


class Resident:
    def __init__(self, target: Any, sock: Path, *, idle: float) -> None:
        self.target = target
        self.socket_path = sock
        self.idle = idle
        self.src = str(target.workspace / "src")
        self.me = quick.identity()
        self.env = quick.env_key()
        self.fields = quick.target_fields(target)
        self.stamp = code_stamp(self.me["package"])
        self.stop_event = threading.Event()
        self.last_used = time.monotonic()
        self.last_report: dict[str, Any] | None = None
        self.last_sync: float | None = None
        self.last_error = ""
        self.pushes = 0
        self._jobs: queue.Queue[tuple[dict[str, Any], list[dict[str, Any]], threading.Event]] = (
            queue.Queue()
        )
        self._busy = threading.Lock()  # held by the one request being served
        self._lock_fd = -1
        self._transport: Any = None
        self._conn: Any = None
        self._state: Any = None
        self._state_id: tuple[int, int] | None = None
        self._socket_id: tuple[int, int] | None = None
        self._release = False  # hand memory back after answering (a large push)
        self._kept: Any = None  # the scan of src/ kept by inotify (fetchsync.agent.keptscan)

    # ------------------------------------------------------------------ lifecycle
    def acquire(self) -> bool:
        """Take the agent's lock for the target; False when a watch or resident has it."""
        from fetchsync.agent.control import agent_paths
        from fetchsync.agent.service import take_lock

        lock, sock = agent_paths(self.target)
        if sock != self.socket_path:
            return False
        try:
            self._lock_fd = take_lock(
                lock, lambda owner: RuntimeError(owner), words=quick.LOCK_WORDS
            )
        except RuntimeError:
            return False
        return True

    def run(self) -> None:
        from fetchsync.agent.control import ControlServer

        server = ControlServer(self.socket_path, self, handler=self.handle)
        server.start()
        st = os.stat(self.socket_path)
        self._socket_id = (st.st_dev, st.st_ino)
        worker = threading.Thread(target=self._work, name="fetchsync-resident", daemon=True)
        worker.start()
        self._jobs.put(({"cmd": "connect"}, [], threading.Event()))
        code_checked = time.monotonic()
        try:
            while not self.stop_event.wait(LOOK_EVERY):
                now = time.monotonic()
                if not self._busy.locked() and now - self.last_used > self.idle:
                    log.info("idle for %.0f s: exiting", now - self.last_used)
                    break
                if not self._socket_ours():
                    break  # taken away (a new login session's cleanup, another resident)
                if self._link_dead():
                    break  # the master or the robot went: the next push starts afresh
                if now - code_checked > CODE_EVERY:
                    code_checked = now
                    if code_stamp(self.me["package"]) != self.stamp:
                        break
        finally:
            self.stop_event.set()
            if self._socket_ours():
                server.stop()  # no new requests (one taken away is another's now)
            self._jobs.put(({"cmd": "exit"}, [], threading.Event()))
            worker.join(PUSH_MAX)  # a push under way finishes, as a killed one would not
            for client in list(server.clients):
                client.join(5)  # its answer goes out
            if self._lock_fd >= 0:
                os.close(self._lock_fd)

    def stop(self) -> None:
        self.stop_event.set()

    def _socket_ours(self) -> bool:
        try:
            st = os.stat(self.socket_path)
        except OSError:
            return False
        return (st.st_dev, st.st_ino) == self._socket_id

    def _link_dead(self) -> bool:
        conn = self._conn
        return conn is not None and conn.answered(0)  # request 0 is never sent: failed

    # ------------------------------------------------------------------ requests
    def handle(self, req: dict[str, Any], caller: Any = None) -> dict[str, Any] | None:
        """A request from the control socket; None: close without an answer (a push
        from a client that does not say who it is: an older fetchsync, which then
        pushes the normal way, as with no agent)."""
        cmd = req.get("cmd")
        if cmd == "status":
            return {"ok": True, "status": self.status()}
        if cmd == "quit":
            self.stop()
            return {"ok": True}
        if cmd not in ("push", "flush"):
            raise ValueError(f"unknown command {cmd!r}")
        if not isinstance(req.get("client"), dict):
            return None
        if self.stop_event.is_set():
            return {"resident": True, "declined": "exiting"}
        why = self._not_mine(req)
        if why:
            mark(f"resident: declined ({why})")
            return {"resident": True, "declined": why}
        if not self._busy.acquire(timeout=quick.BUSY_WAIT):
            return {"resident": True, "busy": True}
        try:
            if code_stamp(self.me["package"]) != self.stamp:
                self.stop()
                return {"resident": True, "declined": "its code changed on disk"}
            self.last_used = time.monotonic()
            answer: list[dict[str, Any]] = []
            done = threading.Event()
            self._jobs.put((req, answer, done))
            while not done.wait(LOOK_EVERY):
                if caller is not None and _hung_up(caller):
                    # Ctrl-C, or the caller killed: the push stops, as its own would
                    mark("resident: the caller hung up: push stopped")
                    self._abandon()
                    done.wait()
            self.last_used = time.monotonic()
            if not answer:
                return {"resident": True, "fallback": "no answer"}
            if "ok" in answer[0]:  # printed: its where-line names the login
                answer[0]["login"] = self._login()
            return answer[0]
        finally:
            self._busy.release()

    def _not_mine(self, req: dict[str, Any]) -> str:
        if req.get("client") != self.me:
            return "another install"
        if req.get("target") != self.fields:
            return "another target"
        if req.get("env") != self.env:
            return "another environment"
        return ""

    def _login(self) -> str | None:
        """The login the push's first line names (``push SRC -> USER@ROBOT:DEST``), as the
        asking process would find it now (the ssh config read again): it then needs
        neither hashlib nor the ssh config's note."""
        from fetchsync.config import login_name

        try:
            return login_name(self.target)
        except FetchsyncError:
            return None  # the asking process finds it, and says what is wrong

    def status(self) -> dict[str, Any]:
        return {
            "state": "resident",
            "robot": self.target.robot,
            "workspace": self.src,
            "remote": self.target.remote_workspace + "/src",
            "pid": os.getpid(),
            "last_sync": self.last_sync,
            "pending": 0,
            "offline_since": None,
            "conflicts": [],
            "last_error": self.last_error,
            "last_report": self.last_report,
            "build": None,
            "pushes": self.pushes,
        }

    # ------------------------------------------------------------------ the work
    def _work(self) -> None:
        """The one thread that uses the connection and the state (SQLite's connection
        belongs to the thread that opened it)."""
        while True:
            req, answer, done = self._jobs.get()
            try:
                if req["cmd"] == "exit":
                    self._close()
                    return
                if req["cmd"] == "connect":
                    try:
                        self._connect()
                        self._keep_scan()  # the first push finds it ready
                        self._warm()
                    except Exception as exc:  # noqa: BLE001 - no master, no robot: not needed
                        log.info("could not connect: %s", exc)
                        self._drop()
                        self.stop()
                    continue
                answer.append(self._push())
            except BaseException as exc:  # noqa: BLE001 - never leave a client waiting
                answer.append({"resident": True, "fallback": f"{type(exc).__name__}: {exc}"})
            finally:
                done.set()
            if not self.stop_event.is_set():
                self._keep_scan()  # answered: the next push's scan made ready meanwhile
            if self._release:
                from fetchsync.agent.service import release_memory

                self._release = False
                release_memory()

    def _connect(self) -> None:
        if self._conn is not None and not self._link_dead():
            return
        self._drop()
        from fetchsync.link.session import open_connection, open_transport

        if self.target.is_local:
            transport = open_transport(self.target)
        else:
            # through the connection master only: without one (a password login leaves
            # none), a resident would connect with no terminal to ask on, and its pushes
            # would each pay that before the normal path
            from fetchsync.errors import ConnectError
            from fetchsync.link import mux

            path = mux.socket_path(self.target.host, self.target.user)
            mux.wait_while_starting(path)
            attached = mux.MuxTransport.attach(path, self.target.robot)
            if attached is None:
                raise ConnectError("no connection master")
            transport = attached
        try:
            transport, conn = open_connection(self.target, transport)
        except BaseException:
            transport.close()
            raise
        self._transport, self._conn = transport, conn
        mark("resident: connected")

    def _keep_scan(self) -> None:
        """Make the kept scan ready for the next push when it is not (a full scan and a
        watch on each directory: ~35 ms of CPU for 2,547 paths), once the client has
        its answer. The next push then lists only where something happened."""
        from fetchsync.agent.keptscan import KeptScan
        from fetchsync.protocol.ignore import build_rules
        from fetchsync.protocol.store import is_temp

        if self._kept is None:
            self._kept = KeptScan(self.src, build_rules(()), is_temp=is_temp)
        if not self._kept.warm and not self._kept.gave_up:  # gave up: the engine scans
            try:
                self._kept.scan()
            except Exception as exc:  # noqa: BLE001 - only a cache: the push scans itself
                log.info("no kept scan: %s", exc)  # src/ cannot be listed, no inotify
                self._kept.close()
            mark("resident: scan kept")

    def _warm(self) -> None:
        """Make ready, before the first push, what the first two pushes would each make
        (~30 ms of the robot's CPU each, ~15 of this process's): the state's rows read
        (kept: State.entries), the robot's Store kept (an endpoint keeps a workspace's
        Store from its second open) and its listing kept (by the walk after that:
        fetchsync.protocol.kept). Only caches that answer what a fresh look would: each
        push still opens the workspace and asks for the robot's changes itself. Asked as
        a push asks (its rules and options), the listing only for the changes since the
        state's generation (a few bytes)."""
        from fetchsync.link.client import Endpoint
        from fetchsync.protocol.ignore import build_rules

        try:
            state, _note = self._open_state()
            state.entries()
            state.signed_paths()
            if not state.epoch:
                return  # no generation to ask about: the first push lists the whole tree
            endpoint = Endpoint(self._conn)
            for _ in range(2):
                endpoint.open(self.target.remote_workspace, rules=build_rules(()))
            endpoint.listing(since=(state.epoch, state.gen))
            mark("resident: warmed")
        except Exception as exc:  # noqa: BLE001 - only caches: the pushes make them
            log.info("not warmed: %s", exc)

    def _abandon(self) -> None:
        """End the push under way from another thread: its connection closed at once,
        the push fails as a killed one does (nothing torn, the state behind)."""
        conn = self._conn
        if conn is not None:
            try:
                conn.close()
            except Exception:  # noqa: BLE001 - the link is gone already
                pass

    def _drop(self) -> None:
        conn, transport = self._conn, self._transport
        self._conn = self._transport = None
        for each in (conn, transport):
            if each is not None:
                try:
                    each.close()
                except Exception:  # noqa: BLE001 - the link is gone already
                    pass

    def _open_state(self) -> tuple[Any, str]:
        """The target's state, opened again when the file is not the one held (another
        process set a damaged one aside, or it was removed): as a fresh process finds it."""
        from fetchsync.link.session import robot_id
        from fetchsync.sync.state import open_state, state_path

        path = state_path(robot_id(self.target), self.target.remote_workspace)
        try:
            st = os.stat(path)
            ident: tuple[int, int] | None = (st.st_dev, st.st_ino)
        except OSError:
            ident = None
        if self._state is not None and ident is not None and ident == self._state_id:
            return self._state, ""
        if self._state is not None:
            self._state.close()
            self._state = None
        state = open_state(self.target)
        st = os.stat(state.path)
        self._state, self._state_id = state, (st.st_dev, st.st_ino)
        return state, state.note

    def _push(self) -> dict[str, Any]:
        mark("resident: push asked")
        from fetchsync.agent.quick import pushable
        from fetchsync.agent.service import RELEASE_AFTER
        from fetchsync.protocol.ignore import build_rules
        from fetchsync.sync.engine import Syncer, raise_for

        src = Path(self.src)
        try:
            pushable(src, force=False, whose="the robot's")
        except FetchsyncError as exc:
            return {"resident": True, "fallback": str(exc)}  # said the normal way
        try:
            self._connect()
        except (FetchsyncError, OSError, EOFError) as exc:
            self._drop()
            return {"resident": True, "fallback": f"cannot connect: {exc}"}
        try:
            state, note = self._open_state()
        except FetchsyncError as exc:
            return {"resident": True, "fallback": str(exc)}
        mark("resident: connected, state open")
        kept = self._kept
        syncer = Syncer(
            self._conn,
            state,
            local_root=self.src,
            remote_workspace=self.target.remote_workspace,
            rules=build_rules(()),
            policy="preserve",
        )
        try:
            # the tree as a fresh scan finds it, from the kept scan when it can say (else
            # the engine's scan), made once the robot is asked for its changes: the robot
            # works out its listing meanwhile
            warm = kept is not None and kept.warm
            mark("resident: pushing" if warm else "resident: pushing (scan not kept)")
            report = syncer.push(scanner=kept.scan if warm else None)
        except (TransportError, ProtocolError, EOFError, OSError) as exc:
            # the link (or the robot's answers) failed: the client pushes again itself,
            # the way a push after a killed one does
            self._drop()
            return {"resident": True, "fallback": f"{type(exc).__name__}: {exc}"}
        except FetchsyncError as exc:  # the guard, the state: said as a push here says it
            self.last_error = str(exc)
            return {"resident": True, "ok": False, **_error(exc), "note": note}
        mark("resident: pushed")
        # a large push's pages go back once it is answered: it may idle for minutes
        self._release = report.changed >= RELEASE_AFTER
        self.pushes += 1
        report.connection = "resident"
        data = report.to_json()
        self.last_report = data
        self.last_sync = time.time()
        answer: dict[str, Any] = {
            "resident": True,
            "ok": True,
            "report": data,
            "note": note,
            "raise": None,
        }
        try:
            raise_for(report, strict=False)
        except FetchsyncError as exc:
            answer["raise"] = _error(exc)
        return answer

    def _close(self) -> None:
        self._drop()
        if self._kept is not None:
            self._kept.close()
        if self._state is not None:
            try:
                self._state.close()
            except Exception:  # noqa: BLE001 - closing at exit
                pass


def _hung_up(sock: Any) -> bool:
    """Whether the caller on ``sock`` has gone (it sends one request, then waits)."""
    import socket

    try:
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except BlockingIOError:
        return False
    except OSError:
        return True


def _error(exc: FetchsyncError) -> dict[str, Any]:
    return {"error": exc.message, "hint": exc.hint, "exit_code": exc.exit_code}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="fetchsync-resident")
    parser.add_argument("--socket", required=True)
    parser.add_argument("--target", required=True)
    parser.add_argument("--client", required=True)
    args = parser.parse_args(argv)
    if json.loads(args.client) != quick.identity():
        return 0  # not the code of the push that started it: it would serve none
    os.chdir("/")  # pin no directory (a workspace on a drive to unmount)
    idle = quick.idle_seconds()
    if idle <= 0:
        return 0
    target = quick.target_from(json.loads(args.target))
    resident = Resident(target, Path(args.socket), idle=idle)
    if not resident.acquire():
        return 0  # a watch or another resident serves it
    mark("resident: started")
    try:
        resident.run()
    finally:
        mark("resident: exiting")
    return 0


if __name__ == "__main__":
    sys.exit(main())
