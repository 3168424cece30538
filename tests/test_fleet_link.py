"""A fleet push opens each robot's connection while that robot's state opens (issue 27:
twenty new state databases, synced to the laptop's disk, held every connection back);
a robot whose state cannot be opened fails alone, and the connection opened for it is
closed."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import pytest
from helpers import tree_of
from test_fleet import fleet_env  # noqa: F401 - the fixture

from fetchsync.cli import cli
from fetchsync.errors import StateError
from fetchsync.link import connection as connection_mod
from fetchsync.sync import state as state_mod

pytestmark = pytest.mark.ssh


def test_a_robot_whose_state_fails_fails_alone_and_its_connection_is_closed(
    fleet_env,  # noqa: F811
    tmp_path,
    monkeypatch,
    clean_process_env,
    capfd,
):
    src = Path(fleet_env["FETCHSYNC_WORKSPACE"]) / "src"
    opened: dict[str, list[object]] = {}
    closed: list[object] = []
    state_began: dict[str, float] = {}
    link_began: dict[str, float] = {}
    lock = threading.Lock()
    real_open, real_close = connection_mod.Connection.open, connection_mod.Connection.close
    real_state = state_mod.open_state

    def conn_open(transport, **kw):
        name = transport.name
        with lock:
            link_began.setdefault(name, time.monotonic())
        conn = real_open(transport, **kw)
        with lock:
            opened.setdefault(name, []).append(conn)
        return conn

    def conn_close(self):
        with lock:
            closed.append(self)
        return real_close(self)

    def open_state(target):
        with lock:
            state_began[target.robot] = time.monotonic()
        if target.robot == "fetch2":
            time.sleep(0.5)  # a slow disk: the connection goes on meanwhile
            raise StateError("cannot open the state: a test's refusal")
        return real_state(target)

    monkeypatch.setattr(connection_mod.Connection, "open", staticmethod(conn_open))
    monkeypatch.setattr(connection_mod.Connection, "close", conn_close)
    monkeypatch.setattr(state_mod, "open_state", open_state)
    for key, value in fleet_env.items():
        monkeypatch.setenv(key, value)
    for key in [k for k in os.environ if k not in fleet_env]:
        monkeypatch.delenv(key)
    with pytest.raises(SystemExit) as exit_:
        cli.main(["push", "--robot", "fetch1,fetch2,fetch3", "-j", "3"], standalone_mode=False)
    assert exit_.value.code != 0
    err = capfd.readouterr().err
    assert "[fetch2] fetchsync: error: cannot open the state: a test's refusal" in err
    for name in ("fetch1", "fetch3"):
        assert tree_of(tmp_path / f"robot-{name}/src") == tree_of(src), name
    assert not (tmp_path / "robot-fetch2/src").exists()
    # fetch2's connection was opening while its state did, and is closed once open
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline and not (
        opened.get("fetch2") and all(c in closed for c in opened["fetch2"])
    ):
        time.sleep(0.05)
    assert opened.get("fetch2"), opened
    assert all(c in closed for c in opened["fetch2"])
    assert link_began["fetch2"] < state_began["fetch2"] + 0.5
