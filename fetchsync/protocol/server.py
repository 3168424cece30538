"""The robot-side endpoint: serves one client's requests over stdin/stdout.

Started by the loader (``fetchsync.protocol.loader``) as ``python3`` over the
SSH exec channel (or as a local subprocess for the ``local`` robot). It says
hello first, waits for the client's hello, then answers request frames in
order until end of input. A failure on one file is data in a response; a
request that cannot be served at all gets an error frame; only a broken
stream ends the endpoint.
"""

from __future__ import annotations

import collections
import gc
import json
import os
import queue
import select
import sys
import threading
from typing import Any, BinaryIO, Deque, Dict, List, Optional, Tuple

from fetchsync.protocol import hashing, wire
from fetchsync.protocol import messages as M
from fetchsync.protocol.errors import ProtocolError
from fetchsync.protocol.loader import cache_dir, write_cache_file
from fetchsync.protocol.store import Store, StoreError, unpack_zpart

MAX_WORKSPACE = 4096
# A client that has not spoken this long after our hello is probably not there:
# we are a connection master's spare endpoint, with time to prepare. If one was
# only slow and opens the same workspace, its open takes what was prepared.
PREWARM_AFTER = 0.05
PREWARM_POLL = 0.5  # then how often a waiting spare looks whether another workspace was opened
LAST_OPEN = "last-open.json"


def _open_key(h: Dict[str, Any], algorithm: str) -> str:
    return json.dumps([h.get("workspace"), h.get("rules"), bool(h.get("create", True)), algorithm],
                      sort_keys=True)


