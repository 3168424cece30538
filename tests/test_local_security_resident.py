"""Another user on the laptop and the resident's socket (fetchsync.agent.resident).

The resident makes pushes for whoever asks on its socket: only processes of its own
uid may (SO_PEERCRED), even when its directory and socket were opened up by mistake.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import pytest
from helpers import fetchsync
from test_local_security import intruder, needs_root, run_as  # noqa: F401
from test_resident import env, push_json, resident_up  # noqa: F401

from fetchsync.agent import quick

pytestmark = [pytest.mark.ssh, needs_root]

ASK = (
    "import socket, sys; s = socket.socket(socket.AF_UNIX); s.connect(sys.argv[1]); "
    "s.sendall(sys.argv[2].encode() + b'\\n'); s.settimeout(20); "
    "data = s.recv(1 << 16); print(len(data))"
)


def test_another_user_cannot_push_through_the_resident(intruder, env, remote_dir):  # noqa: F811
    resident_up(env)
    runtime = Path(env["XDG_RUNTIME_DIR"])
    sock = next((runtime / "fetchsync").glob("agent-*.sock"))
    ws = Path(env["FETCHSYNC_WORKSPACE"])
    (ws / "src/my_pkg/package.xml").write_text("not pushed by the other user\n")
    status = json.loads(fetchsync("status", "--json", env=env).stdout)
    assert status["state"] == "resident"
    request = json.dumps(
        {
            "cmd": "push",
            "client": quick.identity(),
            "target": {
                "robot": status["robot"],
                "host": status["robot"],
                "user": None,
                "workspace": str(ws),
                "remote_workspace": str(remote_dir),
                "is_local": False,
            },
        }
    )
    for path in (runtime, runtime / "fetchsync"):
        path.chmod(0o711)  # the mistake: others may reach the socket
    sock.chmod(0o666)
    try:
        for cmd in (request, json.dumps({"cmd": "status"}), json.dumps({"cmd": "quit"})):
            got = run_as(intruder, sys.executable, "-c", ASK, str(sock), cmd)
            assert got.stdout.strip() in (b"0", b""), got
        time.sleep(0.5)
        assert (remote_dir / "src/my_pkg/package.xml").read_text() != (
            "not pushed by the other user\n"
        )
    finally:
        for path in (runtime, runtime / "fetchsync"):
            path.chmod(0o700)
    # the resident is still ours, and serves us
    got = push_json(env)
    assert got["connection"] == "resident" and got["files"] == 1
