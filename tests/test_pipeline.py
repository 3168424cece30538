"""The endpoint's pipelined sync requests: a request's files are written while the
one before is flushed to disk, yet every answer keeps its order and reports only
what a completed syncfs made durable.

The endpoint runs in this process over in-memory streams, with the real store on
a temporary directory; ``syncfs``, ``os.rename`` and the answers are recorded in
one event log, the order the tests check.
"""

from __future__ import annotations

import io
import os
import queue
import threading
from pathlib import Path
from typing import Any

import pytest

from fetchsync.protocol import delta as delta_mod
from fetchsync.protocol import hashing, wire
from fetchsync.protocol import messages as M
from fetchsync.protocol import server as server_mod
from fetchsync.protocol import store as store_mod

ALG = "blake2b-128"


def h(data: bytes) -> str:
    return hashing.digest(ALG, data).hex()


def write(path: str, data: bytes, at: int, expect: str = M.ABSENT) -> dict[str, Any]:
    return M.Op(M.WRITE, path, expect=expect, mode=0o644, hash=h(data), size=len(data),
                source=M.SRC_DATA, blob=(at, len(data))).to_wire()


def sync(ops: list[dict[str, Any]], blob: bytes = b"", gen: int | None = None) -> tuple[dict[str, Any], bytes]:
    header: dict[str, Any] = {"op": "sync", "ops": ops, "policy": "preserve"}
    if gen is not None:
        header.update(require_fresh=True, epoch="?", gen=gen)
    return header, blob


def files(n: int, prefix: str) -> tuple[dict[str, Any], bytes]:
    """One request writing ``n`` new files ``<prefix>/f<i>``."""
    ops, blob = [{"k": M.MKDIR, "p": prefix, "e": M.ABSENT, "m": 0o755}], b""
    for i in range(n):
        data = (f"{prefix} {i}\n" * 50).encode()
        ops.append(write(f"{prefix}/f{i}", data, len(blob)))
        blob += data
    return sync(ops, blob)


class Run:
    """Serve ``requests`` (after an open) to the end of input; record what happened."""

    def __init__(self, workspace: Path, requests: list[tuple[dict[str, Any], bytes]],
                 monkeypatch: pytest.MonkeyPatch) -> None:
        self.events: list[tuple[Any, ...]] = []
        self.pipelined = 0
        events = self.events
        real_syncfs, real_rename = store_mod.syncfs, os.rename

        def syncfs(fd: int) -> None:
            events.append(("sync>",))
            real_syncfs(fd)
            events.append(("sync<",))

        def rename(src: Any, dst: Any, *a: Any, **k: Any) -> None:
            real_rename(src, dst, *a, **k)
            events.append(("rename", os.path.relpath(str(dst), str(workspace / "src"))))

        monkeypatch.setattr(store_mod, "syncfs", syncfs)
        monkeypatch.setattr(os, "rename", rename)
        run = self

        class Recording(server_mod.Server):
            def _send(self, frame: wire.Frame) -> None:
                events.append(("answer", frame.req_id))
                super()._send(frame)

            def _pipeline(self, frame: wire.Frame, frames: Any) -> bool:
                took = super()._pipeline(frame, frames)
                run.pipelined += took
                return took

        stream = wire.encode_hello({"algorithm": ALG})
        stream += wire.encode_frame(wire.Frame(wire.T_REQUEST, 1, {"op": "open", "workspace": str(workspace)}))
        self.requests = {}
        for i, (header, blob) in enumerate(requests, start=2):
            if header.get("require_fresh"):
                header = dict(header, epoch=self._epoch(workspace))
            self.requests[i] = header
            stream += wire.encode_frame(wire.Frame(wire.T_REQUEST, i, header, blob))
        out = io.BytesIO()
        Recording(io.BytesIO(stream), out).serve()
        reader = wire.Reader(io.BytesIO(out.getvalue()).read)
        reader.read_hello()
        self.answers: list[wire.Frame] = []
        while (frame := reader.read_frame()) is not None:
            self.answers.append(frame)

    @staticmethod
    def _epoch(workspace: Path) -> str:
        s = store_mod.Store(str(workspace), algorithm=ALG)
        return s.epoch

    def answer(self, req_id: int) -> wire.Frame:
        return next(a for a in self.answers if a.req_id == req_id)


@pytest.fixture(autouse=True)
def _cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setenv("HOME", str(tmp_path))


