"""The one connection object through which everything talks to a robot.

A :class:`Connection` starts the robot-side endpoint over a transport (SSH, or
the ``local`` robot), delivers it when the robot's cache lacks it, does the
handshake and then carries request/response frames. Requests may be pipelined:
``send()`` returns an id, ``wait()`` collects its response.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from typing import Any, Callable

from fetchsync.errors import ConnectError, LinkLostError, ProtocolError, RemoteError
from fetchsync.link.transport import Channel, Transport
from fetchsync.protocol import hashing, wire
from fetchsync.protocol.loader import LOADER_BYTES, NEED, NEED_LOADER, loader_spec
from fetchsync.trace import mark

log = logging.getLogger(__name__)

DEFAULT_PYTHON = "python3"
DEFAULT_DEADLINE = 30.0
SEND_PIECE = 256 * 1024
# seconds without a byte from the robot before a waiting request checks the link
LIVENESS_INTERVAL = 5.0


def progress_deadline() -> float:
    """Seconds a call waits on the robot without a byte moving either way before it
    gives up: ``$FETCHSYNC_DEADLINE``, default 30."""
    try:
        value = float(os.environ.get("FETCHSYNC_DEADLINE", DEFAULT_DEADLINE))
    except ValueError:
        return DEFAULT_DEADLINE
    return value if value > 0 else DEFAULT_DEADLINE


class _Watchdog:
    """Ends a call whose robot stopped making progress, with one clear error.

    An SSH keepalive proves the link and sshd alive, not the endpoint: a robot
    endpoint stopped, or blocked in I/O, with the link up, would keep a call
    waiting forever. While the call waits on the robot (``waiting()``: its hello
    not yet in, or requests unanswered) and no byte moves either way
    (``progress()``) for ``deadline`` seconds, the channel is closed: whatever is
    blocked on it wakes up, and :attr:`fired` is the error to report.
    """

    def __init__(
        self,
        channel: Channel,
        name: str,
        deadline: float,
        *,
        progress: Callable[[], Any],
        waiting: Callable[[], bool],
    ) -> None:
        self.channel = channel
        self.name = name
        self.deadline = deadline
        self.progress = progress
        self.waiting = waiting
        self.fired: LinkLostError | None = None
        self.on_fire: Callable[[LinkLostError], None] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fetchsync-deadline", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        tick = min(1.0, self.deadline / 5)
        last = self.progress()
        since = time.monotonic()
        while not self._stop.wait(tick):
            now = self.progress()
            if now != last or not self.waiting():
                last, since = now, time.monotonic()
                continue
            if time.monotonic() - since >= self.deadline:
                self.fired = LinkLostError(
                    f"{self.name} made no progress for {self.deadline:g} s (is its fetchsync "
                    "endpoint stopped or blocked?); gave up"
                )
                if self.on_fire is not None:
                    self.on_fire(self.fired)
                self.channel.close()
                return

    def stop(self) -> None:
        self._stop.set()


def remote_python() -> str:
    """The robot's Python: ``$FETCHSYNC_REMOTE_PYTHON`` or ``python3``."""
    return os.environ.get("FETCHSYNC_REMOTE_PYTHON") or DEFAULT_PYTHON


