"""The robot-side endpoint: serves one client's requests over stdin/stdout.

Started by the loader (``fetchsync.protocol.loader``) as ``python3`` over the
SSH exec channel (or as a local subprocess for the ``local`` robot). It says
hello first, waits for the client's hello, then answers request frames in
order until end of input. A failure on one file is data in a response; a
request that cannot be served at all gets an error frame; only a broken
stream ends the endpoint.
"""

import collections
import gc
import os
import queue
import select
import sys
import threading
import time
from typing import Any, BinaryIO, Deque, Dict, List, Optional, Tuple

from fetchsync.protocol import hashing, heap, wire
from fetchsync.protocol import messages as M
from fetchsync.protocol.errors import ProtocolError
from fetchsync.protocol.store import Store, StoreError, unpack_zpart

MAX_WORKSPACE = 4096
# Keepalives while a request is worked on: the most often a client may ask for them,
# and the least often they come (its progress deadline is 30 s by default)
PROGRESS_MIN = 0.1
PROGRESS_MAX = 5.0


def expand_workspace(spec: str) -> str:
    """A remote workspace as the user wrote it (``~/ws``, ``/abs``) → an absolute path."""
    if not isinstance(spec, str) or not spec or "\x00" in spec:
        raise ProtocolError("bad workspace path")
    path = os.path.expanduser(spec)
    if not os.path.isabs(path):
        path = os.path.join(os.path.expanduser("~"), path)
    path = os.path.normpath(path)
    home = os.path.normpath(os.path.expanduser("~"))
    if path in ("/", home):
        raise StoreError("refusing to use %s itself as the workspace" % path)
    return path


