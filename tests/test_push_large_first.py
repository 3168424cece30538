"""A large round sends its first large files first (engine._large_first): the link is busy
from the first batch while the small text files behind them are deflated; the robot ends
with the same tree, whatever the order."""

from __future__ import annotations

import os
import random
from pathlib import Path

from helpers import tree_of

from fetchsync.link.client import Endpoint
from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.protocol import messages as M
from fetchsync.sync import engine as sync
from fetchsync.sync.plan import COPY, WHOLE, Planned
from fetchsync.sync.state import State


def _write(path: str, size: int, how: str = WHOLE, from_path: str = "") -> Planned:
    op = M.Op(M.WRITE, path, size=size, from_path=from_path)
    return Planned(op, how, M.Listed(path, "f", 0o644, size))


def _dirs(n: int) -> list[Planned]:
    return [Planned(M.Op(M.MKDIR, f"d{k}")) for k in range(n)]


def test_the_first_large_writes_go_first_after_the_directories() -> None:
    small = [_write(f"d0/s{k:04d}", 1000) for k in range(sync.LARGE_FROM)]
    large = [_write(f"d1/l{k}", 3 * 1024 * 1024) for k in range(5)]
    deletes = [Planned(M.Op(M.DELETE, "old"))]
    planned = _dirs(2) + small[:100] + large + small[100:] + deletes
    out = sync._large_first(planned)
    assert sorted(map(id, out)) == sorted(map(id, planned))  # the same operations
    assert out[:2] == planned[:2]  # directories first
    # large files up to LARGE_FIRST bytes (3 of 3 MiB), in their order, then the rest
    assert out[2:5] == large[:3]
    assert out[5:] == small[:100] + large[3:] + small[100:] + deletes


def test_a_file_another_write_copies_from_keeps_its_place() -> None:
    small = [_write(f"s{k:04d}", 1000) for k in range(sync.LARGE_FROM)]
    copied = _write("big_a", 4 * 1024 * 1024)
    copy = _write("z_copy", 4 * 1024 * 1024, how=COPY, from_path="big_a")
    other = _write("big_b", 4 * 1024 * 1024)
    planned = small[:10] + [copied] + small[10:] + [other, copy]
    out = sync._large_first(planned)
    assert out[0] is other and out.index(copied) == 11 and out[-1] is copy


def test_a_small_round_keeps_its_order() -> None:
    planned = [_write(f"s{k}", 10) for k in range(100)] + [_write("big", 8 * 1024 * 1024)]
    assert sync._large_first(planned) == planned


def test_a_large_round_lands_the_same_tree(tmp_path: Path, monkeypatch) -> None:
    """Over a real endpoint (local): 2,100 small files and a few large ones, large first."""
    batches: list[list[str]] = []
    send_sync = Endpoint.send_sync

    def recorded(self, ops, **kw):
        batches.append([op.path for op in ops if op.kind == M.WRITE])
        return send_sync(self, ops, **kw)

    monkeypatch.setattr(Endpoint, "send_sync", recorded)
    rng = random.Random(3)
    src = tmp_path / "ws/src"
    for k in range(sync.LARGE_FROM + 52):
        path = src / f"pkg{k % 7}" / f"f{k:04d}.txt"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"line %d\n" % k * rng.randint(1, 40))
    for k in range(4):
        (src / f"pkg{k}" / "mesh.bin").write_bytes(os.urandom(3 * 1024 * 1024))
    transport = LocalTransport(tmp_path / "robot-home")
    conn = Connection.open(transport)
    state = State(tmp_path / "state.sqlite")
    try:
        syncer = sync.Syncer(
            conn,
            state,
            local_root=str(src),
            remote_workspace=str(tmp_path / "robot"),
            rules=sync.build_rules(),
        )
        r = syncer.push()
        assert r.errors == [] and r.rounds == 1 and r.files == sync.LARGE_FROM + 56
        assert tree_of(src) == tree_of(tmp_path / "robot/src")
        # the first batch: the first large file alone (1 MiB batches first), then the next
        assert batches[0] == ["pkg0/mesh.bin"] and batches[1] == ["pkg1/mesh.bin"]
    finally:
        conn.close()
        state.close()
