"""A fleet push works out each file's digest, kept record and compressibility once for all
its robots, kept with the content read once (SharedPacks.once; issue 27: one lookup per
file and robot), and every robot still ends up holding the tree a single push gives it."""

from __future__ import annotations

import collections
import os
import threading
import time
from pathlib import Path

import pytest
from test_fleet import fleet_env, push_three_in_process  # noqa: F401 - the fixture

from fetchsync.sync import engine as sync


def _settled(path: Path, data: bytes) -> None:
    path.write_bytes(data)
    old = time.time() - 60
    os.utime(path, (old, old))


def test_once_makes_a_shared_reads_value_once_for_threads_at_once(tmp_path, monkeypatch):
    monkeypatch.setattr(sync, "RACY_NS", 0)
    f = tmp_path / "a.cpp"
    _settled(f, b"int a = 1;\n" * 100)
    packs = sync.SharedPacks()
    made: list[bytes] = []
    go = threading.Event()

    def make(data: bytes) -> str:
        made.append(data)
        go.wait(5)  # the others arrive while it is being made
        return f"v{len(data)}"

    out: list[str] = []

    def robot() -> None:
        data, _ = packs.read(str(f))
        out.append(packs.once("x", data, make, lambda: "other"))

    threads = [threading.Thread(target=robot) for _ in range(4)]
    for t in threads:
        t.start()
    time.sleep(0.2)
    go.set()
    for t in threads:
        t.join(10)
    assert out == ["v1100"] * 4 and len(made) == 1
    # content not from a shared read: its own way
    assert packs.once("x", b"int a = 1;\n" * 100, make, lambda: "other") == "other"


def test_once_after_a_failed_make_makes_it_again(tmp_path, monkeypatch):
    monkeypatch.setattr(sync, "RACY_NS", 0)
    f = tmp_path / "a.cpp"
    _settled(f, b"int a = 1;\n")
    packs = sync.SharedPacks()
    data, _ = packs.read(str(f))

    def fail(_: bytes) -> str:
        raise OSError("no")

    with pytest.raises(OSError):
        packs.once("x", data, fail, lambda: "other")
    assert packs.once("x", data, lambda d: "made", lambda: "other") == "made"
    assert packs.once("x", data, fail, lambda: "other") == "made"  # kept now


@pytest.mark.ssh
def test_a_fleet_push_digests_and_keeps_each_file_once(
    fleet_env,  # noqa: F811
    tmp_path,
    monkeypatch,
    clean_process_env,
):
    src = Path(fleet_env["FETCHSYNC_WORKSPACE"]) / "src"
    pkg = src / "pkg_once"
    pkg.mkdir(parents=True)
    for i in range(6):
        (pkg / f"node{i}.cpp").write_bytes(b"int node%d(int x) { return x * %d; }\n" % (i, i) * 50)
    monkeypatch.setattr(sync, "RACY_NS", 0)  # every file counts as settled: shared reads
    lock = threading.Lock()
    digested: collections.Counter[bytes] = collections.Counter()
    kept: collections.Counter[bytes] = collections.Counter()
    real_hex, real_kept = sync.Syncer._hex, sync.Syncer._make_kept

    def hex_(self: sync.Syncer, data: bytes) -> str:
        with lock:
            digested[bytes(data)] += 1
        return real_hex(self, data)

    def make_kept(self: sync.Syncer, data: bytes) -> bytes | None:
        with lock:
            kept[bytes(data)] += 1
        return real_kept(self, data)

    monkeypatch.setattr(sync.Syncer, "_hex", hex_)
    monkeypatch.setattr(sync.Syncer, "_make_kept", make_kept)
    push_three_in_process(fleet_env, monkeypatch, tmp_path, src)  # every robot holds src
    ours = {(pkg / f"node{i}.cpp").read_bytes() for i in range(6)}
    assert ours <= set(digested) and ours <= set(kept)
    assert max(digested.values()) == 1, digested.most_common(1)[0][1]
    assert max(kept.values()) == 1, kept.most_common(1)[0][1]
