"""The endpoint reads request frames ahead of the one it serves, within bounds."""

from __future__ import annotations

import queue
import threading
from typing import Any

import pytest

from fetchsync.protocol import hashing
from fetchsync.protocol import messages as M
from fetchsync.protocol import server as server_mod

ALG = "blake2b-128"


def h(data: bytes) -> str:
    return hashing.digest(ALG, data).hex()


def write(path: str, data: bytes, at: int, expect: str = M.ABSENT) -> dict[str, Any]:
    return M.Op(
        M.WRITE,
        path,
        expect=expect,
        mode=0o644,
        hash=h(data),
        size=len(data),
        source=M.SRC_DATA,
        blob=(at, len(data)),
    ).to_wire()


def sync(
    ops: list[dict[str, Any]], blob: bytes = b"", gen: int | None = None
) -> tuple[dict[str, Any], bytes]:
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
    assert q.get() == "large"  # served: held until the next is asked for
    assert waiting.is_alive()
    assert q.get() == "more"
    waiting.join(5)
    # a frame larger than the bound is taken when nothing is held before it (the one
    # served lets go when the next is asked for)
    waiting = _blocked(q.put, "huge", 3 * server_mod.READ_AHEAD_BYTES)
    assert q.get() == "huge"
    waiting.join(5)
    with pytest.raises(queue.Empty):
        q.get(timeout=0.01)
