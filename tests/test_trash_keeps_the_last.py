"""The robot's trash is bounded, but never below the batch just deleted.

The guard's hint says deleted files go to the robot's ``.fetchsync/trash/`` (also
after ``push --force``), and a push's deletions there are the way back from a
mistaken one. The bound (TRASH_KEEP_BYTES, 512 MiB) used to be applied to the batch
just made as well: a push deleting a file or a directory larger than the bound (a
rosbag, a model, a whole workspace after --force) had it removed from the trash at
once. Keeping the newest batch costs no disk the push had not found in use: its
files were renamed there, not copied.
"""

from __future__ import annotations

from pathlib import Path

from test_store import h, store, write  # noqa: F401 - the fixture

from fetchsync.protocol import messages as M
from fetchsync.protocol import store as store_mod


def test_a_deletion_larger_than_the_trash_bound_is_kept_until_a_later_one(store, monkeypatch):  # noqa: F811
    monkeypatch.setattr(store_mod, "TRASH_KEEP_BYTES", 4096)
    monkeypatch.setattr(store_mod, "TRASH_CHAIN", 0.0)  # each deletion its own (test_trash_chain)
    big = b"x" * 10000
    store.apply([write("big.bin", big)], big)
    store.apply([M.Op(M.DELETE, "big.bin", expect=M.expect_file(h(big)))], b"")
    kept = list((Path(store.meta) / "trash").rglob("big.bin"))
    assert [p.read_bytes() for p in kept] == [big]
    # the bound holds for what came before: the next deletion's batch replaces it
    small = b"small"
    store.apply([write("a.txt", small)], small)
    store.apply([M.Op(M.DELETE, "a.txt", expect=M.expect_file(h(small)))], b"")
    assert not list((Path(store.meta) / "trash").rglob("big.bin"))
    assert [p.read_bytes() for p in (Path(store.meta) / "trash").rglob("a.txt")] == [small]
