"""Attacks on the robot endpoint's kept listing (protocol/kept.py, redteam, session 23):
it must answer what a fresh walk (tree.scan_fd) finds after changes inotify does not
report in the tree."""

from __future__ import annotations

import os
import random
import shutil
from pathlib import Path

from test_resident_keptscan import make_tree
from test_store_kept_listing import ALG, _fresh_drift, _rules

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


def test_edits_made_to_look_unchanged_are_seen(tmp_path: Path) -> None:
    """Changes that keep what a quick look compares: a same-size edit with its mtime put
    back, a directory removed and made again with the same names (an inode number freed
    and reused), a file renamed over another with the same stamps, a directory swapped
    for a symlink to one outside, a file moved between directories: after each the kept
    listing and the drift are a fresh walk's."""
    ws = tmp_path / "ws"
    root = ws / "src"
    make_tree(root, random.Random(5))
    (root / "a").mkdir()
    (root / "a" / "x.txt").write_text("version one\n")
    (root / "a" / "y.txt").write_text("version one\n")
    (root / "b").mkdir()
    (root / "b" / "z.txt").write_text("zzz\n")
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "z.txt").write_text("not the robot's\n")
    store = Store(str(ws), algorithm=ALG, rules=_rules())
    store.keep_listing()
    store.lock()
    try:
        store.adopt(store.listing()[0])
        store.save_index()

        def same_mtime_edit() -> None:
            st = os.stat(root / "a" / "x.txt")
            (root / "a" / "x.txt").write_text("version two\n")
            os.utime(root / "a" / "x.txt", ns=(st.st_atime_ns, st.st_mtime_ns))

        def dir_made_again() -> None:
            shutil.rmtree(root / "b")
            (root / "b").mkdir()
            (root / "b" / "z.txt").write_text("zzZ\n")

        def renamed_over_with_same_stamps() -> None:
            st = os.stat(root / "a" / "y.txt")
            (root / "a" / ".y.new").write_text("version 2!\n")
            os.utime(root / "a" / ".y.new", ns=(st.st_atime_ns, st.st_mtime_ns))
            os.rename(root / "a" / ".y.new", root / "a" / "y.txt")

        def swapped_for_a_symlink() -> None:
            shutil.rmtree(root / "b")
            os.symlink(outside, root / "b")

        def moved_between_directories() -> None:
            os.rename(root / "a" / "x.txt", root / "pkg1" / "x.txt")

        for change in (
            same_mtime_edit,
            dir_made_again,
            renamed_over_with_same_stamps,
            swapped_for_a_symlink,
            moved_between_directories,
        ):
            store.unlock()
            change()
            store.lock()
            assert store.src is not None
            fresh = scan_fd(store.src.fd, _rules(), is_temp=is_temp)
            assert store._scan().entries == fresh.entries, change.__name__
            changed, gone = store.drift()
            assert ([x.to_wire() for x in changed], sorted(gone)) == _fresh_drift(ws), (
                change.__name__
            )
    finally:
        store.close()
