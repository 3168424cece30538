"""A push's local changes go to the robot before its listing answers (Syncer._push_ahead).

The writes queue behind the robot's drift check instead of waiting a round trip
for it; each still checks its own path on the robot. These tests hold what must
not change with that: a robot-side edit (of a file the push writes, of another
file, a file made on the robot) is kept aside and the robot ends identical to
the laptop; another laptop's push in between makes the early writes stale and
nothing of them lands; and the writes really do leave before the listing's
answer is read.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from helpers import make_workspace, tree_of

from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State


def _syncer(tmp_path: Path, conn: Connection, name: str, src: Path) -> tuple[sync.Syncer, State]:
    state = State(tmp_path / f"{name}.sqlite")
    s = sync.Syncer(
        conn, state, local_root=str(src), remote_workspace="~/ws", rules=sync.build_rules()
    )
    return s, state


@pytest.fixture
def env(tmp_path: Path) -> Any:
    make_workspace(tmp_path / "ws")
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    s, state = _syncer(tmp_path, conn, "state", tmp_path / "ws" / "src")
    s.push()
    yield s, tmp_path / "ws" / "src", tmp_path / "robot-home" / "ws" / "src"
    conn.close()
    state.close()


def _fresh(s: sync.Syncer) -> sync.Syncer:
    """A new Syncer on the same connection and state, as a new push process makes."""
    return sync.Syncer(
        s.conn, s.state, local_root=s.local_root, remote_workspace="~/ws", rules=s.rules
    )


def test_robot_side_edits_met_by_an_early_write_are_kept_and_the_rest_pushed_over(env):
    s, src, robot = env
    (src / "my_pkg/src/node.cpp").write_text("edited on the laptop\n")
    (robot / "my_pkg/src/node.cpp").write_text("edited on the robot\n")
    (robot / "my_pkg/package.xml").write_text("also edited on the robot\n")
    (robot / "my_pkg/robot_only.txt").write_text("made on the robot\n")
    r = _fresh(s).push()
    assert r.errors == []
    assert {c["path"] for c in r.conflicts} == {
        "my_pkg/src/node.cpp",
        "my_pkg/package.xml",
        "my_pkg/robot_only.txt",
    }
    assert tree_of(src) == tree_of(robot)
    kept = {
        p.name: p.read_text()
        for p in (robot.parent / ".fetchsync/conflicts").rglob("*")
        if p.is_file()
    }
    assert kept == {
        "node.cpp": "edited on the robot\n",
        "package.xml": "also edited on the robot\n",
        "robot_only.txt": "made on the robot\n",
    }
    assert r.files >= 2  # the early write and the package.xml put back, in one report
    assert _fresh(s).push().changed == 0


def test_a_push_from_another_laptop_in_between_makes_the_early_writes_stale(env, tmp_path):
    s, src, robot = env
    other_src = tmp_path / "other" / "src"
    make_workspace(tmp_path / "other")
    (other_src / "my_pkg/other.txt").write_text("from the other laptop\n")
    other, other_state = _syncer(tmp_path, s.conn, "other", other_src)
    try:
        other.push()  # the robot's generation moves on: this laptop's state is behind
    finally:
        other_state.close()
    assert (robot / "my_pkg/other.txt").exists()
    (src / "my_pkg/src/node.cpp").write_text("edited on the laptop\n")
    r = _fresh(s).push()
    assert r.errors == []
    assert tree_of(src) == tree_of(robot)
    kept = [p for p in (robot.parent / ".fetchsync").rglob("other.txt") if p.is_file()]
    assert [p.read_text() for p in kept] == ["from the other laptop\n"]  # in the trash


def test_the_writes_leave_before_the_listing_is_read(env, monkeypatch):
    s, src, _robot = env
    (src / "my_pkg/src/node.cpp").write_text("edited on the laptop\n")
    events: list[str] = []
    listings: set[int] = set()
    send_sync = sync.Endpoint.send_sync
    send_listing = sync.Endpoint.send_listing
    wait = sync.Pending.wait

    def spy_sync(self: Any, *args: Any, **kw: Any) -> Any:
        events.append("sync sent")
        return send_sync(self, *args, **kw)

    def spy_listing(self: Any, *args: Any, **kw: Any) -> Any:
        pending = send_listing(self, *args, **kw)
        listings.add(pending.req_id)
        return pending

    def spy_wait(self: Any) -> Any:
        if self.req_id in listings:
            events.append("listing read")
        return wait(self)

    monkeypatch.setattr(sync.Endpoint, "send_sync", spy_sync)
    monkeypatch.setattr(sync.Endpoint, "send_listing", spy_listing)
    monkeypatch.setattr(sync.Pending, "wait", spy_wait)
    r = _fresh(s).push()
    assert r.files == 1 and r.errors == []
    assert events == ["sync sent", "listing read"]
