"""A caller of the connection master that has gone before the master answers it (its
deadline passed while the master waited for its spare to start, a Ctrl-C, a kill) leaves
no endpoint on the robot (redteam, session 23).

The master took the spare for it and wrote the spare's hello to the caller: the write
failed (the caller's socket closed) and the error path closed the caller's socket but
not the spare's channel, which nobody closed after: the endpoint waited for a hello on
the robot until the master ended, beside the next spare (the two single-threaded
endpoints test_faults.py's stalled-endpoint [master] case found under load)."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest
from helpers import fetchsync, report, tree_of
from test_mux_spare import env, robot_endpoints, spare_ready, wait_for  # noqa: F401

from fetchsync.link.connection import remote_python
from fetchsync.protocol.loader import loader_spec

pytestmark = pytest.mark.ssh


@pytest.mark.slow
def test_a_caller_gone_before_the_master_answers_leaves_no_endpoint(
    env,  # noqa: F811 - test_mux_spare's fixture
    remote_dir,
    monkeypatch,
):
    monkeypatch.setenv("FETCHSYNC_REMOTE_PYTHON", env["FETCHSYNC_REMOTE_PYTHON"])
    warm = loader_spec(remote_python())[0]  # the command the master keeps a spare of
    sock_path = None
    for _ in range(3):
        (spare,) = spare_ready(env)
        if sock_path is None:
            [sock_path] = (Path(env["XDG_RUNTIME_DIR"]) / "fetchsync").glob("mux-*.sock")
        caller = socket.socket(socket.AF_UNIX)
        caller.connect(str(sock_path))
        caller.sendall(b'{"exec": %s}\n' % _json(warm))
        caller.close()  # gone before the master has answered
        assert wait_for(lambda spare=spare: spare not in robot_endpoints(env["FSMARK"]), 20), (
            "the spare taken for a caller that had gone still runs"
        )
    time.sleep(0.5)
    assert len(robot_endpoints(env["FSMARK"])) <= 1  # the next spare only
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    (local / "my_pkg" / "after.txt").write_text("the master still serves\n")
    assert report(fetchsync("push", "--json", env=env))["connection"] == "master"
    assert tree_of(local) == tree_of(remote_dir / "src")


def _json(text: str) -> bytes:
    import json

    return json.dumps(text).encode()
