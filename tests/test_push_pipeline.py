"""The push's pipeline: a batch is compressed while the one before it is on the link, and
the batches between the caller and the link are bounded (a fake endpoint whose sends
block until released: the link's pace is the test's)."""

from __future__ import annotations

import threading
from typing import Any

from fetchsync.link.client import Applied
from fetchsync.protocol import messages as M
from fetchsync.sync import engine as sync


class _Link:
    """An endpoint whose every send blocks until the test lets it through."""

    stl = False  # takes no split meshes (Endpoint.stl)

    class conn:  # noqa: N801 - stands for the Connection attribute
        compress = True
        bytes_in = bytes_out = 0
        last_arrival = 0.0  # when the latest answer came

        @staticmethod
        def check_link() -> None:
            pass

    def __init__(self) -> None:
        self.events: list[str] = []
        self.lock = threading.Lock()
        self.sending = threading.Event()
        self.go = threading.Semaphore(0)

    def note(self, event: str) -> None:
        with self.lock:
            self.events.append(event)

    def send_sync(self, ops: list[M.Op], **kw: Any) -> Any:
        self.note(f"send {ops[0].path}")
        self.sending.set()
        assert self.go.acquire(timeout=10)
        self.note(f"sent {ops[0].path}")
        return _Answer()


class _Answer:
    def answered(self) -> bool:
        return True

    def wait(self) -> Any:
        return Applied(False, "e", 1, [M.Result()])


def _batcher(link: _Link) -> sync._Batcher:
    return sync._Batcher(
        link,  # type: ignore[arg-type]
        policy="preserve",
        epoch="e",
        gen=0,
        progress=None,
        total=0,
    )


def _text(i: int) -> bytes:
    return b"".join(b"line %d of file %d\n" % (n, i) for n in range(2000))


def _write(path: str, data: bytes) -> M.Op:
    return M.Op(M.WRITE, path, expect=M.ABSENT, hash="00", size=len(data), source=M.SRC_DATA)


def test_the_next_batch_is_compressed_while_one_is_on_the_link(monkeypatch):
    link = _Link()
    batcher = _batcher(link)
    real = sync._Batcher._deflate

    def deflate(self: sync._Batcher, packed: list[bytes], *, level6: bool) -> list[bytes]:
        out = real(self, packed, level6=level6)
        link.note("deflated")
        return out

    monkeypatch.setattr(sync._Batcher, "_deflate", deflate)
    for i in range(2):
        data = _text(i)
        batcher.add(_write(f"f{i}", data), data)
        batcher.flush()
        if i == 0:
            assert link.sending.wait(10)  # the first batch is on the link, and stays there
    deadline = threading.Event()
    for _ in range(100):  # the second batch is compressed meanwhile
        with link.lock:
            if link.events.count("deflated") == 2:
                break
        deadline.wait(0.05)
    with link.lock:
        assert link.events == ["deflated", "send f0", "deflated"]
    link.go.release(2)
    assert len(batcher.answered(wait=True)) == 2
    assert link.events == ["deflated", "send f0", "deflated", "sent f0", "send f1", "sent f1"]


def test_the_batches_between_the_caller_and_a_stalled_link_are_bounded(monkeypatch):
    monkeypatch.setattr(sync, "LIVENESS_INTERVAL", 0.05)
    link = _Link()
    batcher = _batcher(link)
    added = []

    def caller() -> None:
        for i in range(sync.WINDOW + 3):
            data = _text(i)
            batcher.add(_write(f"f{i}", data), data)
            batcher.flush()
            added.append(i)

    thread = threading.Thread(target=caller, daemon=True)
    thread.start()
    assert link.sending.wait(10)
    thread.join(0.5)
    # the window (compressing, ready, on the link), and the caller waits to hand over
    # the next one
    assert thread.is_alive() and len(added) == sync.WINDOW
    link.go.release(sync.WINDOW + 3)
    thread.join(10)
    assert len(batcher.answered(wait=True)) == sync.WINDOW + 3


def test_an_abandoned_round_ends_the_batchers_threads():
    link = _Link()
    batcher = _batcher(link)
    for i in range(3):
        data = _text(i)
        batcher.add(_write(f"f{i}", data), data)
        batcher.flush()
    assert link.sending.wait(10)
    threads = list(batcher._threads)
    batcher.close()  # the caller gave up (an exception): what is queued is not sent
    link.go.release(1)
    for thread in threads:
        thread.join(10)
        assert not thread.is_alive()
    assert [e for e in link.events if e.startswith("send ")] == ["send f0"]
