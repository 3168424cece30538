"""Incremental pushes of touched paths (the watch agent's fast path), over the local robot."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import make_workspace, tree_of

from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State


@pytest.fixture
def env(tmp_path: Path):
    make_workspace(tmp_path / "ws")
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    state = State(tmp_path / "state.sqlite")
    s = sync.Syncer(
        conn,
        state,
        local_root=str(tmp_path / "ws" / "src"),
        remote_workspace="~/ws",
        rules=sync.build_rules(),
    )
    s.push()
    yield s, tmp_path / "ws" / "src", tmp_path / "robot-home" / "ws" / "src"
    conn.close()
    state.close()


def test_touched_files_are_created_changed_and_deleted(env):
    s, src, robot = env
    (src / "my_pkg/new.txt").write_text("new\n")
    (src / "my_pkg/src/node.cpp").write_text("int main() { return 2; }\n")
    (src / "my_pkg/CMakeLists.txt").unlink()
    r = s.push_paths({"my_pkg/new.txt", "my_pkg/src/node.cpp", "my_pkg/CMakeLists.txt"})
    assert r.errors == [] and (r.files, r.deleted) == (2, 1)
    assert tree_of(src) == tree_of(robot)


def test_only_the_touched_paths_are_looked_at(env):
    s, src, robot = env
    (src / "my_pkg/untouched.txt").write_text("not reported by the watcher\n")
    (src / "my_pkg/new.txt").write_text("new\n")
    s.push_paths({"my_pkg/new.txt"})
    assert (robot / "my_pkg/new.txt").exists() and not (robot / "my_pkg/untouched.txt").exists()
    # and the state still knows every other path: a full push only adds the one left out
    r = s.push()
    assert (r.files, r.deleted) == (1, 0)


def test_a_new_directory_tree_and_a_deleted_one(env):
    s, src, robot = env
    (src / "pkg2/sub").mkdir(parents=True)
    (src / "pkg2/sub/a.txt").write_text("a")
    s.push_paths(set(), {"pkg2"})
    assert tree_of(src) == tree_of(robot)
    for p in sorted((src / "my_pkg").rglob("*"), reverse=True):
        p.unlink() if p.is_file() or p.is_symlink() else p.rmdir()
    (src / "my_pkg").rmdir()
    r = s.push_paths(set(), {"my_pkg"})
    assert r.deleted == 1 and tree_of(src) == tree_of(robot)
    assert s.push().changed == 0  # the state agrees with the robot


def test_a_rename_reuses_content(env):
    s, src, robot = env
    (src / "my_pkg/data.txt").rename(src / "my_pkg/moved.txt")
    r = s.push_paths({"my_pkg/data.txt", "my_pkg/moved.txt"})
    assert (r.reused, r.deleted) == (1, 1) and r.bytes_sent < 4096
    assert tree_of(src) == tree_of(robot)


def test_an_edit_of_a_big_file_goes_by_delta(env):
    s, src, robot = env
    f = src / "my_pkg/data.txt"
    f.write_text("// first\n" + f.read_text())
    r = s.push_paths({"my_pkg/data.txt"})
    assert r.deltas == 1 and r.bytes_sent < 4096
    assert f.read_bytes() == (robot / "my_pkg/data.txt").read_bytes()


def test_ignored_paths_are_not_pushed(env):
    s, src, robot = env
    (src / "my_pkg/.node.cpp.swp").write_text("swap")
    s.push_paths({"my_pkg/.node.cpp.swp"})
    assert not (robot / "my_pkg/.node.cpp.swp").exists()


def test_a_robot_side_edit_of_a_touched_file_is_kept(env):
    s, src, robot = env
    (robot / "my_pkg/src/node.cpp").write_text("edited on the robot\n")
    (src / "my_pkg/src/node.cpp").write_text("edited on the laptop\n")
    r = s.push_paths({"my_pkg/src/node.cpp"})
    assert [c["path"] for c in r.conflicts] == ["my_pkg/src/node.cpp"]
    assert (robot / "my_pkg/src/node.cpp").read_text() == "edited on the laptop\n"


def test_another_writer_makes_it_fall_back_to_a_full_push(env, tmp_path):
    s, src, robot = env
    other = Connection.open(LocalTransport(tmp_path / "robot-home"))
    ostate = State(tmp_path / "other.sqlite")
    osrc = tmp_path / "other/src"
    osrc.mkdir(parents=True)
    (osrc / "theirs.txt").write_text("theirs")
    sync.Syncer(
        other, ostate, local_root=str(osrc), remote_workspace="~/ws", rules=sync.build_rules()
    ).push()
    other.close()
    ostate.close()
    (src / "my_pkg/new.txt").write_text("new\n")
    r = s.push_paths({"my_pkg/new.txt"})
    assert r.errors == []
    assert tree_of(src) == tree_of(robot)  # the full push also undid the other writer's tree


def test_a_burst_of_new_files_is_read_once_each(env, monkeypatch):
    """The watch agent's burst (new files, in a new directory or beside others): each is
    opened once, to be sent and hashed as it is read; an edited file is read to see if
    its content changed, then to be sent."""
    s, src, robot = env
    (src / "burst").mkdir()
    for i in range(40):
        (src / "burst" / f"f{i}.txt").write_text(f"new file {i}\n" * (i + 1))
    (src / "my_pkg/new.txt").write_text("beside the others\n")
    (src / "my_pkg/src/node.cpp").write_text("int main() { return 3; }\n")
    opened: list[str] = []
    monkeypatch.setattr(
        sync, "read_hook", lambda full, event: opened.append(full) if event == "open" else None
    )
    r = s.push_paths({"my_pkg/new.txt", "my_pkg/src/node.cpp"}, {"burst"})
    assert r.errors == [] and r.files == 42
    assert tree_of(src) == tree_of(robot)
    new = [p for p in opened if "/burst/" in p or p.endswith("new.txt")]
    assert len(new) == len(set(new)) == 41
    assert sum(p.endswith("node.cpp") for p in opened) == 2
