"""Keepalives from the robot's endpoint while it works on a request: legitimately long
silent work (a cold listing of a huge tree, hashing a large file, a long syncfs) must not
trip the client's progress deadline, and a client that did not ask gets none."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from endpoint_client import ALG, Endpoint
from helpers import fetchsync, local_env, make_workspace, tree_of

from fetchsync.protocol import wire


def test_a_request_slower_than_the_deadline_completes(tmp_path):
    """The robot lists for 5 s without a byte while the deadline is 2 s: its keepalives
    keep the push alive, and it completes."""
    make_workspace(tmp_path / "ws")
    env = local_env(tmp_path, FETCHSYNC_DEADLINE="2", FETCHSYNC_TEST_SLOW_LIST="5")
    proc = fetchsync("push", env=env, check=False)
    assert proc.returncode == 0, proc.stderr.decode()
    assert tree_of(tmp_path / "ws/src") == tree_of(tmp_path / "robot-home/robot_ws/src")


def _raw_endpoint(home: Path, **env: str) -> tuple[subprocess.Popen, wire.Reader, dict]:
    proc = subprocess.Popen(
        [sys.executable, "-c", "from fetchsync.protocol.server import main; main()"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=dict(os.environ, HOME=str(home), **env),
    )
    assert proc.stdout is not None
    reader = wire.Reader(proc.stdout.read1)  # type: ignore[attr-defined]
    return proc, reader, reader.read_hello()


def _send(proc: subprocess.Popen, data: bytes) -> None:
    assert proc.stdin is not None
    proc.stdin.write(data)
    proc.stdin.flush()


def test_a_client_that_asks_gets_progress_frames_for_the_request_then_its_answer(tmp_path):
    proc, reader, hello = _raw_endpoint(tmp_path, FETCHSYNC_TEST_SLOW_LIST="1.5")
    try:
        assert hello["progress"] > 0
        _send(proc, wire.encode_hello({"algorithm": ALG, "progress": 0.2}))
        _send(
            proc,
            wire.encode_frame(wire.Frame(wire.T_REQUEST, 1, {"op": "open", "workspace": "~/ws"})),
        )
        assert reader.read_frame().type == wire.T_RESPONSE  # type: ignore[union-attr]
        _send(proc, wire.encode_frame(wire.Frame(wire.T_REQUEST, 2, {"op": "list"})))
        frames = []
        while not frames or frames[-1].type == wire.T_PROGRESS:
            frame = reader.read_frame()
            assert frame is not None
            frames.append(frame)
        assert frames[-1].type == wire.T_RESPONSE and frames[-1].req_id == 2
        assert frames[:-1], "no progress frame during a 1.5 s listing"
        assert all(f.req_id == 2 and f.header == {} for f in frames[:-1])
    finally:
        proc.stdin.close()  # type: ignore[union-attr]
        proc.wait(30)


def test_an_older_client_that_did_not_ask_gets_no_progress_frames(tmp_path):
    """Its reader would refuse the unknown frame type: the answer alone comes."""
    with Endpoint(str(tmp_path), FETCHSYNC_TEST_SLOW_LIST="1.5") as ep:
        assert ep.request({"op": "open", "workspace": "~/ws"}).type == wire.T_RESPONSE
        frame = ep.request({"op": "list"})  # asserts the next frame is the answer
        assert frame.type == wire.T_RESPONSE and frame.header["full"] is True
        code, err = ep.close()
        assert code == 0, err
