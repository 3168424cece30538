"""The resident's kept scan sees an edit through either of two hard links in src/.

The attack (redteam, session 22): inotify reports a write to the directory of the path
it was made through. With ``x/a.txt`` and ``y/b.txt`` one file (hard links), an edit
through ``x/a.txt`` listed ``x/`` again while ``y/b.txt`` kept its old stat: the push
made by the resident sent ``x/a.txt`` and not ``y/b.txt`` (a fresh push sends both),
and said "up to date" after that until the resident's next start. The paths of an
inode another path of the tree shares are now stat'ed again at each push.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
from helpers import fetchsync, report, tree_of
from test_resident import resident_env, resident_up

from fetchsync.agent.keptscan import KeptScan
from fetchsync.protocol.ignore import build_rules
from fetchsync.protocol.store import is_temp
from fetchsync.sync.engine import scan_tree


def test_an_edit_through_one_link_is_seen_at_the_other(tmp_path: Path) -> None:
    root = tmp_path / "src"
    (root / "x").mkdir(parents=True)
    (root / "y").mkdir()
    (root / "x/a.txt").write_text("one\n")
    os.link(root / "x/a.txt", root / "y/b.txt")
    kept = KeptScan(str(root), build_rules(()), is_temp=is_temp)
    try:
        kept.scan()
        for i, through in enumerate(["x/a.txt", "y/b.txt", "x/a.txt"]):
            time.sleep(0.01)
            with open(root / through, "a") as f:
                f.write(f"more {i}\n")
            assert dict(kept.scan().entries) == dict(scan_tree(str(root), build_rules(())).entries)
        (root / "y/b.txt").unlink()  # no longer linked: its directory's event says so
        (root / "x/a.txt").write_text("alone\n")
        assert dict(kept.scan().entries) == dict(scan_tree(str(root), build_rules(())).entries)
        assert kept.full_scans == 1
    finally:
        kept.close()


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    yield from resident_env(ssh_home.home, remote_dir, tmp_path)


@pytest.mark.ssh
def test_a_push_through_the_resident_sends_both_links_of_an_edited_file(env, remote_dir):
    src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    (src / "x").mkdir()
    (src / "y").mkdir()
    (src / "x/a.txt").write_text("one\n")
    os.link(src / "x/a.txt", src / "y/b.txt")
    resident_up(env)
    time.sleep(0.05)
    with open(src / "x/a.txt", "a") as f:
        f.write("edited through x\n")
    got = report(fetchsync("push", "--json", env=env))
    assert got["connection"] == "resident"
    assert (remote_dir / "src/y/b.txt").read_text() == "one\nedited through x\n"
    assert tree_of(src) == tree_of(remote_dir / "src")
