"""The laptop's Store during a pull (keep_replaced): a local file it replaces is linked
into the trash once its replacement is whole and then swapped out as the robot's
replacements are (renameat2), so a save made between the check and the rename is kept,
never overwritten; the trash counts it (its bound holds). In-process Store: the
pull over the real sshd is tests/test_pull_disk_full.py."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from endpoint_client import ALG
from test_trust_boundary import h, write

from fetchsync.protocol import messages as M
from fetchsync.protocol import store as store_mod
from fetchsync.protocol.store import Store

SAVED = b"saved by the user's editor in the window\n"


@pytest.fixture
def store(tmp_path: Path):
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.keep_replaced = True
    s.lock()
    yield s
    s.unlock()


def test_a_replaced_file_goes_to_the_trash_and_is_counted(store):
    assert store.apply([write("a.txt", b"v1" * 100)], b"v1" * 100)[0].ok
    [r] = store.apply([write("a.txt", b"v2", expect=M.expect_file(h(b"v1" * 100)))], b"v2")
    assert r.ok and not r.preserved
    assert (Path(store.root) / "a.txt").read_bytes() == b"v2"
    trashed = [p.read_bytes() for p in Path(store.meta, "trash").rglob("a.txt")]
    assert trashed == [b"v1" * 100]
    assert sum(n for _top, n in store.trash_log) == 200


@pytest.mark.parametrize("how", ["renamed over", "in place"])
def test_a_save_between_the_check_and_the_rename_is_kept(store, monkeypatch, how):
    path = Path(store.root) / "a.txt"
    assert store.apply([write("a.txt", b"v1")], b"v1")[0].ok
    real = Store._trashed
    armed = [True]

    def trashed(self, size):  # type: ignore[no-untyped-def]
        real(self, size)
        if armed[0]:  # the old version is in the trash now; the editor saves
            armed[0] = False
            if how == "in place":
                with open(path, "r+b") as fh:
                    fh.write(SAVED)
            else:
                tmp = path.with_name("a.txt.swp")
                tmp.write_bytes(SAVED)
                os.rename(tmp, path)

    monkeypatch.setattr(store_mod.Store, "_trashed", trashed)
    [r] = store.apply([write("a.txt", b"v2", expect=M.expect_file(h(b"v1")))], b"v2")
    monkeypatch.setattr(store_mod.Store, "_trashed", real)
    assert not armed[0]
    kept = [p.read_bytes() for p in Path(store.meta).rglob("a.txt")] + [path.read_bytes()]
    assert SAVED in kept, (r, kept)
    assert b"v1" in kept or how == "in place"  # (in place: the save was the v1 inode)
    assert not [p for p in Path(store.root).iterdir() if ".fetchsync-tmp-" in p.name]
