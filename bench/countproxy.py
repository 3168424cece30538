#!/usr/bin/env python3
"""Count the bytes of SSH connections, and shape their link: ``countproxy.py HOST PORT COUNTDIR [LINK]``.

Used as the ssh ``ProxyCommand`` of both OpenSSH (rsync's and lsyncd's
transport) and paramiko (fetchsync's), so both tools' bytes on the wire are
counted, and their link shaped, the same way: the encrypted SSH stream, key
exchange and authentication included.

It connects to HOST:PORT and copies stdin to the socket and the socket to
stdout. Each connection keeps its counters in ``COUNTDIR/<pid>.count``: three
little-endian u64, *up* (client to server), *down* (server to client) and
*done* (1 once the proxy has stopped), updated in place (mmap) as bytes pass,
then a fourth, the proxy's own CPU time in microseconds (user + system),
written as it stops: what the bench's link itself cost the machine.

**The link.** ``LINK`` is one of :data:`LINKS` (``loopback``, the default:
bytes pass as fast as they come; ``wifi``: 40 Mbit/s and 4 ms each way;
``weak``: 8 Mbit/s and 25 ms each way) or ``RATE_MBIT:DELAY_MS``. This
kernel has no ``netem``, so the proxy models the link itself, per direction,
as a router's queue in front of a wire:

- *serialisation*: the bytes leave one after the other at the link's rate,
  cut into segments of about a millisecond of the rate (at least 1448 bytes,
  one TCP segment; at most 16 KiB), so a large write streams rather than
  arriving at once; a segment leaves when the one before it has left;
- *propagation*: every segment is delivered a fixed one-way delay after it
  left, however small it is, so a request and its answer cost at least two
  delays (a round trip);
- *a bounded queue*: once the bytes waiting to leave would take more than
  :data:`QUEUE_SECONDS` at the rate, the proxy stops reading from the sender
  until the queue drains, and the sender's socket buffers fill as over a real
  link (TCP's flow control), instead of the proxy buffering without bound.

Each direction has a reader thread (counts, timestamps, queues) and a writer
thread (sleeps until a segment's arrival time, writes every segment due).
Counts are taken when the proxy reads the bytes, shaped or not.

**Outages** (shaped links only), for measuring recovery: the file
``COUNTDIR/link.state`` (:func:`set_link_state`) says ``up`` (or is absent),
``blackhole`` or ``cut``, and every proxy of that directory looks at it every
20 ms. *blackhole*: nothing is read or delivered, in either direction, and
a new connection hangs before connecting (its SYN lost); once ``up`` again,
what was held is delivered at once (TCP's retransmissions, without their
backoff). *cut*: every open connection ends at once, and a new one fails at
once (connection refused) while it lasts.

Counters are live rather than written at exit because a connection may outlive
the command that opened it: fetchsync leaves a connection master holding its
SSH connection between calls. The bytes one push costs are then the growth of
the sum over all connections while it ran, counted until the counters are
quiet (:func:`Counter.settle`), so a master's handshake, its re-warmed
endpoint and channel closes count to the push that caused them.

The proxy stops on EOF from the server (once what it sent is delivered), EOF
from the client once the server closes, or the SIGHUP / SIGTERM its client
sends when it closes the connection (OpenSSH sends SIGHUP, paramiko SIGTERM).
"""

from __future__ import annotations

# Only what the proxy needs at its start, which every connection pays (dataclasses,
# pathlib and typing took 30 of its 55 ms of CPU): twenty of a fleet start at once.
import collections
import contextlib
import mmap
import os
import select
import signal
import socket
import struct
import sys
import threading
import time

TYPE_CHECKING = False
if TYPE_CHECKING:
    from pathlib import Path
    from typing import Callable

__all__ = ["LINKS", "Counter", "Link", "Totals", "link_state", "parse_link", "set_link_state"]

_CHUNK = 64 * 1024
_REC = struct.Struct("<QQQ")
_U64 = struct.Struct("<Q")
_CPU_AT = _REC.size  # the fourth u64: the proxy's CPU microseconds, once it stopped
_FILE_SIZE = _REC.size + _U64.size

