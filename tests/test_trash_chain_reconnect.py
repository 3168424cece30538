"""One deletion keeps all its trash batches also across endpoint sessions: the watch
agent reconnecting in the middle of an ``rm -rf`` (a new connection, a new endpoint, a
new Store) goes on with the same deletion. The chain (store.TRASH_CHAIN) was kept in the
Store's memory: the new session's first batch of the deletion pruned the batches the
earlier session had trashed (over TRASH_KEEP_BYTES), the first part of the deletion
gone from the robot before it ended (redteam, session 23)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from helpers import fetchsync, ssh_env
from test_store import ALG, h, write

from fetchsync.protocol import messages as M
from fetchsync.protocol import store as store_mod
from fetchsync.protocol.store import Store


def _trashed(root: Path) -> list[str]:
    return sorted(p.name for p in (root / ".fetchsync/trash").rglob("*.bag"))


def test_a_deletion_going_on_in_a_new_session_keeps_the_first_ones_batches(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(store_mod, "TRASH_KEEP_BYTES", 15000)
    bags = {f"bag{i}.bag": bytes([65 + i]) * 10000 for i in range(3)}
    first = Store(str(tmp_path / "ws"), algorithm=ALG)
    first.lock()
    for name, data in bags.items():
        first.apply([write(name, data)], data)
    for name in ("bag0.bag", "bag1.bag"):  # the rm -rf's first part, two batches
        first.apply([M.Op(M.DELETE, name, expect=M.expect_file(h(bags[name])))], b"")
    first.save_index()
    first.unlock()
    first.close()
    assert _trashed(tmp_path / "ws") == ["bag0.bag", "bag1.bag"]
    second = Store(str(tmp_path / "ws"), algorithm=ALG)  # the agent reconnected
    second.lock()
    try:
        data = bags["bag2.bag"]
        second.apply([M.Op(M.DELETE, "bag2.bag", expect=M.expect_file(h(data)))], b"")
    finally:
        second.unlock()
        second.close()
    assert _trashed(tmp_path / "ws") == sorted(bags)


@pytest.mark.ssh
def test_two_connections_deleting_in_quick_succession_keep_both_in_the_trash(
    ssh_home, remote_dir: Path, tmp_path: Path
) -> None:
    """End to end over the real sshd: two 300 MiB bags (sparse) deleted by two pushes a
    moment apart, each its own connection and endpoint (as the watch agent's pushes
    before and after a reconnection): the first is still in the trash after the second
    (600 MiB, over the 512 MiB bound)."""
    env = ssh_env(ssh_home.home, remote_dir, tmp_path)
    src = tmp_path / "ws/src"
    (src / "bags").mkdir()
    for i in range(2):
        with open(src / f"bags/bag{i}.bag", "wb") as f:
            f.truncate(300 * 1024 * 1024)
    for i in range(20):
        (src / f"bags/note{i}.txt").write_text(f"{i}\n")
    fetchsync("push", env=env)
    time.sleep(1.0)
    for i in range(2):
        (src / f"bags/bag{i}.bag").unlink()
        fetchsync("push", env=env)
    assert _trashed(remote_dir) == ["bag0.bag", "bag1.bag"]