def test_pipelined_answers_keep_their_order_and_follow_a_syncfs_after_their_renames(tmp_path, monkeypatch):
    requests = [files(20, f"d{k}") for k in range(8)]
    run = Run(tmp_path / "ws", requests, monkeypatch)
    assert run.pipelined > 0  # the reader keeps requests queued: the pipeline is used
    assert [a.req_id for a in run.answers] == list(range(1, 10))
    ev = run.events
    for req_id in range(2, 10):
        answer = ev.index(("answer", req_id))
        assert all(r == M.AS_ASKED for r in run.answer(req_id).header["results"])
        written = [op["p"] for op in run.requests[req_id]["ops"] if op["k"] == M.WRITE]
        for path in written:
            renamed = ev.index(("rename", path))
            # the file's content was flushed before it was renamed into place ...
            assert any(e == ("sync<",) for e in ev[:renamed]), path
            # ... and a syncfs begun after the rename completed before the answer
            after = ev[renamed:answer]
            assert ("sync>",) in after and ("sync<",) in after[after.index(("sync>",)):], path
            assert (tmp_path / "ws" / "src" / path).read_bytes() == \
                (f"{path.split('/')[0]} {path.rsplit('f', 1)[1]}\n" * 50).encode()
    leftovers = [n for _d, _s, fs in os.walk(tmp_path / "ws" / "src") for n in fs if store_mod.is_temp(n)]
    assert leftovers == []
    assert not (tmp_path / "ws" / ".fetchsync" / store_mod.BATCH_MARK).exists()


def test_a_request_that_touches_the_held_requests_files_sees_them_in_place(tmp_path, monkeypatch):
    one, two = b"first version\n" * 2000, b"first version\n" * 1999 + b"second\n"
    sig = delta_mod.signature(one, algorithm=ALG)
    patch = delta_mod.encode_delta(delta_mod.delta(two, sig))
    fill = [files(5, f"pad{k}") for k in range(3)]
    requests = [
        fill[0],
        sync([{"k": M.MKDIR, "p": "a", "e": M.ABSENT, "m": 0o755}, write("a/x", one, 0),
              write("a/y", b"y", len(one))], one + b"y"),
        # a delta against the file the request before wrote
        sync([M.Op(M.WRITE, "a/x", expect=_expect(one), mode=0o644, hash=h(two),
                   size=len(two), source=M.SRC_DELTA, base=h(one), blob=(0, len(patch))).to_wire()], patch),
        fill[1],
        # the directory of a file written just before goes, and a file takes its place
        sync([{"k": M.MKDIR, "p": "b", "e": M.ABSENT, "m": 0o755}, write("b/z", b"z", 0)], b"z"),
        sync([{"k": M.DELETE, "p": "b", "e": "d"}, write("b", b"now a file", 0)], b"now a file"),
        fill[2],
    ]
    run = Run(tmp_path / "ws", requests, monkeypatch)
    assert [a.req_id for a in run.answers] == list(range(1, 9))
    for req_id in range(2, 9):
        results = run.answer(req_id).header["results"]
        assert all(r == M.AS_ASKED or r["c"] == M.OK for r in results), (req_id, results)
    root = tmp_path / "ws" / "src"
    assert (root / "a" / "x").read_bytes() == two
    assert (root / "b").read_bytes() == b"now a file"
    assert (tmp_path / "ws" / ".fetchsync" / "trash").exists()  # b/z went to the trash, not lost


def _expect(data: bytes) -> str:
    listed = M.Listed("a/x", "f", 0o644, len(data), hash=h(data))
    return listed.expectation()


def test_an_error_or_a_stale_request_between_pipelined_ones_is_answered_in_its_place(tmp_path, monkeypatch):
    bad = ({"op": "sync", "ops": [write("e/f", b"x", 0)], "zpart": [5, 99]}, b"xx")
    requests = [files(5, "p0"), files(5, "p1"), bad, files(5, "p2"), sync([], gen=999), files(5, "p3")]
    run = Run(tmp_path / "ws", requests, monkeypatch)
    assert [a.req_id for a in run.answers] == list(range(1, 8))
    assert run.answer(4).type == wire.T_ERROR
    assert run.answer(6).header.get("stale") is True
    gens = [run.answer(i).header["gen"] for i in (2, 3, 5, 7)]
    assert gens == sorted(gens) and len(set(gens)) == 4
    for d in ("p0", "p1", "p2", "p3"):
        assert len(os.listdir(tmp_path / "ws" / "src" / d)) == 5


