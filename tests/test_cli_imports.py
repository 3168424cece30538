"""A push through the connection master imports only what it uses (issue 24, start track).

Every module a one-shot push imports is paid at every push, before its first byte
moves: paramiko and the SSH code (only a direct connection needs them), subprocess
(only the local robot and starting a master), the watch agent's service (only the
agent), ctypes. The test runs a real push through a real master and looks at what
it imported beyond the interpreter's own start (site).
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from test_mux_spare import env, spare_ready  # noqa: F401

pytestmark = pytest.mark.ssh

WRAPPER = """
import atexit, json, sys
before = set(sys.modules)
atexit.register(lambda: print("MODULES " + json.dumps(sorted(set(sys.modules) - before))))
sys.argv = ["fetchsync", "push", "--json"]
import runpy
runpy.run_module("fetchsync", run_name="__main__")
"""

NOT_ON_THE_PUSH_PATH = {
    "paramiko",
    "fetchsync.link.ssh",
    "subprocess",
    "fetchsync.agent.service",
    "fetchsync.protocol.heap",
    "ctypes",
    "tempfile",
    # other verbs' work: loaded by their commands only (LAZY_COMMANDS)
    "fetchsync.chores.snapshot",
    "fetchsync.chores.lint",
    "fetchsync.chores.workspace_status",
    "fetchsync.chores.build",
    "fetchsync.cli.snapshot",
    "fetchsync.cli.watch",
}


@pytest.mark.slow
def test_a_push_through_the_master_imports_only_what_it_uses(env):  # noqa: F811
    spare_ready(env)
    proc = subprocess.run(
        [sys.executable, "-c", WRAPPER], env=env, capture_output=True, text=True, check=False
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    report = json.loads(next(ln for ln in lines if ln.startswith("{")))
    assert report["connection"] == "master" and report["ok"]
    imported = set(json.loads(next(ln for ln in lines if ln.startswith("MODULES "))[8:]))
    assert "fetchsync.sync.engine" in imported  # the push's own work was done here
    assert not NOT_ON_THE_PUSH_PATH & imported, sorted(NOT_ON_THE_PUSH_PATH & imported)
