"""A full laptop disk during a pull leaves every local file it could not replace in place.

The pull moved each local file it replaces to the trash first, then wrote the robot's
version; with no room for that write (ENOSPC) the file was gone from the laptop's src/
(only in .fetchsync/trash), and the next push, the watch agent's at once, deleted it from
the robot's src/ too. Now a replaced file goes to the trash only once its replacement is
whole, at the rename. Over the real sshd; the laptop's workspace on a small tmpfs."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import fetchsync, report, ssh_env, tree_of

pytestmark = pytest.mark.ssh

KiB = 1024


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(mnt)]).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield mnt
    finally:
        with contextlib.suppress(OSError):
            subprocess.run(["umount", "-l", str(mnt)], check=True)


def test_a_pull_onto_a_full_laptop_disk_loses_no_local_file(
    ssh_home, remote_dir, tmp_path, small_disk
):
    env = ssh_env(ssh_home.home, remote_dir, tmp_path, FETCHSYNC_WORKSPACE=str(small_disk / "ws"))
    src = small_disk / "ws/src"
    for i in range(5):
        (src / f"my_pkg/f{i}.txt").write_text(f"laptop version {i}\n" * 10)
    assert report(fetchsync("push", "--json", env=env))["ok"]
    before = tree_of(src)
    robot = remote_dir / "src/my_pkg"
    for i in range(5):
        (robot / f"f{i}.txt").write_bytes(os.urandom(600 * KiB))  # edited on the robot
    free = shutil.disk_usage(small_disk).free
    with open(small_disk / "fill", "wb") as fh:
        fh.write(bytes(free - 700 * KiB))  # room for one of the five
    proc = fetchsync("pull", "--json", "--yes", "--no-safety", env=env, check=False)
    assert proc.returncode == 5, proc.stderr.decode()
    assert "No space left on device" in proc.stderr.decode()
    after = tree_of(src)
    for i in range(5):
        rel = f"my_pkg/f{i}.txt"
        assert after[rel] in (before[rel], tree_of(remote_dir / "src")[rel]), rel
    assert sum(after[f"my_pkg/f{i}.txt"] == before[f"my_pkg/f{i}.txt"] for i in range(5)) >= 3
    # room again: a push deletes nothing on the robot, a pull then brings the rest
    os.unlink(small_disk / "fill")
    r = report(fetchsync("push", "--json", "--dry-run", env=env))
    assert not [p for p in r["planned"] if p["op"] == "delete"], r["planned"]
    assert report(fetchsync("pull", "--json", "--yes", "--no-safety", env=env))["ok"]
    assert tree_of(src) == tree_of(remote_dir / "src")
    # every laptop version replaced is kept (in the trash; those the failed pull could
    # not replace were then no longer the last synced: in the conflicts)
    meta = small_disk / "ws/.fetchsync"
    kept = [p.read_text() for p in meta.rglob("f*.txt") if p.parts[-4] in ("trash", "conflicts")]
    assert sorted(kept) == sorted(f"laptop version {i}\n" * 10 for i in range(5))


def test_a_large_file_filling_the_laptop_disk_is_one_line(
    ssh_home, remote_dir, tmp_path, small_disk
):
    """A file over BIG comes in upload pieces: the one that fills the disk keeps what it
    wrote until the pull ends, so the index written after it fails too: that was an
    OSError traceback (exit 1); now one line, the laptop's files as they were, nothing
    of the upload left, and once there is room the pull brings it."""
    env = ssh_env(ssh_home.home, remote_dir, tmp_path, FETCHSYNC_WORKSPACE=str(small_disk / "ws"))
    src = small_disk / "ws/src"
    assert report(fetchsync("push", "--json", env=env))["ok"]
    before = tree_of(src)
    (remote_dir / "src/my_pkg/map.pgm").write_bytes(os.urandom(40 << 20))  # over BIG
    proc = fetchsync("pull", "--json", "--yes", "--no-safety", env=env, check=False)
    err = proc.stderr.decode()
    assert proc.returncode != 0 and "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("fetchsync: error")]
    assert len(lines) == 1 and "No space left on device" in lines[0], err
    assert tree_of(src) == before
    assert not list((small_disk / "ws/.fetchsync/tmp").glob("upload-*"))
    (remote_dir / "src/my_pkg/map.pgm").write_bytes(os.urandom(2 << 20))  # it fits now
    assert report(fetchsync("pull", "--json", "--yes", "--no-safety", env=env))["ok"]
    assert tree_of(src) == tree_of(remote_dir / "src")