def test_the_next_request_is_served_while_the_large_files_before_are_written(tmp_path, monkeypatch):
    """A request's large files are written by a second thread; the serving thread goes
    on to the next request meanwhile, and the large files are durable before they are
    renamed into place and answered."""
    big = os.urandom(store_mod.WRITE_APART + 1)
    first = sync([{"k": M.MKDIR, "p": "big", "e": M.ABSENT, "m": 0o755}, write("big/mesh.stl", big, 0)], big)
    requests = [files(3, "p0"), first, files(3, "p1"), files(3, "p2")]
    next_one = threading.Event()
    order: list[str] = []
    real_write_all, real_write_large = store_mod._write_all, store_mod._write_large

    def write_large(fd: int, data: Any) -> None:
        # held until the serving thread writes a file of the request after
        # (at most 5 s: the serving thread may instead wait for this one)
        next_one.wait(5)
        order.append("large written")
        real_write_large(fd, data)

    def write_all(fd: int, data: Any) -> None:
        serving = threading.current_thread() is threading.main_thread()
        if serving and not next_one.is_set() and "large begun" in order:
            order.append("next request")
            next_one.set()
        real_write_all(fd, data)

    real_put = store_mod._Writes.put

    def put(self: Any, fd: int, *args: Any) -> None:
        if fd >= 0:  # not the end mark
            order.append("large begun")
        real_put(self, fd, *args)

    monkeypatch.setattr(store_mod, "_write_all", write_all)
    monkeypatch.setattr(store_mod, "_write_large", write_large)
    monkeypatch.setattr(store_mod._Writes, "put", put)
    run = Run(tmp_path / "ws", requests, monkeypatch)
    assert order == ["large begun", "next request", "large written"]
    assert [a.req_id for a in run.answers] == list(range(1, 6))
    assert all(r == M.AS_ASKED for r in run.answer(3).header["results"])
    assert (tmp_path / "ws" / "src" / "big" / "mesh.stl").read_bytes() == big
    ev = run.events
    renamed, answered = ev.index(("rename", "big/mesh.stl")), ev.index(("answer", 3))
    assert ("sync<",) in ev[:renamed] and ("sync>",) in ev[renamed:answered]


def test_a_begun_batch_keeps_the_lock_until_it_is_finished(tmp_path):
    """Another writer taking the lock between two pipelined requests would take the
    held one's temporaries for a dead writer's, and delete them."""
    s = store_mod.Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    batch = s.begin([M.Op.from_wire(write("f", b"data", 0))], b"data")
    s.unlock()  # as after every request: not while a batch is open
    other = store_mod.Store(str(tmp_path / "ws"), algorithm=ALG)
    with pytest.raises(store_mod.StoreError):
        other.lock(timeout=0.0)
    assert (tmp_path / "ws" / ".fetchsync" / store_mod.BATCH_MARK).exists()
    s.finish(batch)
    s.unlock()
    other.lock(timeout=0.0)
    assert not (tmp_path / "ws" / ".fetchsync" / store_mod.BATCH_MARK).exists()
    assert (tmp_path / "ws" / "src" / "f").read_bytes() == b"data"
    other.unlock()


def _blocked(target: Any, *args: Any) -> threading.Thread:
    """``target(*args)`` in a thread, which it must still be in 0.2 s later."""
    thread = threading.Thread(target=target, args=args, daemon=True)
    thread.start()
    thread.join(0.2)
    assert thread.is_alive()
    return thread


def test_frames_are_read_ahead_up_to_a_count_and_a_size():
    q = server_mod._ReadAhead()
    for i in range(server_mod.READ_AHEAD):
        q.put(i, 1)
    waiting = _blocked(q.put, "next", 1)  # full by count
    assert q.get() == 0
    waiting.join(5)
    assert not waiting.is_alive()
    for i in range(1, server_mod.READ_AHEAD):
        assert q.get() == i
    assert q.get() == "next" and q.empty()
    # by size: one frame holding most of the bound leaves no room for the next
    q.put("large", server_mod.READ_AHEAD_BYTES - 10)
    waiting = _blocked(q.put, "more", 20)
    assert q.get() == "large"
    waiting.join(5)
    assert q.get() == "more"
    # a frame larger than the bound is taken when nothing waits before it
    q.put("huge", 3 * server_mod.READ_AHEAD_BYTES)
    assert q.get() == "huge"
    with pytest.raises(queue.Empty):
        q.get(timeout=0.01)
