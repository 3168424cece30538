"""Attacks on the push's pipeline (59d72bf: a packer thread compresses a batch while the
one before it is on the link): an error on the packer thread, and a file that changes
between its batch's packing and its sending (over the local robot, no SSH)."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import tree_of

from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State


@pytest.fixture
def syncer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(sync, "BATCH_OPS", 20)
    monkeypatch.setattr(sync, "BATCH_BYTES", 16 * 1024)
    src = tmp_path / "ws" / "src"
    for d in range(6):
        (src / f"pkg{d}").mkdir(parents=True)
        for f in range(20):
            (src / f"pkg{d}" / f"f{f}.txt").write_text(f"{d} {f}\n" * (40 + f * d))
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    state = State(tmp_path / "state.sqlite")
    s = sync.Syncer(
        conn, state, local_root=str(src), remote_workspace="~/ws", rules=sync.build_rules()
    )
    yield s, src, tmp_path / "robot-home" / "ws" / "src"
    conn.close()
    state.close()


def test_an_error_on_the_packer_thread_fails_the_push_and_nothing_is_lost(syncer, monkeypatch):
    """The packer's exception is the push's: the push fails (no batch silently dropped
    and a success reported), and the next push lands the whole tree."""
    s, src, robot_src = syncer
    real = sync._Batcher._pack
    calls = []

    def pack(self, *args, **kw):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("the packer broke")
        return real(self, *args, **kw)

    monkeypatch.setattr(sync._Batcher, "_pack", pack)
    with pytest.raises(RuntimeError, match="the packer broke"):
        s.push()
    assert len(calls) >= 3
    monkeypatch.setattr(sync._Batcher, "_pack", real)
    report = s.push()
    assert report.errors == []
    assert tree_of(src) == tree_of(robot_src)


def test_a_file_changed_after_its_batch_was_packed_lands_as_read_then_as_changed(
    syncer, monkeypatch
):
    """What a batch carries is the bytes read and hashed, whatever the file becomes while
    the batch waits for the link: the robot gets the content recorded for it, and the
    next push sees the change and sends it."""
    s, src, robot_src = syncer
    real = sync._Batcher._pack
    changed: dict[str, bytes] = {}

    def pack(self, gen, items, tags):
        out = real(self, gen, items, tags)
        if not changed:
            for op, data, _ in items:
                if data:
                    path = src / op.path
                    before = path.read_bytes()
                    assert before == data
                    path.write_bytes(b"changed while its batch waited for the link\n")
                    changed[op.path] = before
                    break
        return out

    monkeypatch.setattr(sync._Batcher, "_pack", pack)
    report = s.push()
    assert report.errors == [] and changed
    ((path, before),) = changed.items()
    # the robot holds what was read (never a mix), the laptop the new content
    assert (robot_src / path).read_bytes() == before
    monkeypatch.setattr(sync._Batcher, "_pack", real)
    report = s.push()
    assert report.errors == []
    assert tree_of(src) == tree_of(robot_src)
    assert (robot_src / path).read_bytes() == b"changed while its batch waited for the link\n"


def test_an_error_on_the_packer_thread_stops_the_reading_at_once(syncer, monkeypatch):
    """After the packer fails, the caller does not go on reading and hashing the rest of
    the tree for nothing (all of it on a large workspace, before the error is said):
    it stops at its next batch, a window's worth of operations at most."""
    monkeypatch.setattr(sync, "BATCH_OPS", 10)
    s, src, robot_src = syncer
    real_pack, real_add = sync._Batcher._pack, sync._Batcher.add
    adds: list[int] = []
    failed_at: list[int] = []

    def pack(self, *args, **kw):
        if not failed_at and len(adds) >= 20:
            failed_at.append(len(adds))
            raise RuntimeError("the packer broke")
        return real_pack(self, *args, **kw)

    def add(self, *args, **kw):
        adds.append(1)
        return real_add(self, *args, **kw)

    monkeypatch.setattr(sync._Batcher, "_pack", pack)
    monkeypatch.setattr(sync._Batcher, "add", add)
    with pytest.raises(RuntimeError, match="the packer broke"):
        s.push()
    assert failed_at and len(adds) - failed_at[0] <= (sync.WINDOW + 1) * sync.BATCH_OPS
    assert len(adds) < 100  # of the tree's 120 files
