"""The watch agent: keeps a robot's ``src/`` identical to the local one, live.

Three threads share one :class:`Agent`:

- the watcher (``fetchsync.agent.watcher.batches``) turns inotify events into
  coalesced batches of touched paths and puts them in a queue;
- the sync loop merges whatever is pending into one incremental push
  (:meth:`fetchsync.sync.engine.Syncer.push_paths`), or a full push after a rescan,
  a reconnection or a request; when the link is lost it keeps collecting
  changes, tries to reconnect every quarter of a second while the user is
  editing (backing off to a few seconds only when idle) and then pushes
  everything that changed meanwhile;
- the control server (``fetchsync.agent.control``) answers ``status``,
  ``flush`` and ``push`` on an owner-only unix socket.

One agent runs per (robot, remote workspace): a second one finds the lock
taken and says where the first one is.
"""

from __future__ import annotations

import fcntl
import gc
import logging
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from fetchsync.agent.control import agent_paths  # noqa: F401  (it lives by the control socket)
from fetchsync.config import Target
from fetchsync.errors import FetchsyncError, TransportError, UsageError
from fetchsync.protocol.errors import ProtocolError
from fetchsync.protocol.heap import libc, map_large_buffers
from fetchsync.trace import mark

log = logging.getLogger(__name__)

BACKOFF_FIRST = 0.25
BACKOFF_CAP = 8.0  # seconds between reconnection attempts once nobody is editing
EDITING = 120.0  # a change or request this recent: the user is editing
RETRY_EDITING = 0.25  # seconds between reconnection attempts while the user is editing
PROBE_EVERY = 2.0  # seconds between link checks while idle
KEEPALIVE_WAIT = 3.0  # an unanswered keepalive this old: the link is down
SUSPECT_GRACE = 1.0  # a new connection works but the old one stays silent this long: it is dead
RELEASE_AFTER = 1000  # paths a push must have changed before its memory is handed back


def release_memory() -> None:
    """Hand the memory a large push used back to the system.

    CPython frees a full push's hundreds of thousands of objects, but glibc
    keeps the pages in its heaps and arenas (the sender thread has its own),
    so the agent would stay at its high-water mark for as long as it runs.
    ``malloc_trim(0)`` returns free heap pages to the kernel; without glibc
    this is only a collection.
    """
    gc.collect()
    trim = libc("malloc_trim")
    if trim is not None:
        trim(0)


@dataclass
class Pending:
    """Changes seen but not yet on the robot."""

    paths: set[str] = field(default_factory=set)
    dirs: set[str] = field(default_factory=set)
    full: bool = False
    # back from offline: what was pending goes first (push_paths, the save on the robot
    # without a scan of the whole tree), then a full push checks everything
    recheck: bool = False
    first: int = 0  # the first request merged in
    seq: int = 0  # the last request merged in

    def empty(self) -> bool:
        return not (self.paths or self.dirs or self.full or self.recheck)

    def count(self) -> int:
        return len(self.paths) + len(self.dirs) + (1 if self.full else 0)


