"""A full laptop disk when a push writes its state (the laptop's disk, not the robot's).

The robot has applied the push; the state's commit fails (SQLite: "database or disk is
full"). The push must end in one line naming the state, not a traceback (the failed
COMMIT's own rollback used to mask it with "cannot rollback - no transaction is active"),
the state stays behind the robot (never ahead), and once there is room again the next
push converges. The watch agent must say so and go on, not lose its sync thread.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import fetchsync, ssh_env, tree_of
from test_watch import Watch, same, wait_for

SIZE_KB = 400


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 400 KiB tmpfs for the laptop's state."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    if subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={SIZE_KB}k", "tmpfs", str(mnt)]
    ).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield mnt
    finally:
        with contextlib.suppress(OSError):
            subprocess.run(["umount", "-l", str(mnt)], check=True)


def fill(disk: Path, *, leave_kb: int) -> None:
    """Fill ``disk`` but ``leave_kb`` KiB."""
    (disk / "fill").unlink(missing_ok=True)
    free = shutil.disk_usage(disk).free // 1024
    with open(disk / "fill", "wb") as f:
        f.write(b"\0" * max(0, free - leave_kb) * 1024)


def edit_all(src: Path, n: int, tag: str) -> None:
    for i in range(n):
        (src / f"pkg/f{i}.txt").write_text(f"file {i} {tag}\n")


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path, small_disk):
    e = ssh_env(ssh_home.home, remote_dir, tmp_path, XDG_STATE_HOME=str(small_disk / "state"))
    (tmp_path / "ws/src/pkg").mkdir()
    edit_all(tmp_path / "ws/src", 50, "first")
    return e


@pytest.mark.ssh
def test_a_full_laptop_disk_at_the_state_commit_is_one_line_and_the_next_push_converges(
    env, small_disk, tmp_path, remote_dir
):
    src = tmp_path / "ws/src"
    fetchsync("push", env=env)
    failed_at_commit = 0
    for n, leave in enumerate((48, 40, 32, 24, 16, 8)):
        fill(small_disk, leave_kb=leave)
        edit_all(src, 50, f"edit {n}")
        proc = fetchsync("push", env=env, check=False)
        err = proc.stderr.decode()
        assert "Traceback" not in err, err
        if proc.returncode:
            lines = [line for line in err.splitlines() if line.startswith("fetchsync: ")]
            assert len(lines) == 1 and "state" in lines[0], err
            failed_at_commit += "cannot open" not in lines[0]
        (small_disk / "fill").unlink()
        # room again: the next push converges (what the robot holds from the failed one
        # is unknown to the state: it goes to the robot's conflicts, nothing is lost)
        fetchsync("push", env=env)
        assert tree_of(src) == tree_of(remote_dir / "src")
    assert failed_at_commit, "no push failed at its commit: the test's disk sizes are off"


@pytest.fixture
def runtime():
    d = Path(tempfile.mkdtemp(prefix="fsw", dir="/tmp"))  # AF_UNIX paths are short
    d.chmod(0o700)
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.mark.ssh
def test_the_watch_agent_goes_on_after_a_full_laptop_disk(
    env, small_disk, tmp_path, remote_dir, runtime
):
    env = dict(env, XDG_RUNTIME_DIR=str(runtime))
    src = tmp_path / "ws/src"
    w = Watch(env, tmp_path / "watch.log")
    try:
        wait_for(lambda: w.status().get("state") == "live", what="the agent to be live")
        wait_for(lambda: same(src, remote_dir / "src"), what="the first sync")
        fill(small_disk, leave_kb=0)
        edit_all(src, 50, "on a full disk")
        wait_for(lambda: w.status().get("last_error"), what="the agent to say why")
        assert "state" in w.status()["last_error"]
        (small_disk / "fill").unlink()
        (src / "pkg/after.txt").write_text("room again\n")
        wait_for(lambda: same(src, remote_dir / "src"), what="the agent to catch up")
        assert w.proc.poll() is None
        assert b"Traceback" not in (tmp_path / "watch.log").read_bytes()
    finally:
        w.stop()