class Server:
    def __init__(self, inp: "BinaryIO", out: "BinaryIO") -> None:
        self.inp = inp
        self.out = out
        self.reader = wire.Reader(self._recv, getattr(inp, "readinto", None))
        self.store = None  # type: Optional[Store]
        self._opened = None  # type: Any  # the open request that made ``store`` (see do_open)
        self.compress = False
        self.algorithm = ""
        self.unpacked = None  # type: Optional[Tuple[bytearray, Any]]  # the request's, see _unpacked
        # after a sync refused as stale: (epoch, the generation the store was at), until
        # this client lists or opens again (see _chained)
        self._refused = None  # type: Optional[Tuple[str, int]]
        # one writer at a time on ``out``: the serving thread's frames and the keepalives
        self._out_lock = threading.Lock()
        self._working = None  # type: Optional[int]  # the id of the request being served
        self._quiet_since = time.monotonic()  # the last write, or the request's start
        self._done = threading.Event()

    def _recv(self, n: int) -> bytes:
        read1 = getattr(self.inp, "read1", None)
        return read1(n) if read1 is not None else self.inp.read(n)

    def _send(self, frame: "wire.Frame") -> None:
        chunks = wire.encode_frame_chunks(frame, compress=self.compress)
        with self._out_lock:
            for chunk in chunks:
                self.out.write(chunk)
            self.out.flush()
            self._working = None
            self._quiet_since = time.monotonic()

    def _keepalive(self, interval: float) -> None:
        """Send a T_PROGRESS frame whenever a request has been worked on for ``interval``
        seconds with nothing written: legitimately long silent work (a cold listing of
        a huge tree, hashing a large file, a long syncfs on an SD card) must not look
        like a stalled endpoint to the client's progress deadline. A stopped endpoint
        (SIGSTOP) stops this thread too, so the deadline still catches it."""
        while not self._done.wait(interval / 4):
            with self._out_lock:
                req_id = self._working
                now = time.monotonic()
                if req_id is None or now - self._quiet_since < interval:
                    continue
                try:
                    self.out.write(wire.encode_frame(wire.Frame(wire.T_PROGRESS, req_id, {})))
                    self.out.flush()
                except (OSError, ValueError):  # the serving thread finds out on its own
                    return
                self._quiet_since = now

    def hello(self) -> "Dict[str, Any]":
        return {
            "algorithms": hashing.available(),
            "compression": ["zlib"],
            "python": "%d.%d.%d" % sys.version_info[:3],
            "executable": sys.executable,  # the laptop runs it by this path next time
            "host": os.uname().nodename,  # socket.gethostname(), without importing socket
            "home": os.path.expanduser("~"),
            "progress": PROGRESS_MAX,  # T_PROGRESS frames, to a client that asks
            "zdict": 1,  # writes of source "zdict" (messages.SRC_ZDICT)
            "stl": 1,  # writes of source "stl" (messages.SRC_STL)
        }

    def serve(self) -> None:
        try:
            self._serve()
        finally:
            self._done.set()
            if self.store is not None:
                self.store.discard_uploads()
                self.store.close()

    def _serve(self) -> None:
        self.out.write(wire.encode_hello(self.hello()))
        self.out.flush()
        client = self.reader.read_hello()
        self.algorithm = client.get("algorithm", "")
        if self.algorithm not in hashing.available():
            raise ProtocolError("client asked for unknown hash algorithm %r" % (self.algorithm,))
        self.compress = client.get("compression") == "zlib"
        interval = client.get("progress")
        if isinstance(interval, (int, float)) and not isinstance(interval, bool) and interval > 0:
            interval = min(max(float(interval), PROGRESS_MIN), PROGRESS_MAX)
            threading.Thread(
                target=self._keepalive, args=(interval,), name="fetchsync-keepalive", daemon=True
            ).start()
        # frames are read ahead by a thread, so the link keeps carrying the next
        # batch while this one is applied and flushed to disk (the SSH window
        # alone holds ~2 MB: the client would stall after that)
        frames = _ReadAhead()
        threading.Thread(
            target=self._read_ahead, args=(frames,), name="fetchsync-read", daemon=True
        ).start()
        item = frame = None
        while True:
            item = frame = None  # the last frame's data goes before the next is waited for
            item = frames.get()
            if isinstance(item, BaseException):
                raise item
            frame, self.unpacked = item
            if frame is None:
                return
            if frame.type != wire.T_REQUEST:
                raise ProtocolError("expected a request frame")
            if frame.header.get("op") in ("sync", "adopt") and self._client_gone():
                return  # a killed push's batch read ahead: never applied after it has gone
            with self._out_lock:
                self._working = frame.req_id
                self._quiet_since = time.monotonic()
            self._send(self.dispatch(frame))
            if frame.header.get("op") == "bye":
                return

    def _client_gone(self) -> bool:
        """Whether nobody reads our answers any more: the read end of our output closed
        (sshd closed the channel: the client, its connection or its master's call gone).
        One poll, before each write request (tests/test_endpoint_client_gone.py)."""
        try:
            fd = self.out.fileno()
        except (AttributeError, OSError, ValueError):
            return False
        watch = select.poll()
        watch.register(fd, 0)  # POLLERR and POLLHUP are always reported
        return bool(watch.poll(0))

    def _read_ahead(self, frames: "_ReadAhead") -> None:
        try:
            while True:
                frames.wait_below(READ_AHEAD_START)
                frame = self.reader.read_frame()
                size = _frame_size(frame)
                frames.reserve(size)  # before inflating: a large frame waits as it came
                frames.add((frame, _unpacked(frame)), size)
                if frame is None:
                    return
                frame = None  # served: its data goes when the serving thread is done with it
        except BaseException as exc:  # EOF mid-frame, garbage: raised by the serving thread
            frames.put(exc)

    def dispatch(self, frame: "wire.Frame") -> "wire.Frame":
        op = frame.header.get("op")
        handler = getattr(self, "do_" + str(op), None)
        if handler is None:
            return wire.Frame(
                wire.T_ERROR,
                frame.req_id,
                {"error": "unknown request %r" % (op,), "kind": "protocol"},
            )
        try:
            header, blob = handler(frame.header, frame.blob)
        except (ProtocolError, OSError) as exc:  # StoreError is a ProtocolError
            return _error_frame(frame.req_id, exc)
        finally:
            if self.store is not None:
                self.store.unlock()
        return wire.Frame(wire.T_RESPONSE, frame.req_id, header, blob)

    # ------------------------------------------------------------------ requests
    def _store(self) -> "Store":
        if self.store is None:
            raise ProtocolError("no workspace open")
        self.store.lock()
        return self.store

    def _writable(self) -> "Store":
        store = self._store()
        if store.readonly:
            raise StoreError("the workspace was opened read-only: nothing is written")
        return store

    def do_open(self, h: "Dict[str, Any]", _blob: bytes) -> "Tuple[Dict[str, Any], bytes]":
        """Open a workspace; ``readonly``: create nothing, lock nothing, write nothing
        (``push --dry-run``, ``pull``, status reads), and refuse every change.

        A re-open of the workspace open in this session, with the same options, keeps
        its Store (a long-lived endpoint's: the resident's, the watch agent's) instead
        of reading its index again: it is what a fresh one would load, as
        :meth:`Store.lock` reloads the index when its files are not the ones this store
        loaded or last saved (held open, so their inodes are not reused), and a store
        with a change of its own unsaved is not kept. The locks, the batch marker's
        clean-up and the descriptors are taken afresh as for a new one."""
        from fetchsync.protocol.ignore import IgnoreRules

        self._refused = None
        workspace = expand_workspace(h.get("workspace", ""))
        readonly = h.get("readonly", False) is True
        create = bool(h.get("create", True))
        key = (workspace, h.get("rules"), create, readonly)
        if self.store is not None and key == self._opened and self.store.reopen():
            self.store.keep_listing()  # a long-lived endpoint: see fetchsync.protocol.kept
        elif self.store is not None:
            self.store.close()
            self.store = None
        if self.store is None:
            rules = IgnoreRules.from_wire(h.get("rules")) if h.get("rules") is not None else None
            self.store = Store(
                workspace, algorithm=self.algorithm, rules=rules, create=create, readonly=readonly
            )
            self._opened = key
        store = self._store()  # the index read again here if another writer saved since
        store.save_index()
        return {
            "workspace": workspace,
            "epoch": store.epoch,
            "gen": store.gen,
            "readonly": readonly,
        }, b""

    def _fresh(self, store: "Store", h: "Dict[str, Any]") -> bool:
        return h.get("epoch") == store.epoch and h.get("gen") == store.gen

    def _chained(self, h: "Dict[str, Any]") -> bool:
        """Whether a sync request was sent behind one this session refused as stale: a
        client pipelines a round's batches as generations gen, gen+1, ..., so with the
        robot k generations ahead (another writer, a killed push's last batches) batch k
        would find its generation current and apply after batches 0..k-1 were refused
        (an upload's later pieces without its first). A client lists (or opens) before
        it plans again, so until then a generation up to the one refused at is part of
        the refused chain."""
        refused = self._refused
        gen = h.get("gen")
        return (
            refused is not None
            and h.get("epoch") == refused[0]
            and isinstance(gen, int)
            and gen <= refused[1]
        )

    def do_list(self, h: "Dict[str, Any]", _blob: bytes) -> "Tuple[Dict[str, Any], bytes]":
        self._refused = None
        store = self._store()
        _test_pause("FETCHSYNC_TEST_SLOW_LIST")
        out = {"epoch": store.epoch, "gen": store.gen}  # type: Dict[str, Any]
        if h.get("mode") == "drift" and self._fresh(store, h):
            changed, gone = store.drift()
            out.update(full=False, entries=[e.to_wire() for e in changed], gone=gone)
        else:
            items, skipped = store.listing()
            out.update(full=True, entries=[e.to_wire() for e in items], skipped=skipped)
        store.save_index()
        return out, b""

    def _sync_request(self, h: "Dict[str, Any]") -> "Optional[Tuple[Store, List[M.Op], str]]":
        """A sync request's store (locked), operations and policy; None if it is stale."""
        store = self._writable()
        if h.get("require_fresh") and (not self._fresh(store, h) or self._chained(h)):
            self._refused = (store.epoch, store.gen)
            return None
        raw = h.get("ops")
        if not isinstance(raw, list):
            raise ProtocolError("sync without an operation list")
        ops = [M.Op.from_wire(o) for o in raw]
        policy = h.get("policy", "preserve")
        if policy not in ("preserve", "refuse"):
            raise ProtocolError("unknown conflict policy %r" % (policy,))
        return store, ops, policy

    def do_sync(self, h: "Dict[str, Any]", blob: bytes) -> "Tuple[Dict[str, Any], bytes]":
        parsed = self._sync_request(h)
        if parsed is None:
            store = self._store()
            return {"stale": True, "epoch": store.epoch, "gen": store.gen}, b""
        store, ops, policy = parsed
        unpacked, self.unpacked = self.unpacked, None
        results = store.apply(ops, blob, policy=policy, zpart=h.get("zpart"), unpacked=unpacked)
        out = {
            "results": [r.to_wire(op) for r, op in zip(results, ops)],
            "epoch": store.epoch,
            "gen": store.gen,
        }  # type: Dict[str, Any]
        if h.get("verify"):
            changed, gone = store.drift()
            out.update(drift=[e.to_wire() for e in changed], gone=gone)
        store.save_index()
        return out, b""

    @staticmethod
    def _per_item(h: "Dict[str, Any]", serve: "Any") -> "Tuple[List[Dict[str, Any]], Any]":
        """Run ``serve(item) -> (answer, data)`` for each item; a failure is that item's answer."""
        items = h.get("items")
        if not isinstance(items, list):
            raise ProtocolError("request without items")
        # one buffer grown as each item's data comes (freed after): a list joined at the
        # end held every file's data twice (tests/test_endpoint_memory_big.py)
        out = bytearray()
        pos = 0
        answers = []
        for item in items:
            if not isinstance(item, dict) or not isinstance(item.get("p"), str):
                raise ProtocolError("bad request item")
            try:
                answer, data = serve(item)
            except (OSError, ProtocolError) as exc:
                answers.append(
                    {
                        "c": M.IO_ERROR,
                        "msg": "%s: %s" % (item["p"], getattr(exc, "strerror", None) or exc),
                    }
                )
                continue
            answer["bl"] = [pos, len(data)]
            answers.append(answer)
            out += data
            pos += len(data)
            data = b""
        return answers, out

    def do_read(self, h: "Dict[str, Any]", blob: bytes) -> "Tuple[Dict[str, Any], bytes]":
        """File contents, whole or as a delta against a signature the client sent."""
        store = self._store()

        def serve(item: "Dict[str, Any]") -> "Tuple[Dict[str, Any], bytes]":
            sig = None
            if "sig" in item:
                ref = item["sig"]
                if not (
                    isinstance(ref, list)
                    and len(ref) == 2
                    and all(isinstance(x, int) for x in ref)
                    and 0 <= ref[0]
                    and 0 <= ref[1]
                    and ref[0] + ref[1] <= len(blob)
                ):
                    raise ProtocolError("bad signature reference")
                sig = blob[ref[0] : ref[0] + ref[1]]
            listed, src, data = store.read(
                item["p"], sig=sig, offset=int(item.get("off", 0)), length=int(item.get("len", -1))
            )
            return {"c": M.OK, "l": listed.to_wire(), "src": src}, data

        answers, data = self._per_item(h, serve)
        store.save_index()
        return {"items": answers}, data

    def do_sigs(self, h: "Dict[str, Any]", _blob: bytes) -> "Tuple[Dict[str, Any], bytes]":
        """Delta signatures of files here, for a sender that has none of its own."""
        store = self._store()

        def serve(item: "Dict[str, Any]") -> "Tuple[Dict[str, Any], bytes]":
            sig, digest = store.signature(item["p"])
            return {"c": M.OK, "h": digest}, sig

        answers, data = self._per_item(h, serve)
        store.save_index()
        return {"items": answers}, data

    def do_adopt(self, h: "Dict[str, Any]", _blob: bytes) -> "Tuple[Dict[str, Any], bytes]":
        store = self._writable()
        items = [M.Listed.from_wire(e) for e in h.get("entries", [])]
        n = store.adopt(items)
        store.save_index()
        return {"adopted": n, "epoch": store.epoch, "gen": store.gen}, b""

    def do_kept(self, h: "Dict[str, Any]", _blob: bytes) -> "Tuple[Dict[str, Any], bytes]":
        """Read-only: the files kept in ``.fetchsync/<where>`` (``conflicts``, ``trash``), or,
        with ``at`` and ``p``, a piece of one (``off``, ``len``) as the blob."""
        store = self._store()
        where = h.get("where")
        if not isinstance(where, str):
            raise ProtocolError("unknown kept place %r" % (where,))
        if "p" not in h:
            entries, more = store.kept(where)
            return {"entries": entries, "more": more}, b""
        at, path, off, n = h.get("at"), h.get("p"), h.get("off", 0), h.get("len", 0)
        if not (
            isinstance(at, str)
            and isinstance(path, str)
            and isinstance(off, int)
            and isinstance(n, int)
        ):
            raise ProtocolError("bad kept read")
        size, data = store.read_kept(where, at, path, off, n)
        return {"size": size}, data

    def do_ping(self, h: "Dict[str, Any]", _blob: bytes) -> "Tuple[Dict[str, Any], bytes]":
        return {"pong": True}, b""

    def do_bye(self, h: "Dict[str, Any]", _blob: bytes) -> "Tuple[Dict[str, Any], bytes]":
        return {}, b""


