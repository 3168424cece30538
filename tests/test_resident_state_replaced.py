"""The resident answers from the laptop's state as it is on disk, also once it was replaced.

The attack (redteam, session 22): the resident holds the state's SQLite database open
between pushes. The user removes the state directory (or another fetchsync install
writes its own) and a push made without the resident records a newer state; the
robot's file is then edited on the robot back to what the resident's old state says
was synced. A resident answering from its old view sees the robot "unchanged" and
overwrites that robot-side edit with no conflict; a fresh process (the state on disk:
the other push's version) keeps it in the robot's conflicts. The resident reopens the
state when the file on disk is not the one it holds (resident.py _open_state).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from helpers import fetchsync, report, tree_of
from test_resident import resident_env, resident_up

pytestmark = pytest.mark.ssh


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    yield from resident_env(ssh_home.home, remote_dir, tmp_path)


@pytest.mark.parametrize("how", ["removed", "replaced"])
def test_a_resident_whose_state_was_replaced_keeps_a_robot_side_edit(
    how, env, remote_dir, tmp_path
):
    ws = Path(env["FETCHSYNC_WORKSPACE"])
    f = ws / "src/my_pkg/package.xml"
    robot_f = remote_dir / "src/my_pkg/package.xml"
    f.write_text("version R\n")
    resident_up(env)  # the resident's state: version R synced
    got = report(fetchsync("push", "--json", env=env))
    assert got["connection"] == "resident"
    state_dir = Path(env["XDG_STATE_HOME"]) / "fetchsync"
    [db] = state_dir.glob("*.sqlite")
    if how == "removed":
        shutil.rmtree(state_dir)  # the user's rm; the next push makes a new one
    else:  # another install's copy, renamed over it
        aside = tmp_path / "other.sqlite"
        shutil.copy(db, aside)
        aside.replace(db)
    # a push made without the resident: version B, recorded in the state on disk
    f.write_text("version B\n")
    fetchsync("push", env=dict(env, FETCHSYNC_RESIDENT="0"))
    assert robot_f.read_text() == "version B\n"
    # a robot-side edit: back to what the resident's old view says was synced
    robot_f.write_text("version R\n")
    got = report(fetchsync("push", "--json", env=env))
    assert got["connection"] == "resident"
    assert robot_f.read_text() == "version B\n"
    kept = [remote_dir / c["kept"] for c in got["conflicts"]]
    assert [k.read_text() for k in kept] == ["version R\n"], got
    assert tree_of(ws / "src") == tree_of(remote_dir / "src")
