"""A fleet push reads and hashes each file once for all its robots (issue 27: the laptop's
CPU per robot), and hands a robot exactly what a fresh read would give: a file written
since, or written too recently to tell by its stat, is read again."""

from __future__ import annotations

import collections
import os
import threading
import time
from pathlib import Path

import pytest
from helpers import fetchsync
from test_fleet import fleet_env, push_three_in_process  # noqa: F401 - the fixture

from fetchsync.protocol import hashing
from fetchsync.sync import engine as sync
from fetchsync.sync.engine import SharedPacks


def test_a_shared_read_is_handed_out_again_only_while_the_file_is_unchanged(tmp_path, monkeypatch):
    monkeypatch.setattr(sync, "RACY_NS", 0)  # files written by this test count as settled
    f = tmp_path / "a.cpp"
    f.write_bytes(b"int a = 1;\n")
    packs = SharedPacks()
    first, entry = packs.read(str(f))
    again, entry2 = packs.read(str(f))
    assert again is first and entry2 == entry and packs.reads_shared == 1
    # the content's hashes are made once too
    calls = []

    def make(data: bytes) -> bytes:
        calls.append(data)
        return hashing.digest(hashing.BLAKE2B_128, data)

    assert packs.hashed("x", first, make) == packs.hashed("x", again, make)
    assert len(calls) == 1
    assert packs.hashed("x", b"int a = 1;\n", make) == make(b"int a = 1;\n")  # not a shared read
    time.sleep(0.02)  # past the file system's timestamp tick
    f.write_bytes(b"int a = 2;\n")  # same size, new content
    third, _ = packs.read(str(f))
    assert third == b"int a = 2;\n" and packs.reads_shared == 1
    f.unlink()
    with pytest.raises(FileNotFoundError):
        packs.read(str(f))


def test_a_file_written_within_the_racy_window_is_read_again_for_every_robot(tmp_path):
    """Rewritten within the file system's timestamp tick, a file's stat may not change:
    one written less than RACY_NS ago is never handed out again, however alike it looks."""
    f = tmp_path / "fresh.cpp"
    f.write_bytes(b"int a = 1;\n")
    packs = SharedPacks()
    first, _ = packs.read(str(f))
    again, _ = packs.read(str(f))
    assert again == first and again is not first and packs.reads_shared == 0
    f.write_bytes(b"int a = 2;\n")
    assert packs.read(str(f))[0] == b"int a = 2;\n" and packs.reads_shared == 0


def test_the_shared_reads_are_bounded(tmp_path, monkeypatch):
    monkeypatch.setattr(sync, "RACY_NS", 0)
    packs = SharedPacks(max_bytes=3000)
    for i in range(5):
        (tmp_path / f"{i}").write_bytes(bytes([65 + i]) * 1000)
        packs.read(str(tmp_path / f"{i}"))
    assert packs._read_size <= 3000 and len(packs._by_id) == len(packs._reads) <= 3
    assert packs.read(str(tmp_path / "4"))[0] == b"E" * 1000 and packs.reads_shared == 1
    assert packs.read(str(tmp_path / "0"))[0] == b"A" * 1000 and packs.reads_shared == 1


@pytest.mark.ssh
def test_a_fleet_push_reads_each_file_once_and_leaves_every_robot_identical(
    fleet_env,  # noqa: F811
    tmp_path,
    monkeypatch,
    clean_process_env,
):
    src = Path(fleet_env["FETCHSYNC_WORKSPACE"]) / "src"
    for i in range(60):
        pkg = src / f"pkg{i % 5}"
        pkg.mkdir(parents=True, exist_ok=True)
        (pkg / f"node{i}.cpp").write_bytes(b"int f%d(int x) { return x; }\n" % i * (20 + i))
    fetchsync("push", "--robot", "fetch1", env=fleet_env)  # fetch1 holds the tree already
    edited = src / "pkg0" / "node0.cpp"
    edited.write_bytes(edited.read_bytes() + b"// more\n")
    monkeypatch.setattr(sync, "RACY_NS", 0)  # the files above count as settled
    reads: collections.Counter[str] = collections.Counter()
    lock = threading.Lock()
    real = sync.read_stable

    def read_stable(full, **kw):
        with lock:
            reads[os.path.relpath(full, src)] += 1
        return real(full, **kw)

    monkeypatch.setattr(sync, "read_stable", read_stable)
    push_three_in_process(fleet_env, monkeypatch, tmp_path, src)
    files = [str(p.relative_to(src)) for p in src.rglob("*") if p.is_file()]
    assert set(reads) <= set(files) and len(reads) >= 60
    # fetch2 and fetch3 read the whole tree between them once, fetch1 its edit: each once
    assert max(reads.values()) == 1, reads.most_common(3)