STATE_FILE = "link.state"
STATES = ("up", "blackhole", "cut")

QUEUE_SECONDS = 0.025
"""The most a direction's queue holds, in time at its rate, before the sender is held back."""


class Link(collections.namedtuple("Link", "name rate delay")):
    """A symmetric link: ``rate`` bytes a second and ``delay`` seconds one way, each direction
    (``name``: a profile of :data:`LINKS`, or ``RATE_MBIT:DELAY_MS``). Immutable."""

    __slots__ = ()
    name: str
    rate: float
    delay: float

    @property
    def segment(self) -> int:
        """Bytes serialised as one piece: about a millisecond at the rate (1448 to 16 KiB)."""
        return int(min(16384, max(1448, self.rate / 1000)))

    def describe(self) -> str:
        return f"{self.name} ({self.rate * 8 / 1e6:g} Mbit/s, {self.delay * 1000:g} ms each way)"


LINKS: dict[str, Link | None] = {
    "loopback": None,
    "wifi": Link("wifi", 40e6 / 8, 0.004),
    "weak": Link("weak", 8e6 / 8, 0.025),
}


def link_state(countdir: str | Path) -> str:
    """``up``, ``blackhole`` or ``cut``: what ``COUNTDIR/link.state`` says (``up`` if absent)."""
    try:
        with open(os.path.join(countdir, STATE_FILE)) as fh:
            state = fh.read().strip()
    except OSError:
        return "up"
    return state if state in STATES else "up"


def set_link_state(countdir: str | Path, state: str) -> None:
    """Put every shaped proxy of ``countdir`` (and every one started later) into ``state``."""
    if state not in STATES:
        raise ValueError(f"link state {state!r}: one of {', '.join(STATES)}")
    path = os.path.join(countdir, STATE_FILE)
    with open(path + ".tmp", "w") as fh:
        fh.write(state + "\n")
    os.replace(path + ".tmp", path)


def parse_link(text: str) -> Link | None:
    """A name of :data:`LINKS`, or ``RATE_MBIT:DELAY_MS``; None: not shaped (loopback)."""
    if text in LINKS:
        return LINKS[text]
    try:
        rate, delay = (float(x) for x in text.split(":"))
    except ValueError:
        raise ValueError(
            f"unknown link {text!r}: one of {', '.join(LINKS)} or RATE_MBIT:DELAY_MS"
        ) from None
    if rate <= 0 or delay < 0:
        raise ValueError(f"link {text!r}: the rate must be positive and the delay not negative")
    return Link(text, rate * 1e6 / 8, delay / 1000)


class _Stop(Exception):
    pass


