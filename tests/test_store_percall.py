"""The robot's per-file work when a batch writes new files (issue 24: the loopback initial
push spends its robot side per file). What each new file costs beyond its own create,
write and rename: no ``uname`` per rename (the renameat2 number is this machine's, looked
up once), and no look at the temporary's name again after a RENAME_NOREPLACE put it in
place (only an exchange can leave something there)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from fetchsync.protocol import hashing
from fetchsync.protocol import messages as M
from fetchsync.protocol import store as store_mod
from fetchsync.protocol.store import Store

ALG = "blake2b-128"
FILES = 40


def write(path: str, data: bytes, at: int) -> M.Op:
    return M.Op(
        M.WRITE,
        path,
        expect=M.ABSENT,
        mode=0o644,
        hash=hashing.digest(ALG, data).hex(),
        size=len(data),
        source=M.SRC_DATA,
        blob=(at, len(data)),
    )


@pytest.fixture
def store(tmp_path: Path):
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    yield s
    s.unlock()


def test_new_files_cost_no_uname_and_three_looks_each_at_their_rename(store, monkeypatch):
    calls = {"uname": 0, "lstat_at": 0}
    real_uname, real_lstat_at = os.uname, store_mod.lstat_at

    def uname():  # type: ignore[no-untyped-def]
        calls["uname"] += 1
        return real_uname()

    def lstat_at(name, dir_fd):  # type: ignore[no-untyped-def]
        calls["lstat_at"] += 1
        return real_lstat_at(name, dir_fd)

    datas = [b"file %d\n" % i for i in range(FILES)]
    blob = b"".join(datas)
    ops = [M.Op(M.MKDIR, "pkg", expect=M.ABSENT, mode=0o755)]
    at = 0
    for i, data in enumerate(datas):
        ops.append(write("pkg/f%d.txt" % i, data, at))
        at += len(data)
    monkeypatch.setattr(os, "uname", uname)
    monkeypatch.setattr(store_mod, "lstat_at", lstat_at)
    results = store.apply(ops, blob)
    monkeypatch.undo()
    assert all(r.ok for r in results), results
    for i, data in enumerate(datas):
        assert (Path(store.root) / "pkg" / ("f%d.txt" % i)).read_bytes() == data
    assert not [p for p in (Path(store.root) / "pkg").iterdir() if ".fetchsync-tmp-" in p.name]
    assert calls["uname"] == 0, calls
    # per new file: what stands at its path (the swap's and the conflict check's looks)
    # and what was written there after the rename; the mkdir's two looks
    assert calls["lstat_at"] <= 3 * FILES + 2, calls


def test_whole_contents_are_hashed_once_each(store, monkeypatch):
    """A new file sent whole is hashed once, as it lies in the request, before anything is
    written; the writer does not hash the same bytes again (a 40 MB file: a second pass)."""
    calls = {"digest": 0, "new": 0}
    real_digest, real_new = hashing.digest, hashing.new

    def digest(algorithm, data):  # type: ignore[no-untyped-def]
        calls["digest"] += 1
        return real_digest(algorithm, data)

    def new(algorithm):  # type: ignore[no-untyped-def]
        calls["new"] += 1
        return real_new(algorithm)

    datas = [b"whole %d\n" % i * (i + 1) for i in range(FILES)]
    ops, at = [], 0
    for i, data in enumerate(datas):
        ops.append(write("w%d.txt" % i, data, at))
        at += len(data)
    monkeypatch.setattr(hashing, "digest", digest)
    monkeypatch.setattr(hashing, "new", new)
    results = store.apply(ops, b"".join(datas))
    monkeypatch.undo()
    assert all(r.ok for r in results), results
    for i, data in enumerate(datas):
        assert (Path(store.root) / ("w%d.txt" % i)).read_bytes() == data
    assert calls == {"digest": FILES, "new": 0}, calls
