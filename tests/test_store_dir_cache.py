"""A batch keeps the descriptors of the directories it writes in (issue 24: a burst of new
files in one directory walked it twice per file), but checks each again before every use:
a directory moved out of the tree and swapped for a symlink in the middle of a batch,
after its descriptor was kept, takes none of the batch's later writes with it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from fetchsync.protocol import hashing, paths
from fetchsync.protocol import messages as M
from fetchsync.protocol import store as store_mod
from fetchsync.protocol.store import Store

ALG = "blake2b-128"


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


def _batch(depth: int, files: int) -> tuple[list[M.Op], bytes]:
    top = "/".join("d%d" % k for k in range(depth))
    ops, blob = [], b""
    for i in range(files):
        data = b"file %d\n" % i
        ops.append(write("%s/f%d" % (top, i), data, len(blob)))
        blob += data
    return ops, blob


def _swap_out(root: Path, top: str, outside: Path) -> None:
    """``root/top`` moved out of the tree, a symlink to where it went in its place."""
    os.rename(root / top, outside / "moved")
    os.symlink(outside / "moved", root / top)


def _names(where: Path) -> list[str]:
    return sorted(p.name for p in where.rglob("*"))


@pytest.mark.parametrize("depth", [1, 3])
def test_a_directory_swapped_out_while_its_files_are_written_takes_none_of_the_later_ones(
    store, tmp_path, monkeypatch, depth
):
    root = Path(store.root)
    (root / "/".join("d%d" % k for k in range(depth))).mkdir(parents=True)
    outside = tmp_path / "outside"
    outside.mkdir()
    ops, blob = _batch(depth, 6)
    real = store_mod._Batch._write_temp
    calls = [0]

    def write_temp(self, op, dir_fd, name, tmp):  # type: ignore[no-untyped-def]
        real(self, op, dir_fd, name, tmp)
        calls[0] += 1
        if calls[0] == 2:  # two files written through the kept descriptor: now swapped
            _swap_out(root, "d0", outside)

    monkeypatch.setattr(store_mod._Batch, "_write_temp", write_temp)
    results = store.apply(ops, blob)
    monkeypatch.undo()
    assert calls[0] == 2  # the later files were never written anywhere
    assert all(r.code == M.PATH_ERROR and "symlink" in r.message for r in results), results
    # only the two temporaries written before the swap went with the moved directory
    moved = _names(outside / "moved")
    assert not [n for n in moved if n.startswith("f")], moved
    assert len([n for n in moved if ".fetchsync-tmp-" in n]) == 2, moved


def test_a_directory_swapped_out_before_the_renames_gets_no_file(store, tmp_path, monkeypatch):
    root = Path(store.root)
    (root / "d0").mkdir()
    outside = tmp_path / "outside"
    outside.mkdir()
    ops, blob = _batch(1, 6)
    real = store_mod.syncfs
    calls = [0]

    def syncfs(fd: int) -> None:
        real(fd)
        calls[0] += 1
        if calls[0] == 1:  # the temporaries are durable, the renames come next
            _swap_out(root, "d0", outside)

    monkeypatch.setattr(store_mod, "syncfs", syncfs)
    results = store.apply(ops, blob)
    monkeypatch.undo()
    assert all(r.code == M.PATH_ERROR for r in results), results
    assert not [n for n in _names(outside / "moved") if n.startswith("f")]


def test_a_directory_replaced_by_the_batch_itself_is_opened_again(store):
    """The batch's own delete and mkdir of a directory it wrote in: the later writes land
    in the new directory (the kept descriptor is of the one moved to the trash)."""
    root = Path(store.root)
    (root / "d0").mkdir()
    a, b = b"first\n", b"second\n"
    ops = [
        write("d0/x", a, 0),
        M.Op(M.DELETE, "d0", expect=M.IS_DIR),
        M.Op(M.MKDIR, "d0", expect=M.ABSENT, mode=0o755),
        write("d0/y", b, len(a)),
    ]
    results = store.apply(ops, a + b)
    assert all(r.ok for r in results[1:]), results
    assert sorted(os.listdir(root / "d0")) == ["y"]
    assert (root / "d0" / "y").read_bytes() == b


def test_kept_descriptors_are_bounded_and_given_back(store, monkeypatch):
    """Many directories in one batch: never more than Dirs.KEEP held, none after it."""
    monkeypatch.setattr(paths.Dirs, "KEEP", 8)
    root = Path(store.root)
    ops, blob = [], b""
    for i in range(40):
        (root / ("p%d" % i) / "q").mkdir(parents=True)
        data = b"%d\n" % i
        ops.append(write("p%d/q/f" % i, data, len(blob)))
        blob += data
    before = len(os.listdir("/proc/self/fd"))
    most = [0]
    real = paths.Dirs.parent

    def parent(self, path):  # type: ignore[no-untyped-def]
        got = real(self, path)
        most[0] = max(most[0], len(self.kept))
        return got

    monkeypatch.setattr(paths.Dirs, "parent", parent)
    results = store.apply(ops, blob)
    assert all(r.ok for r in results), results
    assert 0 < most[0] <= 8
    assert len(os.listdir("/proc/self/fd")) == before
    deep = "/".join("s%d" % k for k in range(paths.Dirs.DEPTH + 2))
    (root / deep).mkdir(parents=True)
    [r] = store.apply([write(deep + "/f", b"deep\n", 0)], b"deep\n")
    assert r.ok and (root / deep / "f").read_bytes() == b"deep\n"
