"""The mass-deletion guard and a directory renamed here (``mv src/pkg src/pkg2``): the
plan writes every file of the old directory again at the new path, so nothing of the
robot's is lost, and the push must not need --force (the watch agent paused on it).
What is not written again elsewhere still counts: an emptied tree, or a renamed
directory whose files all changed, is refused as before."""

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

N = 40


@pytest.fixture
def env(tmp_path: Path) -> Any:
    make_workspace(tmp_path / "ws")
    src = tmp_path / "ws" / "src"
    (src / "pkg/sub").mkdir(parents=True)
    for i in range(N):
        (src / f"pkg/sub/f{i}.txt").write_text(f"{i}\n" * 50)
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    state = State(tmp_path / "state.sqlite")
    s = sync.Syncer(
        conn, state, local_root=str(src), remote_workspace="~/ws", rules=sync.build_rules()
    )
    s.push()
    yield s, src, tmp_path / "robot-home" / "ws" / "src"
    conn.close()
    state.close()


def _fresh(s: sync.Syncer) -> sync.Syncer:
    return sync.Syncer(
        s.conn, s.state, local_root=s.local_root, remote_workspace="~/ws", rules=s.rules
    )


def test_a_renamed_directory_is_pushed_without_force(env):
    s, src, robot = env
    (src / "pkg").rename(src / "pkg2")
    r = _fresh(s).push()
    assert r.errors == []
    assert tree_of(src) == tree_of(robot)


def test_a_renamed_directory_seen_by_the_watch_agent_is_pushed_without_force(env):
    s, src, robot = env
    (src / "pkg").rename(src / "pkg2")
    files = [f"pkg2/sub/f{i}.txt" for i in range(N)] + [f"pkg/sub/f{i}.txt" for i in range(N)]
    r = _fresh(s).push_paths(files, dirs=["pkg", "pkg2"])
    assert r.errors == []
    assert tree_of(src) == tree_of(robot)


def test_an_emptied_directory_with_other_files_written_is_still_refused(env):
    s, src, robot = env
    before = tree_of(robot)
    shutil.rmtree(src / "pkg")
    (src / "other").mkdir()
    for i in range(N):
        (src / f"other/g{i}.txt").write_text(f"not the same {i}\n")
    with pytest.raises(MassDeletionError):
        _fresh(s).push()
    assert tree_of(robot) == before


def test_a_renamed_directory_whose_files_changed_is_still_refused(env):
    s, src, robot = env
    before = tree_of(robot)
    (src / "pkg").rename(src / "pkg2")
    for p in (src / "pkg2/sub").iterdir():
        p.write_text(p.read_text() + "changed\n")
    with pytest.raises(MassDeletionError):
        _fresh(s).push()
    assert tree_of(robot) == before


def test_one_copy_covers_one_deleted_file_only(env):
    """40 deleted files of one content, written again once: 39 still count."""
    s, src, robot = env
    for p in (src / "pkg/sub").iterdir():
        p.write_text("same\n")
    _fresh(s).push()
    before = tree_of(robot)
    shutil.rmtree(src / "pkg")
    (src / "keep.txt").write_text("same\n")
    with pytest.raises(MassDeletionError):
        _fresh(s).push()
    assert tree_of(robot) == before
