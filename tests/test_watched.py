"""The inotify-kept scan of a warm endpoint: after any change, it equals a fresh scan."""

from __future__ import annotations

import json
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


_LIMIT_SCRIPT = r'''
import json, os, sys, time
sys.path.insert(0, REPO)
root = sys.argv[1]
with open("/proc/sys/user/max_inotify_watches", "w") as fh:
    fh.write("4\n")            # in this user namespace only: the root and 3 directories
from fetchsync.agent.mux import SCAN_VERSION, Master
from fetchsync.protocol.store import Store
from fetchsync.sync import build_rules

def watches():
    n = 0
    for fd in os.listdir("/proc/self/fdinfo"):
        try:
            with open("/proc/self/fdinfo/" + fd) as fh:
                n += sum(line.startswith("inotify wd:") for line in fh)
        except OSError:
            pass
    return n

out = {}
store = Store(os.path.dirname(root), algorithm="blake2b-128")
out["store_watch"] = store.watch()
out["watches_after_store"] = watches()
rules = build_rules()
master = Master(transport=None, path="/nonexistent", idle=60, warm=None)
request = {"scan": root, "rules": rules.to_wire(), "v": SCAN_VERSION}
answers = []
for _ in range(40):
    try:
        master._scan(request)
        answers.append("entries")
    except ValueError as exc:
        answers.append(str(exc))
    if "cannot be watched" in answers[-1]:
        break
    time.sleep(0.05)
out["answers"] = answers
out["watches_after_master"] = watches()
print(json.dumps(out))
'''.replace("REPO", repr(str(Path(__file__).resolve().parent.parent)))


def test_over_the_watch_limit_nothing_is_kept_watched_nor_retried(tmp_path: Path) -> None:
    """A tree that cannot be watched whole gives its watches back at once (a watch agent
    needs them), on the robot's spare endpoint and in the connection master alike, and
    the master does not retry it on every call."""
    import subprocess
    import sys

    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("needs unshare (util-linux) for a user namespace of its own")
    src = tmp_path / "ws" / "src"
    for i in range(10):
        (src / f"d{i}").mkdir(parents=True)
    script = tmp_path / "limit.py"
    script.write_text(_LIMIT_SCRIPT)
    proc = subprocess.run([unshare, "--user", "--map-root-user", sys.executable, str(script), str(src)],
                          capture_output=True, text=True, timeout=60)
    if proc.returncode != 0 and "max_inotify_watches" in proc.stderr:
        pytest.skip("cannot set a user namespace's inotify limit here: " + proc.stderr[-300:])
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["store_watch"] is False and out["watches_after_store"] == 0
    assert out["answers"][0].startswith("starting")
    assert "cannot be watched" in out["answers"][-1] and "entries" not in out["answers"]
    assert out["watches_after_master"] == 0


def test_a_path_that_cannot_be_looked_at_makes_the_tree_untrusted(root: Path, monkeypatch) -> None:
    import fetchsync.protocol.watched as watched_mod

    tree = watched(root)
    (root / "pkg" / "src" / "a.cpp").write_text("changed\n")

    def refuse(full):
        raise PermissionError(13, "Permission denied", full)

    monkeypatch.setattr(watched_mod, "stat_path", refuse)
    assert not tree.refresh()  # its events are spent: the entries can no longer be vouched for
    monkeypatch.undo()
    assert not tree.refresh()  # and stay untrusted: the caller scans afresh
