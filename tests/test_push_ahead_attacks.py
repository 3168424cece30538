"""Attacks on the push that sends its local changes before the robot's listing answers
(engine's Syncer._push_ahead) and on any push: what the robot holds that the state does
not know of must survive a push that was planned from the state alone.

- a directory deleted here while, on the robot, a file in it was edited or made: the
  edit and the new file are kept (in the robot's conflicts), not deleted with it;
- a file made here at a path where the robot made its own: the robot's is kept;
- most of the tree deleted here: the mass-deletion guard refuses before anything goes.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import pytest
from helpers import make_workspace, tree_of

from fetchsync.errors import MassDeletionError
from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State


@pytest.fixture
def env(tmp_path: Path) -> Any:
    make_workspace(tmp_path / "ws")
    src = tmp_path / "ws" / "src"
    (src / "pkg").mkdir()
    for i in range(5):
        (src / f"pkg/f{i}.txt").write_text(f"{i}\n")
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    state = State(tmp_path / "state.sqlite")
    s = sync.Syncer(
        conn, state, local_root=str(src), remote_workspace="~/ws", rules=sync.build_rules()
    )
    s.push()
    yield s, src, tmp_path / "robot-home" / "ws"
    conn.close()
    state.close()


def _fresh(s: sync.Syncer) -> sync.Syncer:
    """A new Syncer on the same connection and state, as a new push process makes."""
    return sync.Syncer(
        s.conn, s.state, local_root=s.local_root, remote_workspace="~/ws", rules=s.rules
    )


def _kept(ws: Path) -> dict[str, str]:
    """What the robot keeps aside: file name -> content."""
    return {
        p.name: p.read_text() for p in (ws / ".fetchsync" / "conflicts").rglob("*") if p.is_file()
    }


def test_a_robot_edit_in_a_directory_deleted_here_is_kept(env):
    s, src, ws = env
    (ws / "src/pkg/f1.txt").write_text("edited on the robot\n")
    shutil.rmtree(src / "pkg")
    (src / "my_pkg/package.xml").write_text("<changed/>\n")
    _fresh(s).push()
    # in the conflicts, not the trash (bounded: emptied as later deletions come)
    assert _kept(ws).get("f1.txt") == "edited on the robot\n"


def test_a_file_made_on_the_robot_in_a_directory_deleted_here_is_kept(env):
    s, src, ws = env
    (ws / "src/pkg/robot_made.txt").write_text("made on the robot\n")
    shutil.rmtree(src / "pkg")
    (src / "my_pkg/package.xml").write_text("<changed/>\n")
    _fresh(s).push()
    assert _kept(ws).get("robot_made.txt") == "made on the robot\n"


def test_a_new_file_here_where_the_robot_made_its_own_keeps_the_robots(env):
    s, src, ws = env
    (ws / "src/my_pkg/both.txt").write_text("made on the robot\n")
    (src / "my_pkg/both.txt").write_text("made on the laptop\n")
    r = _fresh(s).push()
    assert r.errors == []
    assert (ws / "src/my_pkg/both.txt").read_text() == "made on the laptop\n"
    assert _kept(ws).get("both.txt") == "made on the robot\n"
    assert tree_of(src) == tree_of(ws / "src")


def test_most_of_the_tree_deleted_here_is_refused_before_anything_goes(env):
    s, src, ws = env
    for i in range(40):
        (src / f"pkg/g{i}.txt").write_text(f"g{i}\n")
    _fresh(s).push()
    before = tree_of(ws / "src")
    shutil.rmtree(src / "pkg")
    (src / "my_pkg/package.xml").write_text("<changed/>\n")
    with pytest.raises(MassDeletionError):
        _fresh(s).push()
    assert tree_of(ws / "src") == before  # not even the edit went ahead
    _fresh(s).push(confirm_deletions=True)
    assert tree_of(src) == tree_of(ws / "src")


def test_a_robot_whose_workspace_was_made_anew_keeps_its_edits(env):
    """The robot's workspace made again (its .fetchsync gone: a reinstalled robot, or
    another robot now at that address) with its own versions of the files: a push planned
    from this laptop's state must not take them for what it synced."""
    s, src, ws = env
    shutil.rmtree(ws / ".fetchsync")
    (ws / "src/pkg/f2.txt").write_text("this robot's own\n")
    (src / "pkg/f2.txt").write_text("edited on the laptop\n")
    (src / "pkg/f3.txt").unlink()
    (ws / "src/pkg/f3.txt").write_text("this robot's f3\n")
    r = _fresh(s).push()
    assert r.errors == []
    assert (ws / "src/pkg/f2.txt").read_text() == "edited on the laptop\n"
    kept = _kept(ws)
    assert kept.get("f2.txt") == "this robot's own\n"
    assert kept.get("f3.txt") == "this robot's f3\n"
    assert tree_of(src) == tree_of(ws / "src")
