"""Two laptops on one robot, the second's push landing between the first's open and its
early writes (engine's Syncer._push_ahead, b285760): the first's batch 0 is refused as
stale, a later batch may apply (its generation is the robot's now). Whatever applied,
the first push must end with the robot identical to its laptop, the other laptop's edit
kept aside, and the first laptop's state true to the robot (its next push sees the
robot as it is)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

from helpers import make_workspace, tree_of

from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State


def _syncer(conn: Connection, state: State, src: Path) -> sync.Syncer:
    return sync.Syncer(
        conn, state, local_root=str(src), remote_workspace="~/ws", rules=sync.build_rules()
    )


def _kept(ws: Path) -> dict[str, str]:
    return {
        p.name: p.read_text()
        for p in (ws / ".fetchsync" / "conflicts").rglob("*")
        if p.is_file() and p.suffix == ".txt"
    }


def test_another_laptops_push_between_open_and_the_early_writes(tmp_path: Path):
    a_src = tmp_path / "a" / "src"
    make_workspace(tmp_path / "a")
    (a_src / "big").mkdir()
    for i in range(3):  # the first batch holds 1 MiB: these go in several
        (a_src / f"big/b{i}.bin").write_bytes(os.urandom(700_000))
    (a_src / "z.txt").write_text("first\n")
    b_src = tmp_path / "b" / "src"
    shutil.copytree(a_src, b_src, symlinks=True)
    home = tmp_path / "robot-home"
    robot = home / "ws"
    a_conn = Connection.open(LocalTransport(home))
    b_conn = Connection.open(LocalTransport(home))
    a_state, b_state = State(tmp_path / "a.sqlite"), State(tmp_path / "b.sqlite")
    try:
        _syncer(a_conn, a_state, a_src).push()
        _syncer(b_conn, b_state, b_src).push()  # identical: B adopts the robot's tree
        _syncer(a_conn, a_state, a_src).push()  # A at the robot's generation again
        for i in range(3):
            (a_src / f"big/b{i}.bin").write_bytes(os.urandom(700_000))
        (b_src / "z.txt").write_text("edited on laptop B\n")

        a = _syncer(a_conn, a_state, a_src)
        real = a._push_touched
        seen: list[Any] = []

        def b_first(*args: Any, **kwargs: Any) -> Any:
            if not seen:  # A's open has answered; B's push lands before A's writes
                seen.append(_syncer(b_conn, b_state, b_src).push())
            return real(*args, **kwargs)

        a._push_touched = b_first  # type: ignore[method-assign]
        r = a.push()
        assert seen, "the push did not send ahead"
        assert r.errors == []
        assert tree_of(robot / "src") == tree_of(a_src)
        assert _kept(robot).get("z.txt") == "edited on laptop B\n"
        # A's state is true to the robot: a second push has nothing to do
        again = _syncer(a_conn, a_state, a_src).push()
        assert again.errors == [] and (again.files, again.deleted, again.conflicts) == (0, 0, [])
        assert tree_of(robot / "src") == tree_of(a_src)
    finally:
        a_conn.close()
        b_conn.close()
        a_state.close()
        b_state.close()


def test_deletions_refused_as_stale_are_not_counted_twice(tmp_path: Path):
    """18 of 40 files deleted here (allowed: at most MASS_MIN), the early push refused as
    stale by the other laptop's push: the push over it plans the same 18 again; counted
    once, not as 36 (a refusal naming "18 deleted by the pushes just before" that were
    not deleted)."""
    a_src = tmp_path / "a" / "src"
    make_workspace(tmp_path / "a")
    (a_src / "many").mkdir()
    for i in range(40):
        (a_src / f"many/f{i}.txt").write_text(f"{i}\n")
    b_src = tmp_path / "b" / "src"
    shutil.copytree(a_src, b_src, symlinks=True)
    home = tmp_path / "robot-home"
    a_conn = Connection.open(LocalTransport(home))
    b_conn = Connection.open(LocalTransport(home))
    a_state, b_state = State(tmp_path / "a.sqlite"), State(tmp_path / "b.sqlite")
    try:
        _syncer(a_conn, a_state, a_src).push()
        _syncer(b_conn, b_state, b_src).push()
        _syncer(a_conn, a_state, a_src).push()
        for i in range(18):
            (a_src / f"many/f{i}.txt").unlink()
        (b_src / "my_pkg/package.xml").write_text("<edited on laptop B/>\n")
        a = _syncer(a_conn, a_state, a_src)
        real = a._push_touched
        seen: list[Any] = []

        def b_first(*args: Any, **kwargs: Any) -> Any:
            if not seen:
                seen.append(_syncer(b_conn, b_state, b_src).push())
            return real(*args, **kwargs)

        a._push_touched = b_first  # type: ignore[method-assign]
        r = a.push()
        assert seen, "the push did not send ahead"
        assert r.errors == []
        assert tree_of(home / "ws" / "src") == tree_of(a_src)
        assert a.deletions.files == 18
    finally:
        a_conn.close()
        b_conn.close()
        a_state.close()
        b_state.close()