def take_lock(path: Path, busy: Callable[[str], Exception], *, words: str = "pid") -> int:
    """A descriptor holding ``path``'s exclusive lock, ``words`` and our pid written in it;
    when another process holds it, ``busy(what it wrote)`` is raised (one watch per target
    or workspace)."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        try:
            owner = os.read(fd, 200).decode("utf-8", "replace").strip()
        finally:
            os.close(fd)
        raise busy(owner or "pid unknown") from None
    os.ftruncate(fd, 0)
    os.write(fd, f"{words} {os.getpid()}".encode())
    return fd


TAKE_OVER_WAIT = 10.0  # seconds a watch waits for a resident to finish its push and exit


def _take_over(lock: Path, sock: Path) -> bool:
    """Ask the resident holding ``lock`` to exit and wait until it has; False when the
    holder is not a resident (a watch agent) or does not let go in time."""
    from fetchsync.agent.control import call
    from fetchsync.agent.quick import LOCK_WORDS

    try:
        owner = lock.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return False
    if not owner.startswith(LOCK_WORDS):
        return False
    call(sock, {"cmd": "quit"}, timeout=5)
    deadline = time.monotonic() + TAKE_OVER_WAIT
    while time.monotonic() < deadline:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True  # free now (released again at once: acquire takes it)
        except OSError:
            time.sleep(0.05)
        finally:
            os.close(fd)
    return False


class Agent:
    def __init__(
        self,
        target: Target,
        *,
        rules: Any,
        policy: str = "preserve",
        accept_fingerprint: str | None = None,
        quiet: float | None = None,
        cap: float | None = None,
        on_event: Callable[[str], None] | None = None,
        build: dict[str, Any] | None = None,
        own_watcher: bool = True,
    ) -> None:
        """``own_watcher=False``: changes come from outside through :meth:`request` (a fleet
        watch, :mod:`fetchsync.agent.fleet`, whose one watcher feeds every robot's agent)."""
        self.target = target
        self.own_watcher = own_watcher
        self.rules = rules
        self.policy = policy
        self.accept_fingerprint = accept_fingerprint
        self.quiet = quiet
        self.cap = cap
        self.say = on_event or (lambda line: log.info("%s", line))
        self.src = str(target.workspace / "src")
        self.stop_event = threading.Event()
        self.cond = threading.Condition()
        # The first sync checks everything; it is the watcher's first batch (a
        # rescan, due once every watch is in place), not a request of its own:
        # a full push started before the watches would have to be repeated
        # after them, and on a large tree each one costs seconds.
        self.pending = Pending()
        self.next_seq = 1
        self.done_seq = 0  # every request up to this one is on the robot
        self.failed: list[tuple[int, int, str]] = []  # (first, last request, why) of failed pushes
        self.state = "starting"
        self.offline_since: float | None = None
        self.last_sync: float | None = None
        self.last_error = ""
        self.conflicts: list[dict[str, str]] = []
        self.last_report: dict[str, Any] | None = None
        self.held: Pending | None = None  # the work of a push paused before a mass deletion
        self._conn: Any = None
        self._transport: Any = None
        self._syncer: Any = None
        self._state: Any = None
        self._deletions: Any = None  # the mass-deletion guard's count, across connections
        self._lock_fd = -1
        self._last_activity = time.monotonic()  # the last change or request of the user's
        self._link_lock = threading.Lock()  # the monitor closes only the connection it probed
        self.builder: Any = None
        if build is not None:
            from fetchsync.agent.builder import Builder

            self.builder = Builder(
                target, say=self.say, accept_fingerprint=accept_fingerprint, **build
            )

    # ------------------------------------------------------------------ lifecycle
    def acquire(self) -> None:
        """Take the one-agent-per-target lock, or say where the running one is."""
        lock, sock = agent_paths(self.target)

        def busy(owner: str) -> Exception:
            return UsageError(
                f"an agent is already watching {self.src} for {self.target.robot} "
                f"({owner}; socket {sock})",
                hint="stop it first, or use fetchsync status / flush",
            )

        try:
            self._lock_fd = take_lock(lock, busy)
        except UsageError:
            # a resident (fetchsync.agent.resident) serving one-shot pushes: it steps aside
            if not _take_over(lock, sock):
                raise
            self._lock_fd = take_lock(lock, busy)
        self.socket_path = sock

    def release(self) -> None:
        if self._lock_fd >= 0:
            os.close(self._lock_fd)
            self._lock_fd = -1

    def run(self) -> None:
        """Watch and sync until :meth:`stop`; returns within a second or two of it."""
        from fetchsync.agent.control import ControlServer

        map_large_buffers()  # the first sync's freed buffers go back (protocol/heap.py)

        server = ControlServer(self.socket_path, self)
        server.start()
        watcher = threading.Thread(target=self._watch, name="fetchsync-watch", daemon=True)
        if self.own_watcher:
            watcher.start()
        syncer = threading.Thread(target=self._sync_loop, name="fetchsync-sync", daemon=True)
        syncer.start()
        threading.Thread(target=self._monitor, name="fetchsync-monitor", daemon=True).start()
        if self.builder is not None:
            self.builder.start()
        try:
            while not self.stop_event.wait(0.2):
                pass
        finally:
            with self.cond:
                self.cond.notify_all()
            syncer.join(1.5)
            if self.own_watcher:
                watcher.join(0.5)
            server.stop()
            if self.builder is not None:
                self.builder.stop()
            self._disconnect()
            if self._state is not None:
                try:
                    self._state.close()
                except Exception:  # closing at exit: nothing left to protect
                    pass

    def stop(self) -> None:
        self.stop_event.set()
        with self.cond:
            self.cond.notify_all()

    # ------------------------------------------------------------------ requests
    def request(
        self,
        *,
        paths: set[str] | None = None,
        dirs: set[str] | None = None,
        full: bool = False,
        recheck: bool = False,
        activity: bool = True,
    ) -> int:
        """Queue work; returns its sequence number for :meth:`wait_for`. ``activity``:
        the user's (a change, a flush), which ends a reconnection backoff at once."""
        with self.cond:
            if activity:
                self._last_activity = time.monotonic()
            seq = self.next_seq
            self.next_seq += 1
            self.pending.paths |= paths or set()
            self.pending.dirs |= dirs or set()
            self.pending.full |= full
            self.pending.recheck |= recheck
            self.pending.first = self.pending.first or seq
            self.pending.seq = seq
            self.cond.notify_all()
            return seq

    def wait_for(self, seq: int, timeout: float) -> tuple[bool, str]:
        """Wait until request ``seq`` is on the robot: (done, error)."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                for lo, hi, why in self.failed:
                    if lo <= seq <= hi:
                        return False, why
                if self.done_seq >= seq:
                    return True, ""
                left = deadline - time.monotonic()
                if left <= 0 or self.stop_event.is_set():
                    why = (
                        f"the robot is offline since {time.strftime('%H:%M:%S', time.localtime(self.offline_since))}"
                        if self.offline_since
                        else "timed out"
                    )
                    return False, why
                self.cond.wait(min(left, 0.5))

    def status(self) -> dict[str, Any]:
        with self.cond:
            return {
                "state": self.state,
                "robot": self.target.robot,
                "workspace": self.src,
                "remote": self.target.remote_workspace + "/src",
                "pid": os.getpid(),
                "last_sync": self.last_sync,
                "pending": self.pending.count(),
                "offline_since": self.offline_since,
                "conflicts": list(self.conflicts[-20:]),
                "last_error": self.last_error,
                "last_report": self.last_report,
                "build": self.builder.status() if self.builder is not None else None,
            }

    # ------------------------------------------------------------------ threads
    def _watch(self) -> None:
        from fetchsync.agent.watcher import batches

        kwargs: dict[str, Any] = {}
        if self.quiet is not None:
            kwargs["quiet"] = self.quiet
        if self.cap is not None:
            kwargs["cap"] = self.cap
        try:
            for batch in batches(self.src, rules=self.rules, stop_event=self.stop_event, **kwargs):
                mark(f"agent: batch of {len(batch.paths)} paths, {len(batch.dirs)} dirs")
                if batch.rescan:
                    self.request(full=True)
                else:
                    self.request(paths=set(batch.paths), dirs=set(batch.dirs))
        except Exception as exc:  # the agent cannot work without its watcher: say why and stop
            self.last_error = f"watcher failed: {exc}"
            self.say(f"error: {self.last_error}")
            self.stop()

    def _sync_loop(self) -> None:
        from fetchsync.sync.engine import MassDeletionError

        failures = 0  # reconnection attempts that failed in a row
        # connect while the watcher puts its watches in place, so the first
        # sync finds the link up; a failure here is the first sync's to retry
        try:
            self._ensure_connected()
        except (TransportError, ProtocolError, EOFError, OSError) as exc:
            self._went_offline(None, exc)
        except FetchsyncError:
            pass  # not the link (a configuration problem): the first sync reports it
        while not self.stop_event.is_set():
            with self.cond:
                while self.pending.empty() and not self.stop_event.is_set():
                    self.cond.wait(PROBE_EVERY)
                if self.stop_event.is_set():
                    return
                work = self.pending
                self.pending = Pending()
                held, self.held = self.held, None
                if held is not None:
                    # paused before a mass deletion: what changed since may have
                    # restored the files, or confirmed it (a forced push): look again
                    work.paths |= held.paths
                    work.dirs |= held.dirs
                    work.full = True
                    work.first = min((x for x in (work.first, held.first) if x), default=0)
            try:
                self._ensure_connected()
                syncer = self._syncer  # the monitor may close the link any time
                if syncer is None:
                    raise TransportError("the link to the robot was closed")
                self._set_state("syncing")
                t0 = time.monotonic()
                mark("agent: push")
                if work.full or not (work.paths or work.dirs):
                    report = syncer.push()
                else:
                    report = syncer.push_paths(work.paths, work.dirs)
                if work.recheck and not work.full:
                    with self.cond:
                        self.pending.full = True  # next: everything, once these are there
                mark(f"agent: pushed {report.files} files")
                self._settled(work, report, time.monotonic() - t0)
                failures = 0
            except (TransportError, ProtocolError, EOFError, OSError) as exc:
                self._went_offline(work, exc)
                if self._wait_to_retry(failures):
                    return
                failures += 1
            except MassDeletionError as exc:
                self._pause(work, exc)
            except FetchsyncError as exc:
                with self.cond:
                    self.last_error = str(exc)
                    self.failed = self.failed[-50:] + [(work.first, work.seq, str(exc))]
                    self.done_seq = max(self.done_seq, work.seq)
                    self.cond.notify_all()
                self.say(f"error: {exc}")
                self._set_state("live")

    def _pause(self, work: Pending, exc: FetchsyncError) -> None:
        """Hold a push that would delete most of the robot's files until the next change
        or request (``fetchsync push --force`` makes one once it has pushed)."""
        why = f"paused: {exc}; restore the files, or confirm with fetchsync push --force"
        with self.cond:
            self.held = work
            self.last_error = why
            self.failed = self.failed[-50:] + [(work.first, work.seq, why)]
            self.done_seq = max(self.done_seq, work.seq)
            self.state = "paused"
            self.cond.notify_all()
        self.say(why)

    def _retry_delay(self, failures: int) -> float:
        """Seconds until the next reconnection attempt.

        While the user is editing, a quarter of a second, however long the robot has
        been away: each attempt that fails costs little (a refused or hanging
        connection, no handshake), and the one that works brings the edits over within
        that of the link's return (the issue-24 target: link back -> robot identical in
        <= 1 s; capped at 4 s, a user saw "back online after 11.9s" once the robot's
        sshd was back). Only when idle does it back off, doubling up to BACKOFF_CAP.
        """
        if time.monotonic() - self._last_activity < EDITING:
            return RETRY_EDITING
        return min(BACKOFF_FIRST * 2**failures, BACKOFF_CAP)

    def _wait_to_retry(self, failures: int) -> bool:
        """Wait before the next reconnection attempt; a change or request of the user's
        ends the wait. True: stopping."""
        deadline = time.monotonic() + self._retry_delay(failures)
        with self.cond:
            seen = self._last_activity
            while not self.stop_event.is_set() and self._last_activity == seen:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self.cond.wait(left)
        return self.stop_event.is_set()

    def _open_link(self) -> tuple[Any, Any]:
        """A new transport and endpoint connection to the robot."""
        from fetchsync.link.connection import Connection
        from fetchsync.link.session import open_transport

        transport = open_transport(
            self.target, accept_fingerprint=self.accept_fingerprint, persistent=False
        )
        try:
            return transport, Connection.open(transport)
        except BaseException:
            transport.close()
            raise

    def _ensure_connected(self) -> None:
        if self._syncer is not None:
            return
        from fetchsync.sync.engine import Deletions, Syncer
        from fetchsync.sync.state import open_state

        transport, conn = self._open_link()
        if self._state is None:
            self._state = open_state(self.target)
            if self._state.note:
                self.say(f"note: {self._state.note}")
        syncer = Syncer(
            conn,
            self._state,
            local_root=self.src,
            remote_workspace=self.target.remote_workspace,
            rules=self.rules,
            policy=self.policy,
        )
        # an rm -rf's batches on either side of a reconnection are still one deletion,
        # however long the robot was away (the time offline does not count)
        if self._deletions is None:
            self._deletions = Deletions.kept(self._state)  # this agent restarted mid rm -rf
        elif self.offline_since is not None:
            self._deletions.ended += time.monotonic() - self._offline_mono
        syncer.deletions = self._deletions
        with self._link_lock:
            self._transport, self._conn, self._syncer = transport, conn, syncer
        if self.offline_since is not None:
            self.say(f"back online after {time.monotonic() - self._offline_mono:.1f}s")
        with self.cond:
            self.offline_since = None

    def _disconnect(self, *, only: Any = None) -> bool:
        """Close the connection (``only``: if it still is that transport); whether it did."""
        with self._link_lock:
            if only is not None and self._transport is not only:
                return False
            conn, transport = self._conn, self._transport
            self._conn = self._transport = self._syncer = None
        if conn is not None:
            try:
                conn.channel.close()
            except Exception:  # the link is already gone
                pass
        if transport is not None:
            try:
                transport.close()
            except Exception:  # the link is already gone
                pass
        return True

    def _monitor(self) -> None:
        """Notice a dead link within seconds, idle or mid-push.

        A link whose packets stop (a robot out of Wi-Fi range) gives no error
        by itself: a keepalive unanswered for KEEPALIVE_WAIT makes the agent
        offline, and :meth:`_suspect` decides between that connection and a new one.
        """
        while not self.stop_event.wait(PROBE_EVERY):
            transport = self._transport
            if transport is None or not transport.capabilities.keepalive:
                continue
            try:
                answered = transport.ping()
            except Exception:  # a probe that fails in any way means the same
                answered = None
            if answered is not None and answered.wait(KEEPALIVE_WAIT):
                continue
            if transport is self._transport:
                self._suspect(transport, answered)

    def _suspect(self, transport: Any, answered: threading.Event | None) -> None:
        """The robot stopped answering on a connection that has not ended: keep it while
        the robot's sshd is probed, and give it up only once that answers and it does not.

        When packets only stopped (out of Wi-Fi range), what the old connection holds
        is delivered once the link is back and a push blocked on it simply finishes:
        nothing to redo, no handshake, no endpoint to start (bench/watch.py --link
        wifi, 12 s blackholes: link back -> save on the robot went from 1.5 s to
        10-50 ms, p50 22 ms of 5). When the robot lost that connection (it rebooted,
        the laptop's address changed), a new connection gets the sshd's banner while
        the old one stays silent: SUSPECT_GRACE later it is closed, which fails a push blocked on
        it, and the sync loop reconnects and checks everything. A connection silent
        past the call deadline is closed too (a blocked call's own watchdog would end
        it then). The probe stops at the banner: no handshake, no login.
        """
        from fetchsync.link.connection import progress_deadline

        exc = TransportError("the robot stopped answering keepalives")
        self._mark_offline(exc)
        give_up = time.monotonic() + progress_deadline()
        probe: _Attempt | None = None
        reachable_since: float | None = None
        next_probe = time.monotonic()
        while not self.stop_event.is_set():
            if answered is None:  # the connection ended: nothing to wait for
                break
            if answered.wait(0.05):
                if transport is self._transport:
                    self._back_online()
                return
            if transport is not self._transport:
                return  # the sync loop gave it up (its push failed) and reconnects
            now = time.monotonic()
            if now > give_up:
                break
            if reachable_since is not None:
                if now - reachable_since >= SUSPECT_GRACE:
                    break
            elif probe is None and now >= next_probe:
                probe = _Attempt(self._reachable)
            elif probe is not None and probe.done.is_set():
                if probe.result:
                    reachable_since = now
                else:
                    next_probe = now + self._retry_delay(0)
                probe = None
        # only that connection: the sync loop may have replaced it meanwhile
        if self.stop_event.is_set() or not self._disconnect(only=transport):
            return
        self._mark_offline(exc)
        self.request(recheck=True, activity=False)

    def _reachable(self) -> bool:
        """Whether the robot's sshd answers a new connection (its banner, no login)."""
        from fetchsync.link.ssh import sshd_answers

        answer = sshd_answers(self.target.host, user=self.target.user)
        if answer is None:  # through jump hosts: only a login tells
            transport, conn = self._open_link()
            conn.channel.close()
            transport.close()
            return True
        return answer

    def _back_online(self) -> None:
        with self.cond:
            since, self.offline_since = self.offline_since, None
            if since is None:
                return
            self.state = "live" if self.pending.empty() else "syncing"
            self.cond.notify_all()
        self.say(f"back online after {time.monotonic() - self._offline_mono:.1f}s")

    def _went_offline(self, work: Pending | None, exc: BaseException) -> None:
        self._disconnect()
        self._mark_offline(exc, work)

    def _mark_offline(self, exc: BaseException, work: Pending | None = None) -> None:
        with self.cond:
            if work is not None:
                # keep what was not synced, and check everything once back
                self.pending.paths |= work.paths
                self.pending.dirs |= work.dirs
                self.pending.full |= work.full
                self.pending.recheck = True
                self.pending.seq = max(self.pending.seq, work.seq)
                self.pending.first = (
                    min(x for x in (self.pending.first, work.first) if x)
                    if (self.pending.first or work.first)
                    else 0
                )
            if self.offline_since is None:
                self.offline_since = time.time()
                self._offline_mono = time.monotonic()
                self.say(f"offline: {exc}; changes are kept and sent when the robot is back")
            self.state = "offline"
            self.last_error = str(exc)
            self.cond.notify_all()

    def _settled(self, work: Pending, report: Any, seconds: float) -> None:
        with self.cond:
            self.last_sync = time.time()
            self.last_report = report.to_json()
            self.conflicts.extend(report.conflicts)
            if report.errors:
                self.last_error = f"{report.errors[0]['path']}: {report.errors[0]['error']}"
                self.failed = self.failed[-50:] + [(work.first, work.seq, self.last_error)]
            self.done_seq = max(self.done_seq, work.seq)
            self.state = "live" if self.pending.empty() else "syncing"
            self.cond.notify_all()
        if report.changed or report.conflicts or report.errors:
            line = (
                f"pushed {report.files} files, {report.dirs} dirs, {report.deleted} deleted "
                f"in {seconds * 1000:.0f} ms"
            )
            self.say(line)
            for c in report.conflicts:
                self.say(
                    f"conflict: {c['path']} was changed on the robot; kept in {c.get('kept', '')}"
                )
            for e in report.errors:
                self.say(f"error: {e['path']}: {e['error']}")
        if self.builder is not None and report.changed:
            # what the batch touched; a full push of unknown changes (a rescan) builds everything
            known = work.paths or work.dirs
            self.builder.submit_paths(work.paths, work.dirs, whole=work.full and not known)
        if self.state == "live" and not getattr(self, "_announced", False):
            self._announced = True
            self.say(f"live: {self.src} -> {self.target.robot}:{self.target.remote_workspace}/src")
        if report.files + report.dirs + report.deleted >= RELEASE_AFTER:
            # not after a full sync that changed little (the start-up rescan of an
            # unchanged tree): its entries are the ones loaded from the state
            self._compact()

    def _compact(self) -> None:
        """Rebuild the syncer's last-synced entries from the state, then release memory.

        The entries a large sync leaves in memory were made one by one between
        its hundreds of thousands of temporaries, so once those are freed the
        survivors still pin most of the allocator's pages. Loaded again in one
        go they sit together: after a first sync of 100,000 files the agent
        stays at ~190 MB resident instead of ~365 MB (bench/scale.py), for
        one read of the state (~0.5 s there).
        """
        if self._syncer is not None:
            self._syncer.reload_entries()
        release_memory()

    def _set_state(self, state: str) -> None:
        with self.cond:
            self.state = state


class _Attempt:
    """One probe in its own thread (it can hang until the link is back)."""

    def __init__(self, probe: Callable[[], bool]) -> None:
        self.result = False
        self.done = threading.Event()
        self._probe = probe
        threading.Thread(target=self._run, name="fetchsync-probe", daemon=True).start()

    def _run(self) -> None:
        try:
            self.result = self._probe()
        except Exception as exc:  # noqa: BLE001 - any failure means: not reachable yet
            log.debug("probe of the robot failed: %s", exc)
        finally:
            self.done.set()
