"""The mass-deletion guard's chain of deleting pushes outlives the watch agent's restart
and an outage longer than its window.

The guard counts the files the pushes just before deleted (an ``rm -rf`` reaches the
agent in pieces). That count lived in the agent process and ended RECENT seconds after
the last deleting push, however long the link was down: a piece of an ``rm -rf`` pushed,
the agent restarted (or the link down for a while), and the rest went as a push of its
own, allowed as long as it was under half of what was left. Here 60 of the robot's 100
files went that way without a pause; each restart or outage lets half of the rest go.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import pytest
from helpers import local_sync_loop, make_workspace, ssh_env
from test_watch import Watch, wait_for

from fetchsync.errors import TransportError
from fetchsync.sync import engine as sync

BIG, KEEP = 60, 33  # with make_workspace's 7 files and links: 100 on the robot


def fill(src: Path) -> None:
    for name, count in (("big", BIG), ("keep", KEEP)):
        (src / name).mkdir()
        for i in range(count):
            (src / f"{name}/f{i}.txt").write_text(f"{name} {i}\n")


def left(robot_src: Path) -> int:
    big = robot_src / "big"
    return sum(1 for p in big.iterdir()) if big.is_dir() else 0


@pytest.fixture
def runtime():
    d = Path(tempfile.mkdtemp(prefix="fsw", dir="/tmp"))  # AF_UNIX paths are short
    d.chmod(0o700)
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.mark.ssh
def test_the_count_goes_on_across_a_restart_of_the_agent(ssh_home, remote_dir, tmp_path, runtime):
    env = ssh_env(ssh_home.home, remote_dir, tmp_path, XDG_RUNTIME_DIR=str(runtime))
    src = tmp_path / "ws" / "src"
    fill(src)
    robot = remote_dir / "src"
    w = Watch(env, tmp_path / "watch.log")
    try:
        wait_for(lambda: w.status().get("state") == "live", what="the agent to be live")
        wait_for(lambda: left(robot) == BIG, what="the first sync")
        for i in range(BIG // 2):  # the first half of an rm -rf big: 30 of 100, it goes
            (src / f"big/f{i}.txt").unlink()
        wait_for(lambda: left(robot) == BIG // 2, what="the first half to go")
    finally:
        w.stop()
    shutil.rmtree(src / "big")  # the rest of it, while the agent is away
    w = Watch(env, tmp_path / "watch2.log")
    try:
        wait_for(
            lambda: w.status().get("state") in ("paused", "live"), what="the agent's first push"
        )
        st = w.status()
        assert st["state"] == "paused", (st, left(robot))
        assert f"{BIG // 2} of them deleted by the pushes just before" in st["last_error"]
        assert left(robot) == BIG // 2
    finally:
        w.stop()


@pytest.fixture
def agent(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """The watch agent's sync loop against the local robot, fed batches by the test, after
    the first sync; the chain's window is 1 s."""
    src = make_workspace(tmp_path / "ws") / "src"
    fill(src)
    monkeypatch.setattr(sync, "RECENT", 1.0)
    with local_sync_loop(tmp_path, monkeypatch) as (a, robot):
        assert left(robot) == BIG
        yield a, src, robot


def test_the_time_offline_does_not_end_the_count(agent):
    """Half an rm -rf pushed, the link down for longer than the chain's window, the rest
    pushed once it is back: one deletion still."""
    a, src, robot = agent
    half = BIG // 2
    for i in range(half):
        (src / f"big/f{i}.txt").unlink()
    done = a.wait_for(a.request(paths={f"big/f{i}.txt" for i in range(half)}), 60)
    assert done == (True, "") and left(robot) == half
    a._went_offline(None, TransportError("the link was lost"))
    time.sleep(1.5)  # offline for longer than the window (RECENT, 1 s here)
    shutil.rmtree(src / "big")
    done, why = a.wait_for(a.request(paths={f"big/f{i}.txt" for i in range(half, BIG)}), 60)
    assert not done and why.startswith("paused:"), why
    assert f"{half} of them deleted by the pushes just before" in why
    assert left(robot) == half


def test_a_pause_after_the_window_online_is_a_new_deletion(agent):
    """Not a pause for everything: online, a deletion after the window is a push of its own."""
    a, src, robot = agent
    for i in range(BIG // 2):
        (src / f"big/f{i}.txt").unlink()
    assert a.wait_for(a.request(paths={f"big/f{i}.txt" for i in range(BIG // 2)}), 60)[0]
    time.sleep(1.5)
    for i in range(BIG // 2, BIG // 2 + 10):
        (src / f"big/f{i}.txt").unlink()
    done = a.wait_for(
        a.request(paths={f"big/f{i}.txt" for i in range(BIG // 2, BIG // 2 + 10)}), 60
    )
    assert done == (True, "") and left(robot) == BIG // 2 - 10
