"""Back online, the agent sends what was pending before it checks everything (issue 24:
recovery <= 1 s; the save waits for no scan of the whole tree)."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from helpers import make_workspace, tree_of

from fetchsync.agent import service
from fetchsync.config import Target
from fetchsync.errors import TransportError
from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.sync import engine
from fetchsync.sync.state import State


def test_a_new_connection_pushes_touched_paths_without_a_listing(tmp_path: Path) -> None:
    """A Syncer on a new connection (the agent back online) opens the workspace and sends
    the touched paths; no listing, no full push, as long as the robot is where the state
    says."""
    make_workspace(tmp_path / "ws")
    src, robot = tmp_path / "ws" / "src", tmp_path / "robot-home" / "ws" / "src"
    state = State(tmp_path / "state.sqlite")

    def syncer() -> engine.Syncer:
        return engine.Syncer(
            Connection.open(LocalTransport(tmp_path / "robot-home")),
            state,
            local_root=str(src),
            remote_workspace="~/ws",
            rules=engine.build_rules(),
        )

    first = syncer()
    first.push()
    first.conn.close()
    again = syncer()
    asked: list[str] = []
    listing = again.endpoint.send_listing
    again.endpoint.send_listing = lambda **kw: asked.append("list") or listing(**kw)  # type: ignore[method-assign]
    (src / "my_pkg/src/node.cpp").write_text("int main() { return 7; }\n")
    report = again.push_paths({"my_pkg/src/node.cpp"})
    assert report.files == 1 and asked == []
    assert tree_of(src) == tree_of(robot)
    again.conn.close()
    state.close()


class _Recording:
    """A Syncer that records what the agent asks of it."""

    def __init__(self) -> None:
        self.calls: list[Any] = []
        self.done = threading.Event()

    def push(self) -> engine.Report:
        self.calls.append("push")
        self.done.set()
        return engine.Report("push")

    def push_paths(self, paths: set[str], dirs: set[str]) -> engine.Report:
        self.calls.append(("push_paths", set(paths), set(dirs)))
        return engine.Report("push")


def test_what_was_pending_goes_first_then_everything_is_checked(tmp_path: Path) -> None:
    target = Target(
        robot="robot",
        host="robot",
        user=None,
        workspace=tmp_path,
        remote_workspace="~/ws",
        is_local=False,
    )
    agent = service.Agent(target, rules=None)
    # a push of a save failed as the link went; the user saved another file meanwhile
    agent.request(paths={"a.cpp"})
    with agent.cond:
        work, agent.pending = agent.pending, service.Pending()
    agent._mark_offline(TransportError("the link was lost"), work)
    saved = agent.request(paths={"b.cpp"})
    recording = _Recording()
    agent._syncer = recording  # back online
    loop = threading.Thread(target=agent._sync_loop, daemon=True)
    loop.start()
    try:
        assert recording.done.wait(30)
        assert recording.calls == [("push_paths", {"a.cpp", "b.cpp"}, set()), "push"]
        assert agent.wait_for(saved, 5) == (True, "")
    finally:
        agent.stop()
        loop.join(5)
