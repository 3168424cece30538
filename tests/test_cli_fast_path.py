"""The console entry's fast path for a plain push (fetchsync.agent.quick.fast_main).

``fetchsync push`` (with at most ``--robot``, ``--workspace``, ``--json``) is offered to
a running resident before click and the engine are imported; the answer is printed
as the CLI prints a push's. These tests hold that it imports neither, that it prints
exactly what the click path prints (success, a conflict, an unreachable robot: the
same lines and exit code), and that anything else goes to the click path unchanged.
"""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import fetchsync
from test_resident import env, push_json, resident_up  # noqa: F401

from fetchsync.agent.quick import plain_push

pytestmark = pytest.mark.ssh

WRAPPER = """
import atexit, json, os, sys
before = set(sys.modules)
def said():
    print("MODULES " + json.dumps(sorted(set(sys.modules) - before)), flush=True)
_exit = os._exit
def exiting(code):
    said()
    _exit(code)
os._exit = exiting
sys.argv = ["fetchsync", "push", "--json"]
import runpy
runpy.run_module("fetchsync", run_name="__main__")
"""

# the click path, as a push made without the fast path (fetchsync.cli's group itself)
CLICK = """
import sys
sys.argv = ["fetchsync", *sys.argv[1:]]
from fetchsync.cli import cli, _exit
try:
    cli(prog_name="fetchsync")
    code = 0
except SystemExit as exc:
    code = exc.code or 0
_exit(int(code))
"""


def test_plain_push_is_only_what_it_can_make_exactly(monkeypatch):
    monkeypatch.delenv("FETCHSYNC_ROBOT", raising=False)
    monkeypatch.delenv("FETCH_ROBOT", raising=False)
    assert plain_push(["push"]) == {"robot": None, "workspace": None, "as_json": False}
    assert plain_push(["push", "--robot", "r", "--workspace=/w", "--json"]) == {
        "robot": "r",
        "workspace": "/w",
        "as_json": True,
    }
    for argv in (
        [],
        ["pull"],
        ["push", "-n"],
        ["push", "--force"],
        ["push", "--build"],
        ["push", "-v"],
        ["push", "--robot", "a,b"],
        ["push", "--robot", "@lab"],
        ["push", "--robot", "a", "--robot", "b"],
        ["push", "--robot"],
        ["push", "--json", "--json"],
        ["push", "--user", "u"],
        ["push", "--", "x"],
    ):
        assert plain_push(argv) is None, argv
    monkeypatch.setenv("FETCH_ROBOT", "a,b")
    assert plain_push(["push"]) is None


def test_the_fast_path_imports_neither_click_nor_the_engine(env):  # noqa: F811
    resident_up(env)
    proc = subprocess.run(
        [sys.executable, "-c", WRAPPER], env=env, capture_output=True, text=True, check=False
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    got = json.loads(next(ln for ln in lines if ln.startswith("{")))
    assert got["connection"] == "resident" and got["ok"]
    imported = set(json.loads(next(ln for ln in lines if ln.startswith("MODULES "))[8:]))
    heavy = {"click", "fetchsync.cli", "fetchsync.sync.engine", "fetchsync.sync.state", "paramiko"}
    assert not heavy & imported, sorted(heavy & imported)
    # nor what only the normal way needs (issue 24: ~25 ms of the asking process's CPU):
    # dataclasses (inspect, ast, dis), logging, socket.py, hashlib (OpenSSL), the link's
    # modules, the ssh config's note (the resident names the login)
    light = {"dataclasses", "inspect", "logging", "socket", "hashlib", "getpass"}
    light.add("fetchsync.protocol.loader")
    assert not light & imported, sorted(light & imported)
    assert not [m for m in imported if m.startswith("fetchsync.link")], sorted(imported)


def normalized(text: str) -> str:
    text = re.sub(r"\d+\.\d\ds$", "N.NNs", text, flags=re.M)
    text = re.sub(r"(sent|received) [\d.]+ (B|KiB|MiB)", r"\1 X", text)
    return re.sub(r"conflicts/[^ \n]*", "conflicts/KEPT", text)


def one_way(environ: dict[str, str], click: bool, *args: str) -> tuple[int, str, str]:
    """A push the fast way or the click way: (exit code, stdout, stderr) normalized."""
    if click:
        cmd = [sys.executable, "-c", CLICK, "push", *args]
        p = subprocess.run(cmd, env=environ, capture_output=True, check=False)
    else:
        p = fetchsync("push", *args, env=environ, check=False)
    return p.returncode, normalized(p.stdout.decode()), normalized(p.stderr.decode())


def both_ways(environ: dict[str, str], *args: str) -> list[tuple[int, str, str]]:
    return [one_way(environ, click, *args) for click in (False, True)]


def test_the_fast_path_says_what_the_click_path_says(env, remote_dir):  # noqa: F811
    resident_up(env)
    ws = Path(env["FETCHSYNC_WORKSPACE"])
    trace = Path(env["FETCHSYNC_TRACE"])
    node = ws / "src/my_pkg/src/node.cpp"
    xml = ws / "src/my_pkg/package.xml"
    edits, conflicts = [], []
    for click in (False, True):
        # the same situation each way: from the same synced content, the same edit
        node.write_text("base\n")
        xml.write_text("base\n")
        assert push_json(env)["connection"] == "resident"
        node.write_text("an edit\n")
        trace.write_text("")
        edits.append(one_way(env, click))
        marks = trace.read_text()
        assert "resident: pushed" in marks  # through the resident both ways
        assert ("push: start" in marks) == click  # the click command ran, or not
        # a conflict: the robot's edit kept aside, said on stderr, exit 0
        (remote_dir / "src/my_pkg/package.xml").write_text("the robot's\n")
        xml.write_text("the laptop's\n")
        conflicts.append(one_way(env, click))
    assert edits[0] == edits[1] and edits[0][0] == 0, edits
    assert "pushed 1 files" in edits[0][1]
    assert conflicts[0] == conflicts[1] and conflicts[0][0] == 0, conflicts
    assert "1 conflicts" in conflicts[0][1] and "conflict: my_pkg/package.xml" in conflicts[0][2]


def test_an_unreachable_robot_is_said_the_same_way(env, ssh_home):  # noqa: F811
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    config = ssh_home.config.read_text()
    block = config[config.index("Host robot") :]
    ssh_home.config.write_text(
        config
        + "\n"
        + block.replace("Host robot", "Host down", 1).replace(
            f"Port {ssh_home.sshd.port}", f"Port {port}"
        )
    )
    fast, slow = both_ways(dict(env, FETCHSYNC_ROBOT="down"))
    assert fast == slow and fast[0] == 3, (fast, slow)
