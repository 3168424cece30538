"""A batch's trash directory is named once: its time and generation (Store.stamp).

The name was taken again at each call: a second ticking over between a file's
set-aside (the directory it went to) and its count in the trash's log made the log
name a directory that does not exist, so pruning never removed the real one (the
trash's 512 MiB bound did not hold; tests/test_trash_chain.py failed so once under
CI's load), and a batch crossing a second kept its files in two directories. Here the
clock ticks a second at every call."""

from __future__ import annotations

import itertools
import time
from pathlib import Path

import pytest
from test_store import h, store, write  # noqa: F401 - the fixture

from fetchsync.protocol import messages as M
from fetchsync.protocol import store as store_mod


@pytest.fixture
def ticking(monkeypatch):
    """time.strftime in the store a second later at every call."""
    start = time.time() - 3600
    seconds = itertools.count()
    real = time.strftime

    def strftime(fmt: str, t: object = None) -> str:
        return real(fmt, time.localtime(start + next(seconds)))

    monkeypatch.setattr(store_mod.time, "strftime", strftime)


def _delete(store, name: str, data: bytes) -> M.Op:  # noqa: F811
    return M.Op(M.DELETE, name, expect=M.expect_file(h(data)))


def _batches(store) -> list[Path]:  # noqa: F811
    return sorted(p for p in (Path(store.meta) / "trash").iterdir() if p.is_dir())


def test_a_batch_deleting_files_keeps_them_in_one_trash_directory_its_log_names(
    store,  # noqa: F811
    ticking,
):
    files = {f"f{i}.txt": bytes([65 + i]) * 100 for i in range(3)}
    for name, data in files.items():
        store.apply([write(name, data)], data)
    store.apply([_delete(store, n, d) for n, d in files.items()], b"")
    (batch,) = _batches(store)
    assert sorted(p.name for p in batch.iterdir()) == sorted(files)
    assert [top for top, _n in store.trash_log] == [f"trash/{batch.name}"]


def test_the_trash_bound_removes_an_old_batch_whatever_the_clock_did(
    store,  # noqa: F811
    ticking,
    monkeypatch,
):
    monkeypatch.setattr(store_mod, "TRASH_KEEP_BYTES", 150)
    monkeypatch.setattr(store_mod, "TRASH_CHAIN", 0.5)  # each batch a deletion of its own
    old, new = b"o" * 100, b"n" * 100
    store.apply([write("old.txt", old)], old)
    store.apply([_delete(store, "old.txt", old)], b"")
    store.apply([write("new.txt", new)], new)
    store.apply([_delete(store, "new.txt", new)], b"")
    # 200 bytes in the trash, over the bound: the older batch goes, from the disk
    (batch,) = _batches(store)
    assert [p.name for p in batch.iterdir()] == ["new.txt"]