def _test_pause(name: str) -> None:
    """Sleep ``$name`` seconds if it is set: the tests make a request slower than the
    client's progress deadline with it (the ``local`` robot's endpoint inherits it)."""
    value = os.environ.get(name)
    if value:
        time.sleep(float(value))


def _error_frame(req_id: int, exc: "Exception") -> "wire.Frame":
    if isinstance(exc, StoreError):
        return wire.Frame(wire.T_ERROR, req_id, {"error": str(exc), "kind": "store"})
    if isinstance(exc, ProtocolError):
        return wire.Frame(wire.T_ERROR, req_id, {"error": str(exc), "kind": "protocol"})
    assert isinstance(exc, OSError)
    return wire.Frame(
        wire.T_ERROR,
        req_id,
        {
            "error": "%s%s" % (exc.strerror or exc, ": " + exc.filename if exc.filename else ""),
            "kind": "os",
            "errno": exc.errno or 0,
        },
    )


class _ReadAhead:
    """The request frames read ahead of the serving thread, their compressed parts
    inflated: up to READ_AHEAD of them holding up to READ_AHEAD_BYTES (a frame's data
    and its inflated part) with the frame being served, or a single frame of any size.

    Four frames keep the laptop reading and compressing while a batch of large files
    is written here; the bound in bytes keeps a queue of large-file frames within the
    memory of one of small-file frames. The frame being served counts until the next is
    asked for, and the reading thread reads no further frame while READ_AHEAD_START is
    held, and inflates one only once there is room: a push of 32 MiB meshes peaked the
    endpoint at 270 MiB (three such frames and the third's inflating), now one frame's
    (tests/test_endpoint_memory_big.py).
    """

    def __init__(self) -> None:
        self._items: "Deque[Tuple[Any, int]]" = collections.deque()
        self._bytes = 0  # queued, being made, and being served
        self._served = 0
        self._cond = threading.Condition()

    def wait_below(self, size: int) -> None:
        """Return once less than ``size`` bytes are held."""
        with self._cond:
            while self._bytes >= size:
                self._cond.wait()

    def reserve(self, size: int) -> None:
        """Count ``size`` bytes more, once there is room for them (or nothing is held)."""
        with self._cond:
            while self._bytes and (
                len(self._items) >= READ_AHEAD or self._bytes + size > READ_AHEAD_BYTES
            ):
                self._cond.wait()
            self._bytes += size

    def add(self, item: "Any", size: int = 0) -> None:
        """Queue ``item``, its ``size`` bytes reserved before."""
        with self._cond:
            self._items.append((item, size))
            self._cond.notify_all()

    def put(self, item: "Any", size: int = 0) -> None:
        """Queue ``item``, once there is room for ``size`` more bytes."""
        self.reserve(size)
        self.add(item, size)

    def get(self, timeout: "Optional[float]" = None) -> "Any":
        """The next item (the one before is done with); queue.Empty if none came within
        ``timeout`` seconds."""
        with self._cond:
            self._bytes -= self._served
            self._served = 0
            self._cond.notify_all()
            if not self._cond.wait_for(lambda: self._items, timeout):
                raise queue.Empty
            item, self._served = self._items.popleft()
            return item

    def empty(self) -> bool:
        return not self._items


