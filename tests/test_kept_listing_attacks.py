"""Attacks on the robot endpoint's kept listing (protocol/kept.py, redteam, session 23):
it must answer what a fresh walk (tree.scan_fd) finds after changes inotify does not
report in the tree."""

from __future__ import annotations

import os
import random
from pathlib import Path

from test_resident_keptscan import make_tree
from test_store_kept_listing import ALG, _rules

from fetchsync.protocol.store import Store, is_temp
from fetchsync.protocol.tree import IGNORE_FILE, scan_fd


def test_an_ignore_file_written_through_a_hard_link_from_outside_is_seen(tmp_path: Path) -> None:
    """The robot's ``.fetchsyncignore`` shares its inode with a file outside src/; a
    pattern added through that file makes no event in any watched directory. Its new
    stat alone was taken (a file's stat moved): the walk's rules below it stayed the old
    ones, and the kept listing kept listing what the new pattern excludes."""
    ws = tmp_path / "ws"
    root = ws / "src"
    make_tree(root, random.Random(3))
    (root / "pkg1" / "logs").mkdir()
    (root / "pkg1" / "logs" / "run.log").write_text("a log\n")
    ignore = root / "pkg1" / IGNORE_FILE
    ignore.write_text("# nothing ignored yet\n")
    outside = tmp_path / "outside-ignore"
    os.link(ignore, outside)
    store = Store(str(ws), algorithm=ALG, rules=_rules())
    store.keep_listing()
    store.lock()
    try:
        store.adopt(store.listing()[0])
        store.save_index()
        store.unlock()
        store.lock()
        assert store.src is not None
        assert store._scan().entries == scan_fd(store.src.fd, _rules(), is_temp=is_temp).entries
        with open(outside, "a") as fh:  # no event in any watched directory
            fh.write("logs/\n")
        fresh = scan_fd(store.src.fd, _rules(), is_temp=is_temp)
        assert "pkg1/logs/run.log" not in fresh.entries  # the new pattern holds for a walk
        assert store._scan().entries == fresh.entries
    finally:
        store.close()