def _on_signal(signum: int, frame: object) -> None:
    raise _Stop()


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _open_counts(countdir: str, name: str = "") -> mmap.mmap:
    os.makedirs(countdir, exist_ok=True)
    path = os.path.join(countdir, f"{name or os.getpid()}.count")
    fd = os.open(path + ".tmp", os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
    os.ftruncate(fd, _FILE_SIZE)
    counts = mmap.mmap(fd, _FILE_SIZE)
    os.close(fd)
    os.replace(path + ".tmp", path)  # readers never see a short file
    return counts


def proxy(host: str, port: int, countdir: str, link: Link | None = None) -> int:
    for sig in (signal.SIGHUP, signal.SIGTERM, signal.SIGINT, signal.SIGPIPE):
        signal.signal(sig, _on_signal)
    counts = _open_counts(countdir)
    if link is not None:
        return _shaped(host, port, counts, link, countdir)
    up = down = 0
    try:
        sock = socket.create_connection((host, port))
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        stdin, stdout = sys.stdin.fileno(), sys.stdout.fileno()
        reading = {stdin, sock.fileno()}
        while reading:
            ready, _, _ = select.select(list(reading), [], [])
            if stdin in ready:
                data = os.read(stdin, _CHUNK)
                if data:
                    up += len(data)
                    _REC.pack_into(counts, 0, up, down, 0)
                    sock.sendall(data)
                else:
                    reading.discard(stdin)
                    sock.shutdown(socket.SHUT_WR)
            if sock.fileno() in ready:
                data = sock.recv(_CHUNK)
                if data:
                    down += len(data)
                    _REC.pack_into(counts, 0, up, down, 0)
                    _write_all(stdout, data)
                else:
                    break  # the server is done: nothing more can be said to it
    except (_Stop, OSError):
        pass
    finally:
        _stopped(counts, up, down)
        counts.close()
    return 0


def _stopped(counts: mmap.mmap, up: int, down: int, *, cpu: bool = True) -> None:
    """The final counts, this process's CPU time (``cpu``: a proxy of its own), then *done*."""
    if cpu:
        t = os.times()
        _U64.pack_into(counts, _CPU_AT, int((t.user + t.system) * 1e6))
    _REC.pack_into(counts, 0, up, down, 1)


class _Direction:
    """One direction of a shaped link: a reader thread queues, a writer thread delivers.

    Byte ``i`` of what was read at ``t`` leaves the queue at ``max(t, when the last byte
    before it left) + (i + 1) / rate``; it is written out ``delay`` after the segment it
    is in has left. Each read is one entry of the queue (its segments' times follow from
    where it starts), and the writer writes every segment due in one call: a Python
    wake-up per read and per segment due, not several per segment (the twenty links of a
    fleet push shaped 60 MiB: ~23 ms of CPU per MiB each, now ~10).
    """

    def __init__(
        self,
        link: Link,
        *,
        read: Callable[[], bytes],
        write: Callable[[bytes], None],
        count: Callable[[int], None],
        at_eof: Callable[[], None],
        failed: Callable[[], None],
        up: threading.Event,
    ) -> None:
        self.link = link
        self.up = up  # cleared while the link is a blackhole
        self.read, self.write, self.count = read, write, count
        self.at_eof, self.failed = at_eof, failed
        # (when its first byte starts to leave, the bytes; None: EOF at that time)
        self.queue: collections.deque[tuple[float, bytes | None]] = collections.deque()
        self.cond = threading.Condition()
        self.free_at = 0.0  # when the last queued byte has left
        for target in (self._reader, self._writer):
            threading.Thread(target=target, daemon=True).start()

    def _reader(self) -> None:
        link = self.link
        try:
            while True:
                self.up.wait()
                data = self.read()
                if not data:
                    break
                self.count(len(data))
                now = time.monotonic()
                start = max(now, self.free_at)
                self.free_at = start + len(data) / link.rate
                with self.cond:
                    self.queue.append((start, data))
                    self.cond.notify()
                backlog = self.free_at - now - QUEUE_SECONDS
                if backlog > 0:  # the queue is full: hold the sender back
                    time.sleep(backlog)
        except OSError:
            pass
        with self.cond:  # EOF (or a read error) after what was read is delivered
            self.queue.append((max(time.monotonic(), self.free_at), None))
            self.cond.notify()

    def _writer(self) -> None:
        seg, rate, delay = self.link.segment, self.link.rate, self.link.delay
        done = 0  # bytes of the queue's first entry written
        try:
            while True:
                with self.cond:
                    while not self.queue:
                        self.cond.wait()
                    entries = list(self.queue)
                now = time.monotonic()
                out: list[memoryview] = []
                eof = False
                finished = 0
                wake = 0.0
                for start, data in entries:
                    if data is None:
                        if start + delay <= now:
                            eof = True
                        else:
                            wake = start + delay
                        break
                    # the segments of this entry that have arrived: whole ones, or all of it
                    due = int((now - delay - start) * rate)
                    due = len(data) if due >= len(data) else due - due % seg
                    if due > done:
                        out.append(memoryview(data)[done:due])
                        done = due
                    if done < len(data):
                        end = min(done + seg, len(data))
                        wake = start + end / rate + delay
                        break
                    finished += 1
                    done = 0
                if finished:
                    with self.cond:
                        for _ in range(finished):
                            self.queue.popleft()
                if out:
                    self.up.wait()
                    self.write(b"".join(out))
                if eof:
                    self.at_eof()
                    return
                if wake:
                    wait = wake - time.monotonic()
                    if wait > 0:
                        time.sleep(wait)
        except OSError:
            self.failed()


def _shaped(host: str, port: int, counts: mmap.mmap, link: Link, countdir: str) -> int:
    up = down = 0
    done = threading.Event()
    link_up = threading.Event()

    def apply_state() -> bool:
        """Follow ``link.state``; False once the link is cut (the connection ends)."""
        state = link_state(countdir)
        if state == "cut":
            done.set()
            return False
        if state == "blackhole":
            link_up.clear()
        else:
            link_up.set()
        return True

    def watch_state() -> None:
        changes = _state_changes(countdir)
        if changes is None:  # no inotify: look every 20 ms
            while not done.is_set() and apply_state():
                time.sleep(0.02)
            return
        while apply_state():  # woken by a change of the directory only: no CPU while idle
            changes()

    def count_up(n: int) -> None:
        nonlocal up
        up += n
        _U64.pack_into(counts, 0, up)

    def count_down(n: int) -> None:
        nonlocal down
        down += n
        _U64.pack_into(counts, 8, down)

    refused = False
    try:
        while link_state(countdir) == "blackhole":  # the SYN is lost until the link is back
            time.sleep(0.02)
        if link_state(countdir) == "cut":
            refused = True
            raise OSError("the link is cut")
        link_up.set()
        threading.Thread(target=watch_state, daemon=True).start()
        sock = socket.create_connection((host, port))
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        stdin, stdout = sys.stdin.fileno(), sys.stdout.fileno()

        def end_up() -> None:
            try:
                sock.shutdown(socket.SHUT_WR)
            except OSError:
                done.set()

        _Direction(
            link,
            read=lambda: os.read(stdin, _CHUNK),
            write=sock.sendall,
            count=count_up,
            at_eof=end_up,
            failed=done.set,
            up=link_up,
        )
        _Direction(
            link,
            read=lambda: sock.recv(_CHUNK),
            write=lambda data: _write_all(stdout, data),
            count=count_down,
            at_eof=done.set,  # the server is done: nothing more can be said to it
            failed=done.set,
            up=link_up,
        )
        while not done.wait(1.0):
            pass
    except (_Stop, OSError):
        pass
    finally:
        _stopped(counts, up, down)
        counts.flush()
    os._exit(1 if refused else 0)  # the threads may be blocked reading: do not wait for them


def serve(host: str, port: int, countdir: str, link: Link | None) -> int:
    """The link as a server: listen on a port of 127.0.0.1 (printed on stdout, one line)
    and shape every connection made to it to ``host:port`` as :func:`proxy` does, each
    counted in its own ``COUNTDIR/<pid>-<n>.count``; until SIGTERM.

    One process for every connection of a robot: a proxy started per connection costs
    ~40 ms of CPU (an interpreter's start), twenty at once in a fleet push, where a real
    link costs the laptop nothing; and the client connects over TCP, as to a robot, not
    through a ProxyCommand's pipes. The process's CPU is the link's (its /proc stat);
    the count files carry no CPU of their own. Outages as :func:`proxy`'s: ``blackhole``
    holds new connections before they reach the server and what open ones carry; ``cut``
    ends every open connection and closes new ones at once."""
    for sig in (signal.SIGHUP, signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, _on_signal)
    signal.signal(signal.SIGPIPE, signal.SIG_IGN)
    os.makedirs(countdir, exist_ok=True)
    link_up = threading.Event()
    conns: set[threading.Event] = set()
    lock = threading.Lock()

    def apply_state() -> str:
        state = link_state(countdir)
        if state == "blackhole":
            link_up.clear()
        else:
            link_up.set()
        if state == "cut":
            with lock:
                for done in conns:
                    done.set()
        return state

    def watch_state() -> None:
        changes = _state_changes(countdir)
        while True:
            apply_state()
            if changes is None:
                time.sleep(0.02)
            else:
                changes()

    apply_state()
    threading.Thread(target=watch_state, daemon=True).start()
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", 0))
    listener.listen(128)
    sys.stdout.write(f"{listener.getsockname()[1]}\n")
    sys.stdout.flush()
    n = 0
    try:
        while True:
            client, _ = listener.accept()
            n += 1
            threading.Thread(
                target=_serve_one,
                args=(client, host, port, countdir, f"{os.getpid()}-{n}", link),
                kwargs={"link_up": link_up, "conns": conns, "lock": lock},
                daemon=True,
            ).start()
    except _Stop:
        pass
    return 0


def _serve_one(
    client: socket.socket,
    host: str,
    port: int,
    countdir: str,
    name: str,
    link: Link | None,
    *,
    link_up: threading.Event,
    conns: set[threading.Event],
    lock: threading.Lock,
) -> None:
    """One connection of :func:`serve`: held while the link is a blackhole, closed at once
    while it is cut, else shaped (or copied, unshaped) both ways until either end is done."""
    counts = _open_counts(countdir, name)
    done = threading.Event()
    up = down = 0
    # A direction's thread may still count a last chunk after the connection ended and
    # the counters were closed (a TypeError from pack_into on a closed mmap once): the
    # counts go under a lock and stop when the connection's record is final.
    counting = threading.Lock()
    final = False

    def count_up(k: int) -> None:
        nonlocal up
        with counting:
            if not final:
                up += k
                _U64.pack_into(counts, 0, up)

    def count_down(k: int) -> None:
        nonlocal down
        with counting:
            if not final:
                down += k
                _U64.pack_into(counts, 8, down)

    sock = None
    try:
        if link is not None:
            while link_state(countdir) == "blackhole":  # the SYN is lost until the link is back
                time.sleep(0.02)
            if link_state(countdir) == "cut":
                return
        with lock:
            conns.add(done)
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock = socket.create_connection((host, port))
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        server = sock

        def end_up() -> None:
            try:
                server.shutdown(socket.SHUT_WR)
            except OSError:
                done.set()

        for read, write, count, at_eof in (
            (lambda: client.recv(_CHUNK), server.sendall, count_up, end_up),
            (lambda: server.recv(_CHUNK), client.sendall, count_down, done.set),
        ):
            if link is None:
                threading.Thread(
                    target=_copy, args=(read, write, count, at_eof, done.set), daemon=True
                ).start()
            else:
                _Direction(
                    link,
                    read=read,
                    write=write,
                    count=count,
                    at_eof=at_eof,
                    failed=done.set,
                    up=link_up,
                )
        done.wait()
    except OSError:
        pass
    finally:
        with lock:
            conns.discard(done)
        for s in (client, sock):
            if s is not None:
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
                s.close()
        with counting:
            final = True
            _stopped(counts, up, down, cpu=False)
            counts.close()


def _copy(
    read: Callable[[], bytes],
    write: Callable[[bytes], None],
    count: Callable[[int], None],
    at_eof: Callable[[], None],
    failed: Callable[[], None],
) -> None:
    """One direction of an unshaped connection of :func:`serve`."""
    try:
        while True:
            data = read()
            if not data:
                break
            count(len(data))
            write(data)
    except OSError:
        failed()
        return
    at_eof()


_IN_CREATE, _IN_CLOSE_WRITE, _IN_MOVED_TO = 0x100, 0x8, 0x80


def _state_changes(countdir: str) -> Callable[[], None] | None:
    """A function that blocks until something in ``countdir`` changes (inotify), or None
    where inotify is not to be had. One Python wake-up per change, instead of a look at
    ``link.state`` every 20 ms: twenty links of a fleet looked 1,000 times a second."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        fd = libc.inotify_init1(os.O_CLOEXEC)
        if fd < 0:
            return None
        mask = _IN_CREATE | _IN_CLOSE_WRITE | _IN_MOVED_TO
        if libc.inotify_add_watch(fd, os.fsencode(countdir), mask) < 0:
            os.close(fd)
            return None
    except (OSError, AttributeError):
        return None
    return lambda: None if os.read(fd, 4096) else None


class Totals:
    """Bytes over all connections in a count directory at one moment."""

    def __init__(self, per_conn: dict[str, tuple[int, int, bool]]) -> None:
        self.per_conn = per_conn

    @property
    def up(self) -> int:
        return sum(u for u, _d, _e in self.per_conn.values())

    @property
    def down(self) -> int:
        return sum(d for _u, d, _e in self.per_conn.values())

    @property
    def live(self) -> int:
        return sum(not e for _u, _d, e in self.per_conn.values())

    def key(self) -> tuple[int, int, int, int]:
        return (len(self.per_conn), self.up, self.down, self.live)


class Counter:
    """Reads the counters the proxies of one count directory keep."""

    def cpu(self) -> float:
        """CPU seconds the stopped proxies of this directory used (their own report)."""
        total = 0
        for p in self.dir.glob("*.count"):
            with contextlib.suppress(OSError, struct.error):
                data = p.read_bytes()
                if len(data) >= _FILE_SIZE and _REC.unpack(data[: _REC.size])[2]:
                    total += _U64.unpack(data[_CPU_AT:_FILE_SIZE])[0]
        return total / 1e6

    def __init__(self, countdir: Path) -> None:
        from pathlib import Path

        self.dir = Path(countdir)
        self.dir.mkdir(parents=True, exist_ok=True)

    def read(self) -> Totals:
        out: dict[str, tuple[int, int, bool]] = {}
        for p in self.dir.glob("*.count"):
            try:
                up, down, done = _REC.unpack(p.read_bytes()[: _REC.size])
            except (OSError, struct.error):
                continue
            out[p.stem] = (up, down, bool(done))
        return Totals(out)

    def settle(
        self, *, quiet: float = 0.3, timeout: float = 10.0, live: int | None = None
    ) -> Totals:
        """The totals once nothing has moved for ``quiet`` seconds.

        With ``live`` given, also wait until that many connections are still
        open (0: every proxy has stopped).
        """
        deadline = time.monotonic() + timeout
        last = self.read()
        since = time.monotonic()
        while True:
            time.sleep(0.02)
            now = self.read()
            if now.key() != last.key():
                last, since = now, time.monotonic()
            elif time.monotonic() - since >= quiet and (live is None or now.live <= live):
                return now
            if time.monotonic() > deadline:
                if live is not None and now.live > live:
                    raise TimeoutError(
                        f"{self.dir}: {now.live} connection(s) still open, expected at most {live}"
                    )
                return now


def proxy_command(host: str, port: int, countdir: Path, link: Link | None) -> str:
    """The ``ProxyCommand`` line that runs this proxy (``-S``: no site, a faster start).

    It imports this module from its compiled bytecode, made here once (a script run as
    ``python3 countproxy.py`` is compiled from source at every start: ~8 of a proxy's
    ~30 ms of CPU, paid by every connection, twenty at once in a fleet push)."""
    import py_compile
    import shlex
    from importlib.util import cache_from_source

    here = os.path.realpath(__file__)
    try:
        cached = cache_from_source(here)
        if not os.path.exists(cached) or os.stat(cached).st_mtime < os.stat(here).st_mtime:
            py_compile.compile(here, cfile=cached, doraise=True)
        stub = (
            f"import sys; sys.path.insert(0, {os.path.dirname(here)!r}); "
            "import countproxy; countproxy.main(sys.argv[1:])"
        )
        argv = [sys.executable, "-S", "-c", stub]
    except (OSError, py_compile.PyCompileError):  # a read-only checkout: from source
        argv = [sys.executable, "-S", here]
    argv += [host, str(port), str(countdir)]
    if link is not None:
        argv.append(
            link.name if link.name in LINKS else f"{link.rate * 8 / 1e6:g}:{link.delay * 1000:g}"
        )
    return shlex.join(argv)


def main(args: list[str]) -> int:
    serving = args[:1] == ["--serve"]
    if serving:
        args = args[1:]
    if len(args) not in (3, 4):
        sys.exit(
            "usage: countproxy.py [--serve] HOST PORT COUNTDIR [loopback|wifi|weak|RATE_MBIT:DELAY_MS]"
        )
    try:
        shaping = parse_link(args[3]) if len(args) == 4 else None
    except ValueError as e:
        sys.exit(f"countproxy.py: {e}")
    if serving:
        return serve(args[0], int(args[1]), args[2], shaping)
    return proxy(args[0], int(args[1]), args[2], shaping)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
