"""A robot whose disk is full when the endpoint must cache itself (a new fetchsync
version, a cleaned cache: ROS logs fill robots' disks): the start fails with the disk's
reason as its last line, and leaves no partial file behind (each failed start would
leave another, filling what the user frees)."""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_loader import _run_loader


@pytest.fixture
def full_home(tmp_path: Path) -> Iterator[Path]:
    """A home on a 64 KiB tmpfs: too small for the endpoint's archive (~70 KB)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)])
    if made.returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        (mnt / "home").mkdir()
        yield mnt / "home"
    finally:
        with contextlib.suppress(OSError):
            subprocess.run(["umount", str(mnt)], check=True)


def test_a_full_robot_disk_fails_the_start_in_one_line_and_leaves_nothing(full_home: Path):
    got, magic = _run_loader(full_home)
    assert got.returncode != 0 and magic not in got.stdout
    last = got.stderr.decode().strip().splitlines()[-1]  # what the laptop shows
    assert "No space left on device" in last, got.stderr
    left = [p.name for p in (full_home / ".cache" / "fetchsync").iterdir()]
    assert not [n for n in left if n.endswith(".tmp")], left