class Connection:
    def __init__(
        self,
        transport: Transport,
        channel: Channel,
        reader: wire.Reader,
        hello: dict[str, Any],
        algorithm: str,
        compress: bool,
        watchdog: _Watchdog | None = None,
    ) -> None:
        self.transport = transport
        self.channel = channel
        self.reader = reader
        self.hello = hello
        self.algorithm = algorithm
        self.compress = compress
        self.bytes_out = 0
        self._next_id = 1
        self._pending: dict[int, wire.Frame] = {}
        self._lock = threading.Lock()
        # one frame at a time on the channel: a round abandoned mid-send lets its sender
        # finish the frame it is sending (engine._Batcher.close) while the caller may
        # already send the next push's requests (the watch agent keeps its connection)
        self._sending = threading.Lock()
        # responses are read as they come, whatever the main thread is doing:
        # a client that writes a long pipeline before reading would otherwise
        # deadlock with an endpoint blocked on writing its first answer
        self._arrived = threading.Condition()
        self._failure: BaseException | None = None
        self._owed: set[int] = set()  # requests sent (or being sent) and not answered yet
        # when the latest answer arrived (time.monotonic()): any answered request's came
        # at or before it (a push's sender tells how long the link sat idle by it, with
        # every batch answered, without polling: engine._Batcher._next_packed)
        self.last_arrival = 0.0
        self._watchdog = watchdog
        if watchdog is not None:
            watchdog.progress = lambda: (self.reader.bytes_in, self.bytes_out)
            watchdog.waiting = lambda: bool(self._owed)
            watchdog.on_fire = self._fail
        self.ping_id: int | None = None  # a ping sent at open (see open)
        self._reader = threading.Thread(
            target=self._read_loop, name="fetchsync-reader", daemon=True
        )
        self._reader.start()

    def _read_loop(self) -> None:
        failure: BaseException
        try:
            while True:
                frame = self.reader.read_frame()
                if frame is None:
                    failure = LinkLostError(
                        f"the fetchsync endpoint on {self.transport.name} went away"
                    )
                    break
                if frame.type == wire.T_PROGRESS:  # its bytes are the progress the watchdog sees
                    continue
                with self._arrived:
                    self._pending[frame.req_id] = frame
                    self._owed.discard(frame.req_id)
                    self.last_arrival = time.monotonic()
                    self._arrived.notify_all()
        except EOFError:
            failure = LinkLostError(f"the connection to {self.transport.name} ended mid-request")
        except (ProtocolError, LinkLostError) as exc:
            failure = exc
        except Exception as exc:  # anything else from the transport ends the session, reported
            failure = LinkLostError(f"the connection to {self.transport.name} failed: {exc}")
        self._fail(failure)

    def _fail(self, failure: BaseException) -> None:
        """Record why the session ended (the first reason wins) and wake the waiters."""
        with self._arrived:
            if self._failure is None:
                self._failure = failure
            self._arrived.notify_all()

    @property
    def bytes_in(self) -> int:
        return self.reader.bytes_in

    # ------------------------------------------------------------------ setup
    @classmethod
    def open(
        cls,
        transport: Transport,
        *,
        python: str | None = None,
        meanwhile: Callable[[Callable[[], bool]], Any] | None = None,
        ping: bool = False,
    ) -> Connection:
        """Start the endpoint on the robot and exchange hellos.

        ``meanwhile`` runs once the endpoint's command is sent, while the robot
        starts its shell and Python (a few tenths of a second on a direct
        connection): work that needs no answer from the robot. It is given a
        function that tells whether the start-up is over (the endpoint's hello is
        in and ours sent, or the start failed): work that can as well be done
        later, under a request's round trip, is better left then (a connection
        master's warm endpoint says hello within milliseconds).
        Meanwhile a thread of ours answers the robot as soon as it speaks: sends
        the endpoint when its loader asks, and our hello when its hello comes, so
        the start-up's round trips run under the local work instead of after it.

        ``ping`` also sends a ping right after our hello, as the first request: its
        id is :attr:`ping_id`, and waiting for it (:meth:`wait`) proves that the
        endpoint answers before anything else is asked of it (an endpoint handed
        over by a connection master, see session.open_connection). Its round trip
        runs under ``meanwhile`` too.
        """
        return cls._open(transport, python or remote_python(), meanwhile, ping)

    @classmethod
    def _open(
        cls,
        transport: Transport,
        python: str,
        meanwhile: Callable[[Callable[[], bool]], Any] | None,
        ping: bool = False,
    ) -> Connection:
        command, archive = loader_spec(python)
        mark("connection: imported, the loader's command made")
        channel = transport.exec(command)
        mark("connection: the endpoint's command sent")
        reader = wire.Reader(channel.recv)
        starting = threading.Event()  # the start-up waits on the robot
        starting.set()
        watchdog = _Watchdog(
            channel,
            transport.name,
            progress_deadline(),
            progress=lambda: reader.bytes_in,
            waiting=starting.is_set,
        )
        done: list[Connection] = []
        failed: list[BaseException] = []

        def start() -> None:
            try:
                done.append(
                    cls._handshake(transport, channel, reader, archive, watchdog, ping=ping)
                )
            except BaseException as exc:  # raised in the caller's thread
                failed.append(exc)
            finally:
                starting.clear()

        if meanwhile is None:
            start()
        else:
            helper = threading.Thread(target=start, name="fetchsync-start", daemon=True)
            helper.start()
            try:
                meanwhile(lambda: not starting.is_set())
                mark("connection: the local work meanwhile done")
            except BaseException:
                watchdog.stop()
                channel.close()  # wakes the helper if it still waits on the robot
                helper.join(1.0)
                if done:
                    done[0].close()
                raise
            helper.join()
        if failed:
            watchdog.stop()
            raise failed[0]
        return done[0]

    @classmethod
    def _handshake(
        cls,
        transport: Transport,
        channel: Channel,
        reader: wire.Reader,
        archive: Callable[[], bytes],
        watchdog: _Watchdog,
        *,
        ping: bool,
    ) -> Connection:
        """Deliver the endpoint if its loader asks, read its hello, send ours (and a ping)."""
        try:
            sent = cls._deliver(channel, reader, archive)
            hello = reader.read_hello()
            mark("connection: the endpoint's hello in")
        except EOFError as exc:
            if watchdog.fired is not None:
                raise watchdog.fired from exc
            raise cls._startup_error(transport, channel, exc) from exc
        except ProtocolError:
            channel.close()
            raise
        except LinkLostError as exc:
            if watchdog.fired is not None:
                raise watchdog.fired from exc
            raise
        if hello.get("version") != wire.VERSION:
            channel.close()
            raise ProtocolError(
                f"the robot's endpoint speaks protocol {hello.get('version')}, "
                f"we speak {wire.VERSION}"
            )
        theirs = hello.get("algorithms") or []
        try:
            algorithm = hashing.negotiate(hashing.available(), theirs)
        except ProtocolError:
            channel.close()
            raise
        compress = "zlib" in (hello.get("compression") or [])
        ours: dict[str, Any] = {
            "algorithm": algorithm,
            "compression": "zlib" if compress else "none",
        }
        offered = hello.get("progress")
        if isinstance(offered, (int, float)) and not isinstance(offered, bool) and offered > 0:
            # keepalives while the robot works on a request: several per deadline
            ours["progress"] = min(float(offered), watchdog.deadline / 4)
        data = wire.encode_hello(ours)
        channel.send_all(data)
        conn = cls(transport, channel, reader, hello, algorithm, compress, watchdog)
        conn.bytes_out = sent + len(data)
        if ping:
            conn.ping_id = conn.send({"op": "ping"})
        log.debug("endpoint up: %s", hello)
        return conn

    @staticmethod
    def _deliver(channel: Channel, reader: wire.Reader, archive: Callable[[], bytes]) -> int:
        """Send the loader and the endpoint if the stub says NEED_LOADER, the endpoint if
        the loader says NEED; stop at the hello's magic. The bytes sent."""
        buf = reader._buf
        sent = 0
        while True:
            at = {mark: buf.find(mark) for mark in (NEED_LOADER, NEED, wire.MAGIC)}
            found = [(i, mark) for mark, i in at.items() if i >= 0]
            if found:
                i, first = min(found)
                if first == wire.MAGIC:
                    return sent
                del buf[: i + len(first)]
                mark(
                    "connection: the robot asked for the "
                    + ("loader" if first == NEED_LOADER else "endpoint")
                )
                # a robot without this loader lacks this endpoint too (both change with
                # fetchsync's version): the loader reads it right after itself, unasked,
                # one round trip instead of two (the loader checks its hash either way)
                data = LOADER_BYTES + archive() if first == NEED_LOADER else archive()
                channel.send_all(data)
                return sent + len(data)
            if len(buf) > wire.MAX_NOISE:
                raise ProtocolError("the robot printed too much before the endpoint started")
            if not reader._fill(len(buf) + 1):
                raise EOFError("endpoint ended before its hello")

    @staticmethod
    def _startup_error(transport: Transport, channel: Channel, exc: Exception) -> Exception:
        status = channel.exit_status(timeout=5)
        err = b""
        while True:
            chunk = channel.recv_stderr(65536)
            if not chunk:
                break
            err += chunk
            if len(err) > 65536:
                break
        channel.close()
        text = err.decode("utf-8", "replace").strip()
        last = text.splitlines()[-1] if text else ""
        if status == 127:
            return ConnectError(
                f"python3 was not found on {transport.name}",
                hint="the robot needs python3 >= 3.6: install it (sudo apt install "
                "python3), or set FETCHSYNC_REMOTE_PYTHON to where it is",
            )
        if "SyntaxError" in text or "ModuleNotFoundError" in text:
            return ConnectError(
                f"the robot's python3 is too old for fetchsync: {last}",
                hint="python3 >= 3.6 is needed",
            )
        return ConnectError(
            f"the fetchsync endpoint did not start on {transport.name}"
            + (f": {last}" if last else f" (exit status {status})")
        )

    # ------------------------------------------------------------------ requests
    def send(
        self,
        header: dict[str, Any],
        blob: bytes = b"",
        *,
        blob_parts: list[bytes] | None = None,
        sent: Callable[[int, int], None] | None = None,
    ) -> int:
        """Send a request. ``blob_parts``: a blob in parts that carry their own compression,
        sent as they are (not joined, nor compressed again). ``sent(bytes so far, frame
        length)`` is called as the frame goes out."""
        with self._lock:
            req_id = self._next_id
            self._next_id += 1
        frame = wire.Frame(wire.T_REQUEST, req_id, header, blob)
        if blob_parts is None:
            parts = [wire.encode_frame(frame, compress=self.compress)]
        else:
            parts = wire.encode_frame_parts(frame, blob_parts, compress=self.compress)
        total = sum(len(p) for p in parts)
        done = 0
        with self._arrived:
            if self._failure is not None:
                raise self._failure
            self._owed.add(req_id)
        # in pieces, so bytes_out shows progress during a long frame on a slow
        # link (check_link's callers tell a slow link from a dead one by it)
        try:
            with self._sending:
                for data in parts:
                    view = memoryview(data)  # pieces of it, not copies
                    for start in range(0, len(data), SEND_PIECE):
                        piece = view[start : start + SEND_PIECE]
                        self.channel.send_all(piece)
                        self.bytes_out += len(piece)
                        done += len(piece)
                        if sent is not None:
                            sent(done, total)
        except LinkLostError as exc:
            if self._watchdog is not None and self._watchdog.fired is not None:
                raise self._watchdog.fired from exc
            raise
        return req_id

    def check_link(self) -> None:
        """Raise LinkLostError if the robot does not answer a keepalive.

        For callers blocked on something other than :meth:`wait` (a sender
        waiting for SSH window space on a link that silently died): a link
        that does not answer is closed, which wakes whatever is blocked on it.
        """
        if self.transport.capabilities.keepalive and not self.transport.is_alive():
            raise LinkLostError(
                f"the link to {self.transport.name} was lost: "
                "the robot stopped answering keepalives"
            )

    def answered(self, req_id: int) -> bool:
        """Whether :meth:`wait` for ``req_id`` would return (or raise) at once."""
        with self._arrived:
            return req_id in self._pending or self._failure is not None

    def wait(self, req_id: int) -> wire.Frame:
        # A dead Wi-Fi link acks nothing but fails nothing either: the kernel's
        # user timeout only fires while we have data in flight, so a client
        # waiting for a response would wait forever. While no byte arrives,
        # ask the transport (SSH keepalive with a reply) whether the robot is
        # still there; a link that does not answer is closed and reported.
        probe = self.transport.is_alive if self.transport.capabilities.keepalive else None
        seen = self.reader.bytes_in
        while True:
            with self._arrived:
                if req_id in self._pending:
                    frame = self._pending.pop(req_id)
                    break
                if self._failure is not None:
                    raise self._failure
                if self._arrived.wait(LIVENESS_INTERVAL) or probe is None:
                    continue
            if self.reader.bytes_in != seen:
                seen = self.reader.bytes_in
                continue
            if not probe():
                with self._arrived:
                    self._arrived.wait_for(lambda: self._failure is not None, timeout=5)
                raise LinkLostError(
                    f"the link to {self.transport.name} was lost: "
                    "the robot stopped answering keepalives"
                )
        if frame.type == wire.T_ERROR:
            kind = frame.header.get("kind", "")
            message = str(frame.header.get("error", "unknown error"))
            if kind == "protocol":
                raise ProtocolError(f"the robot refused a request: {message}")
            raise RemoteError(f"{self.transport.name}: {message}")
        return frame

    def request(self, header: dict[str, Any], blob: bytes = b"") -> wire.Frame:
        return self.wait(self.send(header, blob))

    def close(self) -> None:
        # Not waiting for the endpoint's exit: every answer is in, the robot
        # saved its index before sending each, and the end of our input ends it.
        # A session that failed, or is left with requests unanswered (Ctrl-C), is
        # closed at once: a "bye" could block behind a stalled robot, and the
        # closed channel ends the endpoint (EOF on its input) all the same.
        with self._arrived:
            clean = self._failure is None and not self._owed
        if clean:
            try:
                self.send({"op": "bye"})
                self.channel.shutdown_write()
            except Exception:  # closing a dead link is not an error worth reporting
                pass
        if self._watchdog is not None:
            self._watchdog.stop()
        self.channel.close()

    def __enter__(self) -> Connection:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
