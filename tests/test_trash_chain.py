"""One deletion in several batches keeps all of them in the robot's trash until it ends.

The attack (redteam, session 22): a deletion larger than the trash's bound
(TRASH_KEEP_BYTES, 512 MiB) that reaches the robot in several batches (one push's
deletions beyond BATCH_OPS, the watch agent's ``rm -rf`` of a directory of rosbags
seen in bursts) had its first batches pruned from the trash by its later ones: the
files it deleted first were gone before it ended, although the guard's hint and the
README promise the way back from a deletion in the trash. Batches of one store within
TRASH_CHAIN seconds of each other are one deletion now; the bound applies to what came
before it (and to it, once a later deletion comes).
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from helpers import fetchsync, ssh_env
from test_store import h, store, write  # noqa: F401 - the fixture

from fetchsync.protocol import messages as M
from fetchsync.protocol import store as store_mod


def _delete(store, name: str, data: bytes) -> None:  # noqa: F811
    store.apply([M.Op(M.DELETE, name, expect=M.expect_file(h(data)))], b"")


def _trashed(store) -> list[str]:  # noqa: F811
    return sorted(p.name for p in (Path(store.meta) / "trash").rglob("*.bag"))


def test_the_batches_of_one_deletion_stay_in_the_trash_until_it_ends(store, monkeypatch):  # noqa: F811
    monkeypatch.setattr(store_mod, "TRASH_KEEP_BYTES", 15000)
    monkeypatch.setattr(store_mod, "TRASH_CHAIN", 2.0)
    bags = {f"bag{i}.bag": bytes([65 + i]) * 10000 for i in range(3)}
    for name, data in bags.items():
        store.apply([write(name, data)], data)
    old = b"o" * 100
    store.apply([write("old.bag", old)], old)
    _delete(store, "old.bag", old)
    time.sleep(3.5)  # a deletion long before: the bound applies to it (names: to the second)
    for name, data in bags.items():  # one deletion, three batches: 30,000 bytes
        _delete(store, name, data)
        assert (
            _trashed(store)[: list(bags).index(name) + 1]
            == sorted(bags)[: list(bags).index(name) + 1]
        )
    assert _trashed(store) == sorted(bags)
    # a later deletion: the bound applies again, the newest batch kept
    time.sleep(3.5)
    small = b"s" * 10
    store.apply([write("small.bag", small)], small)
    _delete(store, "small.bag", small)
    assert _trashed(store) == ["bag2.bag", "small.bag"]  # within the bound again


@pytest.mark.ssh
def test_a_push_deleting_beyond_the_bound_in_several_batches_keeps_them_all(
    ssh_home, remote_dir, tmp_path
):
    """End to end: a push deleting 4,002 files (two batches of BATCH_OPS) of which two
    sparse 300 MiB bags (600 MiB, over the bound; no disk used) in its first batch."""
    env = ssh_env(ssh_home.home, remote_dir, tmp_path)
    src = tmp_path / "ws/src"
    (src / "a").mkdir()
    (src / "z").mkdir()
    for i in range(2):
        with open(src / f"a/bag{i}.bag", "wb") as f:
            f.truncate(300 * 1024 * 1024)
    for i in range(4000):
        (src / f"z/f{i:04}.txt").write_text(f"{i}\n")
    fetchsync("push", env=env)
    for p in [*src.glob("a/*.bag"), *src.glob("z/*.txt")]:
        p.unlink()
    fetchsync("push", "--force", env=env)
    trash = remote_dir / ".fetchsync/trash"
    assert sorted(p.name for p in trash.rglob("*.bag")) == ["bag0.bag", "bag1.bag"]
    assert len(list(trash.rglob("f*.txt"))) == 4000


@pytest.mark.ssh
def test_the_watch_agents_deletions_in_quick_succession_stay_in_the_trash(
    ssh_home, remote_dir, tmp_path
):
    """The watch agent: two 300 MiB bags (sparse) removed a few seconds apart, each its
    own push on the agent's one connection: the first is still in the trash after the
    second (the old bound pruned it: 600 MiB > 512)."""
    import shutil
    import tempfile

    from test_watch import Watch, same, wait_for

    runtime = Path(tempfile.mkdtemp(prefix="fsw", dir="/tmp"))
    runtime.chmod(0o700)
    env = ssh_env(ssh_home.home, remote_dir, tmp_path, XDG_RUNTIME_DIR=str(runtime))
    src = tmp_path / "ws/src"
    (src / "bags").mkdir()
    for i in range(2):
        with open(src / f"bags/bag{i}.bag", "wb") as f:
            f.truncate(300 * 1024 * 1024)
    for i in range(20):
        (src / f"bags/note{i}.txt").write_text(f"{i}\n")
    fetchsync("push", env=env)
    trash = remote_dir / ".fetchsync/trash"
    w = Watch(env, tmp_path / "watch.log")
    try:
        wait_for(lambda: w.status().get("state") == "live", what="the agent to be live")
        for i in range(2):
            (src / f"bags/bag{i}.bag").unlink()
            wait_for(lambda: same(src, remote_dir / "src"), what=f"bag{i}'s deletion")
        assert sorted(p.name for p in trash.rglob("*.bag")) == ["bag0.bag", "bag1.bag"]
    finally:
        w.stop()
        shutil.rmtree(runtime, ignore_errors=True)
