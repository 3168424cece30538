"""The inotify-kept scan of a warm endpoint: after any change, it equals a fresh scan."""

from __future__ import annotations

import os
import random
import shutil
from pathlib import Path

import pytest

from fetchsync.protocol.ignore import IgnoreRules
from fetchsync.protocol.store import is_temp
from fetchsync.protocol.tree import scan
from fetchsync.protocol.watched import WatchedTree

RULES = IgnoreRules.build()


def fresh(root: Path) -> dict:
    return scan(str(root), RULES, is_temp=is_temp).entries


@pytest.fixture
def root(tmp_path: Path) -> Path:
    r = tmp_path / "src"
    (r / "pkg" / "src").mkdir(parents=True)
    (r / "pkg" / "src" / "a.cpp").write_text("int a;\n")
    (r / "pkg" / "package.xml").write_text("<package/>\n")
    (r / "other" / "deep" / "er").mkdir(parents=True)
    (r / "other" / "deep" / "er" / "x.py").write_text("x = 1\n")
    (r / "CMakeLists.txt").symlink_to("/opt/ros/noetic/share/catkin/cmake/toplevel.cmake")
    return r


def watched(root: Path) -> WatchedTree:
    tree = WatchedTree(str(root), RULES, is_temp)
    assert tree.entries == fresh(root)
    return tree


def test_edits_creations_deletions_and_modes_are_seen(root: Path) -> None:
    tree = watched(root)
    (root / "pkg" / "src" / "a.cpp").write_text("int a = 2;\n")
    (root / "pkg" / "src" / "b.cpp").write_text("int b;\n")
    (root / "pkg" / "package.xml").unlink()
    os.chmod(root / "other" / "deep" / "er" / "x.py", 0o755)
    os.chmod(root / "other" / "deep", 0o700)
    assert tree.refresh()
    assert tree.entries == fresh(root)


def test_new_directories_moves_and_removed_subtrees_are_seen(root: Path) -> None:
    tree = watched(root)
    (root / "new" / "sub").mkdir(parents=True)
    (root / "new" / "sub" / "f.txt").write_text("f\n")
    os.rename(root / "other" / "deep", root / "pkg" / "moved")
    (root / "pkg" / "moved" / "er" / "later.txt").write_text("after the move\n")
    shutil.rmtree(root / "other")
    assert tree.refresh()
    assert tree.entries == fresh(root)
    # events inside the moved directory now land under its new path
    (root / "pkg" / "moved" / "er" / "x.py").write_text("x = 2\n")
    assert tree.refresh()
    assert tree.entries == fresh(root)


def test_file_and_directory_swap_and_symlinks(root: Path) -> None:
    tree = watched(root)
    (root / "pkg" / "package.xml").unlink()
    (root / "pkg" / "package.xml").mkdir()
    (root / "pkg" / "package.xml" / "inside").write_text("i\n")
    shutil.rmtree(root / "other" / "deep")
    (root / "other" / "deep").write_text("now a file\n")
    (root / "CMakeLists.txt").unlink()
    (root / "CMakeLists.txt").symlink_to("elsewhere")
    assert tree.refresh()
    assert tree.entries == fresh(root)


def test_ignored_and_temporary_names_stay_out(root: Path) -> None:
    tree = watched(root)
    (root / "pkg" / ".git").mkdir()
    (root / "pkg" / ".git" / "HEAD").write_text("ref\n")
    (root / "pkg" / "src" / "a.cpp.swp").write_text("swap\n")
    (root / "pkg" / "src" / ".a.cpp.fetchsync-tmp-0123456789ab").write_text("tmp\n")
    assert tree.refresh()
    assert tree.entries == fresh(root)
    assert not any(".git" in p for p in tree.entries)


def test_a_changed_ignore_file_asks_for_a_full_scan(root: Path) -> None:
    tree = watched(root)
    (root / "pkg" / ".fetchsyncignore").write_text("*.xml\n")
    assert not tree.refresh()


def test_a_queue_overflow_asks_for_a_full_scan(root: Path) -> None:
    limit = int(Path("/proc/sys/fs/inotify/max_queued_events").read_text())
    if limit > 50_000:
        pytest.skip(f"max_queued_events is {limit}: too many events to provoke an overflow quickly")
    tree = watched(root)
    a, b = root / "pkg" / "src" / "a.cpp", root / "pkg" / "package.xml"
    for i in range(limit // 2 + 10):  # alternating, so the kernel cannot merge them
        os.chmod(a, 0o644 if i % 2 else 0o600)
        os.chmod(b, 0o644 if i % 2 else 0o600)
    assert not tree.refresh()


def test_random_changes_always_match_a_fresh_scan(root: Path) -> None:
    rnd = random.Random(7)
    tree = watched(root)
    for _round in range(30):
        for _ in range(rnd.randint(1, 6)):
            entries = fresh(root)
            dirs = [""] + [p for p, e in entries.items() if e.kind == "d"]
            files = [p for p, e in entries.items() if e.kind == "f"]
            act = rnd.choice(["new", "edit", "rm", "mkdir", "rmdir", "mv", "chmod"])
            d = root / rnd.choice(dirs)
            name = f"n{rnd.randint(0, 99)}"
            try:
                if act == "new":
                    (d / name).write_text(name)
                elif act == "edit" and files:
                    (root / rnd.choice(files)).write_text(str(rnd.random()))
                elif act == "rm" and files:
                    (root / rnd.choice(files)).unlink()
                elif act == "mkdir":
                    (d / name / "in").mkdir(parents=True)
                    (d / name / "in" / "f").write_text("f")
                elif act == "rmdir" and len(dirs) > 1:
                    shutil.rmtree(root / rnd.choice(dirs[1:]))
                elif act == "mv" and len(dirs) > 1:
                    src = root / rnd.choice(dirs[1:] + files)
                    dst = root / rnd.choice(dirs) / name
                    if not str(dst).startswith(str(src) + "/"):
                        os.rename(src, dst)
                elif act == "chmod" and files:
                    os.chmod(root / rnd.choice(files), rnd.choice([0o600, 0o644, 0o755]))
            except OSError:
                pass  # a collision with what is there: fine, whatever happened is the truth
        assert tree.refresh()
        assert tree.entries == fresh(root), f"round {_round}"
