"""The resident's kept scan steps aside for a directory seen at two paths of src/.

The attack (redteam, session 22): inotify gives one watch descriptor per directory
inode, so a directory bind-mounted at a second path under ``src/`` got one descriptor,
mapped to whichever path was listed last; an edit under the other path was never
listed again, and the push made by the resident said "up to date" while a fresh scan
(which descends into the mount) sends it. The kept scan now scans in full while such
a tree exists.
"""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import pytest

from fetchsync.agent.keptscan import KeptScan
from fetchsync.protocol.ignore import build_rules
from fetchsync.protocol.store import is_temp
from fetchsync.sync.engine import scan_tree


@pytest.fixture
def bound(tmp_path: Path):
    """``src/a/shared`` bind-mounted at ``src/b/view``."""
    if os.geteuid() != 0:
        pytest.skip("a bind mount needs root")
    root = tmp_path / "src"
    (root / "a/shared").mkdir(parents=True)
    (root / "b/view").mkdir(parents=True)
    (root / "a/shared/f.txt").write_text("one\n")
    if subprocess.run(["mount", "--bind", str(root / "a/shared"), str(root / "b/view")]).returncode:
        pytest.skip("cannot bind-mount here")
    try:
        yield root
    finally:
        subprocess.run(["umount", "-l", str(root / "b/view")], check=False)


@pytest.mark.parametrize("edited", ["a/shared/f.txt", "b/view/f.txt"])
def test_an_edit_under_either_path_of_a_bind_mount_is_seen(bound, edited):
    kept = KeptScan(str(bound), build_rules(()), is_temp=is_temp)
    try:
        kept.scan()
        time.sleep(0.01)
        (bound / edited).write_text("two two\n")
        got = dict(kept.scan().entries)
        assert got == dict(scan_tree(str(bound), build_rules(())).entries)
    finally:
        kept.close()