def _frame_size(frame: "Optional[wire.Frame]") -> int:
    """The bytes a frame read ahead holds: its data, and its compressed part inflated
    (the size its header announces, checked when it is inflated)."""
    if frame is None:
        return 0
    zpart = frame.header.get("zpart") if frame.type == wire.T_REQUEST else None
    inflated = zpart[1] if isinstance(zpart, list) and len(zpart) == 2 else 0
    if not isinstance(inflated, int) or not 0 <= inflated <= wire.MAX_BODY:
        inflated = 0
    return len(frame.blob) + inflated


def _unpacked(frame: "Optional[wire.Frame]") -> "Optional[Tuple[bytearray, Any]]":
    """A sync request's compressed part, inflated by the reading thread (zlib lets go of
    the GIL) while the serving one applies the request before; None if it has none, or
    if it is bad: applying the request then says why."""
    if (
        frame is None
        or frame.type != wire.T_REQUEST
        or frame.header.get("op") != "sync"
        or frame.header.get("zpart") is None
    ):
        return None
    try:
        return unpack_zpart(frame.blob, frame.header["zpart"])
    except ProtocolError:
        return None


# Frames read before they are served, and the most data they hold meanwhile: two
# frames (of up to 8 MiB of a push each) measured 2-5% slower on an initial push
READ_AHEAD = 4
READ_AHEAD_BYTES = 48 * 1024 * 1024
READ_AHEAD_START = 32 * 1024 * 1024  # no further frame is read while this much is held


def main() -> None:
    heap.map_large_buffers()  # a first sync's freed buffers go back: 87 -> 37 MiB after 7,000 files
    wire.widen_pipe(0)  # the push arrives on stdin
    # a push makes a few objects per file and no cycles worth the name, yet the
    # default thresholds ran ~100 collections in a 7,000-file push
    if hasattr(gc, "freeze"):  # Python >= 3.7
        gc.freeze()  # novermin
    gc.set_threshold(100000, 50, 100)
    # stdout carries frames only: anything else printed would corrupt the stream
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    code = 0
    try:
        Server(sys.stdin.buffer, out).serve()
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        pass
    except ProtocolError as exc:
        sys.stderr.write("fetchsync endpoint: %s\n" % exc)
        code = 3
    except Exception:
        import traceback  # only here: it costs every start ~2 ms to import

        traceback.print_exc()
        code = 4
    # after a bye the read-ahead thread may still be blocked reading stdin: finalizing
    # the interpreter under it aborts the process ("Fatal Python error:
    # _enter_buffered_busy", SIGABRT, on the robot's stderr). The store is closed
    # (serve's finally) and what is left to do is flushing: then exit at once.
    for stream in (out, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


if __name__ == "__main__":
    main()
