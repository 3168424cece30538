"""The resident's kept scan answers what a fresh scan would, also where inotify is silent.

inotify reports a change to the watched directory of the path it was made through, and
not at all for a write through a shared mmap, or for what another machine writes to a
network file system. The kept scan therefore ``lstat``s every kept path again at each
push (a file takes its stat of now, as a fresh scan's), and steps aside (a full scan)
when the tree is not on a local file system or a mount point lies inside it. Each case
here made a push through the resident say "up to date" while a fresh push sent the
change (the robot stale until the resident's next start).
"""

from __future__ import annotations

import mmap
import os
import subprocess
import time
from pathlib import Path

import pytest
from helpers import fetchsync, report, tree_of
from test_resident import resident_env, resident_up

from fetchsync.agent import keptscan
from fetchsync.agent.keptscan import KeptScan
from fetchsync.protocol.ignore import build_rules
from fetchsync.protocol.store import is_temp
from fetchsync.sync.engine import scan_tree


def fresh(root: Path) -> dict[str, object]:
    return dict(scan_tree(str(root), build_rules(())).entries)


def kept_scan(root: Path) -> KeptScan:
    kept = KeptScan(str(root), build_rules(()), is_temp=is_temp)
    kept.scan()
    assert kept.warm
    return kept


def test_a_write_through_a_hard_link_outside_the_tree(tmp_path: Path) -> None:
    root = tmp_path / "src"
    (root / "pkg").mkdir(parents=True)
    (root / "pkg/a.cpp").write_text("int a;\n")
    os.link(root / "pkg/a.cpp", tmp_path / "outside.cpp")
    kept = kept_scan(root)
    try:
        time.sleep(0.01)
        with open(tmp_path / "outside.cpp", "a") as f:
            f.write("int b;\n")
        assert kept.scan().entries == fresh(root)
        assert kept.warm and kept.full_scans == 1  # answered from the kept scan
    finally:
        kept.close()


def test_a_write_through_a_shared_mmap(tmp_path: Path) -> None:
    root = tmp_path / "src"
    (root / "pkg").mkdir(parents=True)
    path = root / "pkg/map.bin"
    path.write_bytes(b"\0" * 8192)
    kept = kept_scan(root)
    try:
        time.sleep(0.01)
        with open(path, "r+b") as f, mmap.mmap(f.fileno(), 0) as m:
            m[100:105] = b"hello"
            m.flush()
        assert kept.scan().entries == fresh(root)
        assert kept.scan().entries["pkg/map.bin"].mtime_ns != 0
    finally:
        kept.close()


def test_a_directory_changed_without_an_event_is_listed_again(tmp_path: Path, monkeypatch) -> None:
    """What inotify misses on a directory (here: its events are thrown away, as for a
    change another machine made) is found by the directory's own stat."""
    root = tmp_path / "src"
    (root / "pkg/sub").mkdir(parents=True)
    (root / "pkg/sub/a.txt").write_text("a\n")
    kept = kept_scan(root)
    try:
        time.sleep(0.02)
        (root / "pkg/sub/b.txt").write_text("b\n")
        os.unlink(root / "pkg/sub/a.txt")
        monkeypatch.setattr(KeptScan, "_drain", lambda self: set())
        assert kept.scan().entries == fresh(root)
    finally:
        kept.close()


MOUNTINFO = (
    "22 1 8:1 / / rw,relatime shared:1 - {root_fs} /dev/sda1 rw\n"
    "30 22 0:25 / /proc rw,nosuid shared:12 - proc proc rw\n"
    "{extra}"
)


@pytest.mark.parametrize(
    ("root_fs", "extra", "kept"),
    [
        ("ext4", "", True),
        ("nfs4", "", False),
        ("fuse.sshfs", "", False),
        ("cifs", "", False),
        ("ext4", "40 22 0:50 / {tree}/pkg/remote rw - nfs server:/x rw\n", False),
        ("ext4", "41 22 0:51 / {tree}\\040sibling rw - tmpfs tmpfs rw\n", True),
        ("ext4", "42 22 0:52 / {tree} rw - nfs server:/ws rw\n", False),
    ],
)
def test_not_a_local_file_system_or_a_mount_inside_steps_aside(
    tmp_path: Path, root_fs: str, extra: str, kept: bool
) -> None:
    tree = os.path.realpath(tmp_path / "src")
    info = tmp_path / "mountinfo"
    info.write_text(MOUNTINFO.format(root_fs=root_fs, extra=extra.format(tree=tree)))
    if kept:
        keptscan._check_mounts(tree, str(info))
    else:
        with pytest.raises(keptscan._StepAside):
            keptscan._check_mounts(tree, str(info))


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a tmpfs needs root")
def test_a_mount_inside_the_tree_makes_a_full_scan(tmp_path: Path) -> None:
    root = tmp_path / "src"
    (root / "pkg/mnt").mkdir(parents=True)
    kept = kept_scan(root)
    subprocess.run(["mount", "-t", "tmpfs", "tmpfs", str(root / "pkg/mnt")], check=True)
    try:
        (root / "pkg/mnt/new.txt").write_text("on the mount\n")
        assert kept.scan().entries == fresh(root)
        assert kept.full_scans == 2
    finally:
        kept.close()
        subprocess.run(["umount", str(root / "pkg/mnt")], check=True)


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    yield from resident_env(ssh_home.home, remote_dir, tmp_path)


@pytest.mark.ssh
def test_a_resident_push_sends_a_write_made_through_an_outside_link(env, remote_dir, tmp_path):
    """End to end over the real sshd: the push is the resident's, and it sends the edit
    made through a hard link from outside src/."""
    src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    (src / "pkg").mkdir()
    (src / "pkg/a.cpp").write_text("int a;\n")
    os.link(src / "pkg/a.cpp", tmp_path / "outside.cpp")
    resident_up(env)
    time.sleep(0.05)
    with open(tmp_path / "outside.cpp", "a") as f:
        f.write("int b;\n")
    got = report(fetchsync("push", "--json", env=env))
    assert got["connection"] == "resident"
    assert (remote_dir / "src/pkg/a.cpp").read_text() == "int a;\nint b;\n"
    assert tree_of(src) == tree_of(remote_dir / "src")