class _Prewarm:
    """The store of the workspace opened last, opened and watched ahead of the next client.

    Only the scan is done ahead; what the client is told is computed when it
    asks, from the scan as inotify kept it current since.
    """

    def __init__(self, spec: Dict[str, Any]) -> None:
        self.key = spec["key"]
        self.spec = spec
        self.store = None  # type: Optional[Store]
        self.thread = threading.Thread(target=self._run, name="prewarm", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        from fetchsync.protocol.ignore import IgnoreRules
        try:
            rules = self.spec["rules"]
            store = Store(self.spec["workspace"], algorithm=self.spec["algorithm"],
                          rules=IgnoreRules.from_wire(rules) if rules is not None else None,
                          create=False)
            if store.watch():
                self.store = store
        except Exception:  # an optimisation only: the client's open starts afresh
            self.store = None

    def keep_current(self) -> bool:
        """Apply the events queued so far (so a busy tree, such as another client's initial
        push, cannot overflow the queue while we wait); False if events were lost."""
        if self.thread.is_alive() or self.store is None or self.store.watched is None:
            return True
        if self.store.watched.refresh():
            return True
        self.store.watched.close()
        self.store = None
        return False

    def take(self, key: str) -> Optional[Store]:
        self.thread.join()
        store, self.store = self.store, None
        if store is not None and key != self.key:
            if store.watched is not None:
                store.watched.close()
            return None
        return store


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
    def __init__(self, inp: BinaryIO, out: BinaryIO) -> None:
        self.inp = inp
        self.out = out
        self.reader = wire.Reader(self._recv, getattr(inp, "readinto", None))
        self.store = None  # type: Optional[Store]
        self.compress = False
        self.algorithm = ""
        self.prewarm = None  # type: Optional[_Prewarm]
        self.unpacked = None  # type: Optional[Tuple[bytes, Any]]  # the request's, see _unpacked
        # the sync request whose files are written and being synced while the next
        # one's are written: (its id, its batch, the syncfs under way), see _pipeline
        self.held = None  # type: Optional[Tuple[int, Any, Any]]
        # answers to requests whose renames are done, sent once a syncfs begun after
        # them completes: nothing is reported written before it is durable
        self.unsent = []  # type: List[wire.Frame]

    def _recv(self, n: int) -> bytes:
        read1 = getattr(self.inp, "read1", None)
        return read1(n) if read1 is not None else self.inp.read(n)

    def _send(self, frame: wire.Frame) -> None:
        self.out.write(wire.encode_frame(frame, compress=self.compress))
        self.out.flush()

    def hello(self) -> Dict[str, Any]:
        return {
            "algorithms": hashing.available(),
            "compression": ["zlib"],
            "python": "%d.%d.%d" % sys.version_info[:3],
            "executable": sys.executable,  # the laptop runs it by this path next time
            "host": os.uname().nodename,  # socket.gethostname(), without importing socket
            "home": os.path.expanduser("~"),
        }

    def serve(self) -> None:
        try:
            self._serve()
        finally:
            if self.store is not None:
                self.store.discard_uploads()

    def _serve(self) -> None:
        self.out.write(wire.encode_hello(self.hello()))
        self.out.flush()
        _tune_malloc()  # while the hello travels: the frames come after the client's
        self._maybe_prewarm()
        client = self.reader.read_hello()
        self.algorithm = client.get("algorithm", "")
        if self.algorithm not in hashing.available():
            raise ProtocolError("client asked for unknown hash algorithm %r" % (self.algorithm,))
        self.compress = client.get("compression") == "zlib"
        # frames are read ahead by a thread, so the link keeps carrying the next
        # batch while this one is applied and flushed to disk (the SSH window
        # alone holds ~2 MB: the client would stall after that)
        frames = _ReadAhead()
        threading.Thread(target=self._read_ahead, args=(frames,), name="fetchsync-read",
                         daemon=True).start()
        while True:
            if self.held is not None and frames.empty():
                self._settle()  # nothing follows yet: the held request is answered now
            try:
                item = frames.get(timeout=IDLE_TRIM_AFTER)
            except queue.Empty:
                _trim_heap()  # idle: give back what the last requests used
                item = frames.get()
            if isinstance(item, BaseException):
                raise item
            frame, self.unpacked = item
            if frame is None:
                self._settle(quiet=True)
                return
            if frame.type != wire.T_REQUEST:
                raise ProtocolError("expected a request frame")
            if self._pipeline(frame, frames):
                continue
            self._settle()
            self._send(self.dispatch(frame))
            if frame.header.get("op") == "bye":
                return

    def _pipeline(self, frame: wire.Frame, frames: "_ReadAhead") -> bool:
        """Serve a sync request that another follows closely, overlapping disk flushes
        with writing: its files are written while the request before is synced, and
        its own syncfs runs while the next one's are written. Answers keep their order
        and go out only once what they report is durable. False: serve it as usual.

        The first syncfs of a batch (its temporaries, before the renames) took ~9%
        of a 150 MB initial push's time on the robot, its critical path.
        """
        h = frame.header
        if h.get("op") != "sync" or h.get("verify") or self.store is None \
                or (self.held is None and frames.empty()):
            return False
        try:
            parsed = self._sync_request(h)
        except Exception:  # served as usual, which answers what is wrong
            return False
        if parsed is None:
            return False  # stale: answered as usual, after what is held
        store, ops, policy = parsed
        if self.held is not None and self.held[1].blocks(ops):
            self._settle(unlock=False)
        unpacked, self.unpacked = self.unpacked, None
        try:
            batch = store.begin(ops, frame.blob, policy=policy, zpart=h.get("zpart"), unpacked=unpacked,
                                join=False)
        except (ProtocolError, OSError) as exc:
            self._settle()
            self._send(_error_frame(frame.req_id, exc))
            return True
        if self.held is not None:
            req_id, prev, syncing = self.held
            syncing.wait()  # prev's temporaries, and the renames before, are durable
            self._send_unsent()
            store.finish(prev, synced=True, durable=False)
            store.save_index()
            self.unsent.append(wire.Frame(wire.T_RESPONSE, req_id, _sync_answer(store, prev)))
        self.held = (frame.req_id, batch, store.sync_in_background(batch))
        return True

    def _settle(self, *, unlock: bool = True, quiet: bool = False) -> None:
        """Finish the held request and send every answer still owed, in order."""
        store = self.store
        try:
            if self.held is not None and store is not None:
                req_id, batch, syncing = self.held
                self.held = None
                syncing.wait()
                self._send_unsent()
                store.finish(batch, synced=True)
                store.save_index()
                self._send(wire.Frame(wire.T_RESPONSE, req_id, _sync_answer(store, batch)))
            elif self.unsent and store is not None:
                store.sync()
                self._send_unsent()
        except (OSError, ValueError):
            if not quiet:  # the client is gone (end of input): what was done is done
                raise
        finally:
            if unlock and store is not None:
                store.unlock()

    def _send_unsent(self) -> None:
        unsent, self.unsent = self.unsent, []
        for frame in unsent:
            self._send(frame)

    def _read_ahead(self, frames: "_ReadAhead") -> None:
        try:
            while True:
                frame = self.reader.read_frame()
                unpacked = _unpacked(frame)
                size = len(frame.blob) if frame is not None else 0
                frames.put((frame, unpacked), size + (len(unpacked[0]) if unpacked else 0))
                if frame is None:
                    return
        except BaseException as exc:  # EOF mid-frame, garbage: raised by the serving thread
            frames.put(exc)

    def _maybe_prewarm(self) -> None:
        """While no client talks to us, open and watch the workspace opened last, and follow
        the record when another endpoint opens a different one meanwhile (a spare started
        before the first push to a new workspace would otherwise prepare the old one)."""
        path = os.path.join(cache_dir(), LAST_OPEN)
        seen = None  # type: Any
        timeout = PREWARM_AFTER
        while True:
            try:
                ready, _, _ = select.select([self.inp.fileno()], [], [], timeout)
            except (OSError, ValueError, AttributeError):
                return
            if ready:
                return
            timeout = PREWARM_POLL
            if self.prewarm is not None and not self.prewarm.keep_current():
                self.prewarm = _Prewarm(self.prewarm.spec)  # events were lost: scan again
            try:
                st = os.stat(path)
            except OSError:
                continue
            if (st.st_mtime_ns, st.st_size, st.st_ino) == seen:
                continue
            seen = (st.st_mtime_ns, st.st_size, st.st_ino)
            try:
                with open(path, "r", encoding="utf-8") as fh:
                    spec = json.load(fh)
            except (OSError, ValueError):
                continue
            if not (isinstance(spec, dict) and isinstance(spec.get("workspace"), str)
                    and isinstance(spec.get("key"), str)
                    and spec.get("algorithm") in hashing.available()):
                continue
            if self.prewarm is not None:
                if self.prewarm.key == spec["key"]:
                    continue
                self.prewarm.take("")  # let the old one finish, and close it
            self.prewarm = _Prewarm(spec)

    def _remember_open(self, key: str, workspace: str, h: Dict[str, Any]) -> None:
        path = os.path.join(cache_dir(), LAST_OPEN)
        spec = {"key": key, "workspace": workspace, "rules": h.get("rules"),
                "algorithm": self.algorithm}
        text = json.dumps(spec, sort_keys=True)
        try:
            with open(path, "r", encoding="utf-8") as fh:
                if fh.read() == text:
                    return
        except (OSError, ValueError):
            pass
        write_cache_file(path, text)  # an optimisation only

    def dispatch(self, frame: wire.Frame) -> wire.Frame:
        op = frame.header.get("op")
        handler = getattr(self, "do_" + str(op), None)
        if handler is None:
            return wire.Frame(wire.T_ERROR, frame.req_id, {"error": "unknown request %r" % (op,),
                                                           "kind": "protocol"})
        try:
            header, blob = handler(frame.header, frame.blob)
        except (ProtocolError, OSError) as exc:  # StoreError is a ProtocolError
            return _error_frame(frame.req_id, exc)
        finally:
            if self.store is not None:
                self.store.unlock()
        return wire.Frame(wire.T_RESPONSE, frame.req_id, header, blob)

    # ------------------------------------------------------------------ requests
    def _store(self) -> Store:
        if self.store is None:
            raise ProtocolError("no workspace open")
        self.store.lock()
        return self.store

    def do_open(self, h: Dict[str, Any], _blob: bytes) -> Tuple[Dict[str, Any], bytes]:
        from fetchsync.protocol.ignore import IgnoreRules
        workspace = expand_workspace(h.get("workspace", ""))
        key = _open_key(h, self.algorithm)
        warm = self.prewarm.take(key) if self.prewarm is not None else None
        self.prewarm = None
        if self.store is not None and self.store.watched is not None:
            self.store.watched.close()
        if warm is not None and warm.workspace == workspace:
            self.store = warm
        else:
            rules = IgnoreRules.from_wire(h.get("rules")) if h.get("rules") is not None else None
            self.store = Store(workspace, algorithm=self.algorithm, rules=rules,
                               create=bool(h.get("create", True)))
        store = self._store()
        self._remember_open(key, workspace, h)
        store.save_index()
        return {"workspace": workspace, "epoch": store.epoch, "gen": store.gen}, b""

    def _fresh(self, store: Store, h: Dict[str, Any]) -> bool:
        return h.get("epoch") == store.epoch and h.get("gen") == store.gen

    def do_list(self, h: Dict[str, Any], _blob: bytes) -> Tuple[Dict[str, Any], bytes]:
        store = self._store()
        out = {"epoch": store.epoch, "gen": store.gen}  # type: Dict[str, Any]
        if h.get("mode") == "drift" and self._fresh(store, h):
            changed, gone = store.drift()
            out.update(full=False, entries=[e.to_wire() for e in changed], gone=gone)
        else:
            items, skipped = store.listing()
            out.update(full=True, entries=[e.to_wire() for e in items], skipped=skipped)
        store.save_index()
        return out, b""

    def _sync_request(self, h: Dict[str, Any]) -> Optional[Tuple[Store, List[M.Op], str]]:
        """A sync request's store (locked), operations and policy; None if it is stale."""
        store = self._store()
        if h.get("require_fresh") and not self._fresh(store, h):
            return None
        raw = h.get("ops")
        if not isinstance(raw, list):
            raise ProtocolError("sync without an operation list")
        ops = [M.Op.from_wire(o) for o in raw]
        policy = h.get("policy", "preserve")
        if policy not in ("preserve", "refuse"):
            raise ProtocolError("unknown conflict policy %r" % (policy,))
        return store, ops, policy

    def do_sync(self, h: Dict[str, Any], blob: bytes) -> Tuple[Dict[str, Any], bytes]:
        parsed = self._sync_request(h)
        if parsed is None:
            store = self._store()
            return {"stale": True, "epoch": store.epoch, "gen": store.gen}, b""
        store, ops, policy = parsed
        unpacked, self.unpacked = self.unpacked, None
        batch = store.begin(ops, blob, policy=policy, zpart=h.get("zpart"), unpacked=unpacked)
        store.finish(batch)
        out = _sync_answer(store, batch)
        if h.get("verify"):
            changed, gone = store.drift()
            out.update(drift=[e.to_wire() for e in changed], gone=gone)
        store.save_index()
        return out, b""

    @staticmethod
    def _per_item(h: Dict[str, Any], serve: Any) -> Tuple[List[Dict[str, Any]], bytes]:
        """Run ``serve(item) -> (answer, data)`` for each item; a failure is that item's answer."""
        items = h.get("items")
        if not isinstance(items, list):
            raise ProtocolError("request without items")
        parts = []  # type: List[bytes]
        pos = 0
        answers = []
        for item in items:
            if not isinstance(item, dict) or not isinstance(item.get("p"), str):
                raise ProtocolError("bad request item")
            try:
                answer, data = serve(item)
            except (OSError, ProtocolError) as exc:
                answers.append({"c": M.IO_ERROR, "msg": "%s: %s" % (
                    item["p"], getattr(exc, "strerror", None) or exc)})
                continue
            answer["bl"] = [pos, len(data)]
            answers.append(answer)
            parts.append(data)
            pos += len(data)
        return answers, b"".join(parts)

    def do_read(self, h: Dict[str, Any], blob: bytes) -> Tuple[Dict[str, Any], bytes]:
        """File contents, whole or as a delta against a signature the client sent."""
        store = self._store()

        def serve(item: Dict[str, Any]) -> Tuple[Dict[str, Any], bytes]:
            sig = None
            if "sig" in item:
                ref = item["sig"]
                if not (isinstance(ref, list) and len(ref) == 2 and all(isinstance(x, int) for x in ref)
                        and 0 <= ref[0] and 0 <= ref[1] and ref[0] + ref[1] <= len(blob)):
                    raise ProtocolError("bad signature reference")
                sig = blob[ref[0]:ref[0] + ref[1]]
            listed, src, data = store.read(item["p"], sig=sig, offset=int(item.get("off", 0)),
                                           length=int(item.get("len", -1)))
            return {"c": M.OK, "l": listed.to_wire(), "src": src}, data

        answers, data = self._per_item(h, serve)
        store.save_index()
        return {"items": answers}, data

    def do_sigs(self, h: Dict[str, Any], _blob: bytes) -> Tuple[Dict[str, Any], bytes]:
        """Delta signatures of files here, for a sender that has none of its own."""
        store = self._store()

        def serve(item: Dict[str, Any]) -> Tuple[Dict[str, Any], bytes]:
            sig, digest = store.signature(item["p"])
            return {"c": M.OK, "h": digest}, sig

        answers, data = self._per_item(h, serve)
        store.save_index()
        return {"items": answers}, data

    def do_adopt(self, h: Dict[str, Any], _blob: bytes) -> Tuple[Dict[str, Any], bytes]:
        store = self._store()
        items = [M.Listed.from_wire(e) for e in h.get("entries", [])]
        n = store.adopt(items)
        store.save_index()
        return {"adopted": n, "epoch": store.epoch, "gen": store.gen}, b""

    def do_ping(self, h: Dict[str, Any], _blob: bytes) -> Tuple[Dict[str, Any], bytes]:
        return {"pong": True}, b""

    def do_bye(self, h: Dict[str, Any], _blob: bytes) -> Tuple[Dict[str, Any], bytes]:
        return {}, b""


def _sync_answer(store: Store, batch: Any) -> Dict[str, Any]:
    return {"results": [r.to_wire(op) for r, op in zip(batch.results, batch.ops)],
            "epoch": store.epoch, "gen": batch.gen}


def _error_frame(req_id: int, exc: Exception) -> wire.Frame:
    if isinstance(exc, StoreError):
        return wire.Frame(wire.T_ERROR, req_id, {"error": str(exc), "kind": "store"})
    if isinstance(exc, ProtocolError):
        return wire.Frame(wire.T_ERROR, req_id, {"error": str(exc), "kind": "protocol"})
    assert isinstance(exc, OSError)
    return wire.Frame(wire.T_ERROR, req_id, {
        "error": "%s%s" % (exc.strerror or exc, ": " + exc.filename if exc.filename else ""),
        "kind": "os", "errno": exc.errno or 0})


class _ReadAhead:
    """The request frames read ahead of the serving thread, their compressed parts
    inflated: up to READ_AHEAD of them holding up to READ_AHEAD_BYTES (a frame's data
    and its inflated part), or a single frame of any size.

    Four frames keep the laptop reading and compressing while a batch of large files
    is written here; the bound in bytes keeps a queue of large-file frames within the
    memory of one of small-file frames. The reading thread holds one frame more while
    it waits for room.
    """

    def __init__(self) -> None:
        self._items: Deque[Tuple[Any, int]] = collections.deque()
        self._bytes = 0
        self._cond = threading.Condition()

    def put(self, item: Any, size: int = 0) -> None:
        """Queue ``item``, once there is room for ``size`` more bytes."""
        with self._cond:
            while self._items and (len(self._items) >= READ_AHEAD
                                   or self._bytes + size > READ_AHEAD_BYTES):
                self._cond.wait()
            self._items.append((item, size))
            self._bytes += size
            self._cond.notify_all()

    def get(self, timeout: Optional[float] = None) -> Any:
        """The next item; queue.Empty if none came within ``timeout`` seconds."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._items, timeout):
                raise queue.Empty
            item, size = self._items.popleft()
            self._bytes -= size
            self._cond.notify_all()
            return item

    def empty(self) -> bool:
        return not self._items


def _unpacked(frame: Optional[wire.Frame]) -> Optional[Tuple[bytes, Any]]:
    """A sync request's compressed part, inflated by the reading thread (zlib lets go of
    the GIL) while the serving one applies the request before; None if it has none, or
    if it is bad: applying the request then says why."""
    if frame is None or frame.type != wire.T_REQUEST or frame.header.get("op") != "sync" \
            or frame.header.get("zpart") is None:
        return None
    try:
        return unpack_zpart(frame.blob, frame.header["zpart"])
    except ProtocolError:
        return None


# Frames read before they are served, and the most data they hold meanwhile: two
# frames (of up to 8 MiB of a push each) measured 2-5% slower on an initial push
READ_AHEAD = 4
READ_AHEAD_BYTES = 48 * 1024 * 1024
IDLE_TRIM_AFTER = 2.0  # seconds without a request before the heap is trimmed
_libc = None  # type: Any


def _tune_malloc() -> None:
    """Let glibc reuse the heap for frame-sized buffers instead of mmap'ing each afresh.

    Every 8 MiB frame, its inflated part and their slices would otherwise be
    new mappings, page-faulted in and zeroed by the kernel: ~70,000 faults and
    ~0.15 s of CPU on a 150 MB push. The heap is trimmed when idle instead.

    One arena for every thread: the reading thread allocates the frames and the
    serving thread frees them, and a thread's own arena unmaps a heap that
    empties whatever the trim threshold says (that thread had 30,000 of the
    endpoint's 34,000 faults in a 150 MB push; 21,000 with this). Must run
    before the first thread starts.
    """
    global _libc
    try:
        import ctypes  # here, once the hello is out: ~4 ms of every start
        _libc = ctypes.CDLL(None)
        _libc.mallopt(-3, 32 * 1024 * 1024)  # M_MMAP_THRESHOLD
        _libc.mallopt(-1, 64 * 1024 * 1024)  # M_TRIM_THRESHOLD
        _libc.mallopt(-8, 1)  # M_ARENA_MAX
    except (OSError, AttributeError):
        _libc = None  # not glibc: its own allocator's defaults


def _trim_heap() -> None:
    if _libc is not None:
        try:
            _libc.malloc_trim(0)
        except AttributeError:
            pass


def main() -> None:
    wire.widen_pipe(0)  # the push arrives on stdin
    # a push makes a few objects per file and no cycles worth the name, yet the
    # default thresholds ran ~100 collections in a 7,000-file push
    gc.freeze()
    gc.set_threshold(100000, 50, 100)
    # stdout carries frames only: anything else printed would corrupt the stream
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    try:
        Server(sys.stdin.buffer, out).serve()
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        pass
    except ProtocolError as exc:
        sys.stderr.write("fetchsync endpoint: %s\n" % exc)
        sys.exit(3)
    except Exception:
        import traceback  # only here: it costs every start ~2 ms to import
        traceback.print_exc()
        sys.exit(4)


if __name__ == "__main__":
    main()
