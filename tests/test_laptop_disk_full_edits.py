"""After a push whose laptop state commit failed (full disk), nothing is lost.

The robot then holds that push's files, unknown to the state (which stays behind the
robot). Attack (redteam, session 22): the user edits on both sides before the next
push. The robot-side edit made meanwhile must be kept (never taken for the failed
push's own write and overwritten), the laptop's newer edit must win, and resolving the
false conflict (the failed push's own version kept as "changed on the robot") as the
CLI says (``conflicts restore``) must keep the laptop's newer file.
"""

from __future__ import annotations

import json

import pytest
from helpers import fetchsync, tree_of
from test_laptop_disk_full import edit_all, env, fill, small_disk  # noqa: F401 (fixtures)


@pytest.mark.ssh
def test_edits_after_a_failed_state_commit_are_all_kept(env, small_disk, tmp_path, remote_dir):  # noqa: F811
    src = tmp_path / "ws/src"
    fetchsync("push", env=env)
    for n, leave in enumerate((48, 40, 32, 24, 16, 8)):
        fill(small_disk, leave_kb=leave)
        edit_all(src, 50, f"edit {n}")
        proc = fetchsync("push", env=env, check=False)
        (small_disk / "fill").unlink()
        if proc.returncode and "cannot open" not in proc.stderr.decode():
            break
    else:
        pytest.fail("no push failed at its commit: the test's disk sizes are off")
    robot = remote_dir / "src/pkg"
    assert (robot / "f1.txt").read_text() == f"file 1 edit {n}\n"  # the robot has it
    (robot / "f0.txt").write_text("robot edit\n")
    (src / "pkg/f1.txt").write_text("laptop again\n")
    (robot / "f2.txt").write_text("robot edit 2\n")
    (src / "pkg/f2.txt").write_text("laptop again 2\n")
    fetchsync("push", env=env)
    assert tree_of(src) == tree_of(remote_dir / "src")
    kept = {e["path"]: (remote_dir / e["kept"]).read_text() for e in _conflicts(env)}
    assert kept.get("pkg/f0.txt") == "robot edit\n"
    assert kept.get("pkg/f2.txt") == "robot edit 2\n"
    # the failed push's own version of f1, if kept as a conflict, restores safely
    if "pkg/f1.txt" in kept:
        fetchsync("conflicts", "restore", "pkg/f1.txt", env=env)
        trashed = list((tmp_path / "ws/.fetchsync/trash").glob("*/pkg/f1.txt"))
        assert [t.read_text() for t in trashed] == ["laptop again\n"]


def _conflicts(e: dict) -> list[dict]:
    return json.loads(fetchsync("conflicts", "--json", env=e).stdout)
