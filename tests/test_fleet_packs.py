"""A fleet push compresses each batch once for the robots that send the same batch (issue
27's "compresses once"), against the real sshd (aliases stand for robots, as in
test_fleet)."""

from __future__ import annotations

import collections
import threading
from pathlib import Path

import pytest
from helpers import fetchsync
from test_fleet import fleet_env, push_three_in_process  # noqa: F401 - the fixture

from fetchsync.sync import engine as sync

pytestmark = pytest.mark.ssh


def _files(src: Path, names: range) -> None:
    for i in names:
        pkg = src / f"pkg{i % 7}"
        pkg.mkdir(parents=True, exist_ok=True)
        (pkg / f"node{i}.cpp").write_bytes(
            b"".join(b"int f%d_%d(int x) { return x * %d; }\n" % (i, n, n) for n in range(60 + i))
        )


def test_a_fleet_push_compresses_each_batch_once_and_leaves_every_robot_identical(
    fleet_env,  # noqa: F811
    tmp_path,
    monkeypatch,
    clean_process_env,
):
    src = Path(fleet_env["FETCHSYNC_WORKSPACE"]) / "src"
    _files(src, range(0, 40))
    # fetch1 starts from a push of part of the tree: its state and its batches differ
    fetchsync("push", "--robot", "fetch1", env=fleet_env)
    _files(src, range(40, 120))
    edited = src / "pkg0" / "node0.cpp"
    edited.write_bytes(edited.read_bytes().replace(b"x * 5;", b"x * 55;"))

    # batches under 64 KiB (but the first, with the workspace's 2.4 MB data.txt: a push's
    # first batch is always level 6): level 6 whatever the link, so the same plan makes the
    # same bytes
    monkeypatch.setattr(sync, "BATCH_BYTES", 48 * 1024)
    sent: collections.Counter[str] = collections.Counter()
    made: collections.Counter[str] = collections.Counter()
    lock = threading.Lock()
    real_measure, real_deflate = sync._Batcher._measure_link, sync._Batcher._deflate

    def measure(self):  # once per batch with data to compress
        with lock:
            sent[self.conn.transport.name] += 1
        return real_measure(self)

    def deflate(self, packed, *, level6):
        with lock:
            made[self.conn.transport.name] += 1
        return real_deflate(self, packed, level6=level6)

    monkeypatch.setattr(sync._Batcher, "_measure_link", measure)
    monkeypatch.setattr(sync._Batcher, "_deflate", deflate)
    push_three_in_process(fleet_env, monkeypatch, tmp_path, src)
    assert sent["fetch2"] == sent["fetch3"] >= 4
    assert sent["fetch1"] >= 2
    # fetch2 and fetch3 (the same state) share every batch; fetch1's are its own
    assert sum(made.values()) == sent["fetch1"] + sent["fetch2"]


def test_a_fleet_pushs_kept_records_are_made_once_each_and_as_a_single_push_makes_them():
    """What the state keeps of each content (its deflated self, or its signature) is made
    once for a fleet's robots, and is what a single push would keep."""
    from types import SimpleNamespace

    from fetchsync.protocol import hashing
    from fetchsync.sync.engine import SharedPacks, Syncer

    algorithm = hashing.available()[0]
    alone = SimpleNamespace(algorithm=algorithm, packs=None)
    alone._make_kept = lambda data: Syncer._make_kept(alone, data)
    made: list[bytes] = []
    packs = SharedPacks()

    def robot() -> SimpleNamespace:
        r = SimpleNamespace(algorithm=algorithm, packs=packs)
        r._make_kept = lambda data: made.append(data) or Syncer._make_kept(r, data)
        return r

    robots = [robot() for _ in range(3)]
    contents = [b"int main() {}\n" * n for n in (1, 100, 5000)] + [b"\0binary" * 10]
    for data in contents:
        single = Syncer._kept_of(alone, data)
        for r in robots:
            assert Syncer._kept_of(r, data) == single
    assert sorted(made) == sorted(contents[:3])  # each text content once; binary: nothing kept
