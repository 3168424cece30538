"""A connection master stuck in its handshake (the robot's TCP accepts, its sshd never
speaks) holds no call for long, and never loses or repeats a push.

While a master connects, calls wait for it (tests/test_mux_starting.py); the master
stamps each step of its start on the lock that says so, and a call waits only while
those steps come (mux.MASTER_STALL). Before, every call waited MASTER_WAIT (5 s) for a
master whose connect hung, for as long as it hung (its banner timeout: 10 s), and then
went direct anyway.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import threading
from pathlib import Path

import pytest
from helpers import fetchsync, report, tree_of
from sshd import make_ssh_home
from test_mux_spare import env, masters, serving, wait_for  # noqa: F401
from test_mux_starting import connecting

from fetchsync.link import mux

pytestmark = pytest.mark.ssh


class Silent:
    """A TCP port that accepts connections and never says a byte."""

    def __init__(self) -> None:
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.port = self.srv.getsockname()[1]
        self.accepted: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.srv.accept()
            except OSError:
                return
            self.accepted.append(conn)

    def close(self) -> None:
        self.srv.close()
        for conn in self.accepted:
            conn.close()


def waited(trace: Path) -> float:
    """Seconds the traced call spent between asking the master and going on without it."""
    steps: dict[str, float] = {}
    for line in trace.read_text().splitlines():
        at, _, what = line.split(" ", 2)
        steps.setdefault(what, float(at))
    return steps["session: the master is not there"] - steps["session: asking the master"]


def one_call(call_env: dict[str, str], trace: Path) -> tuple[dict, float]:
    """A push traced into ``trace`` (emptied first): its report and its wait for the master."""
    trace.write_text("")
    proc = fetchsync("push", "--json", env=dict(call_env, FETCHSYNC_TRACE=str(trace)), check=False)
    assert proc.returncode == 0, proc.stderr.decode()
    return report(proc), waited(trace)


@pytest.mark.slow
def test_a_master_stuck_in_its_handshake_holds_no_call(env, sshd, remote_dir, tmp_path):  # noqa: F811
    runtime = Path(env["XDG_RUNTIME_DIR"])
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    trace = tmp_path / "trace"
    # a first push leaves a master behind: its command line is the one a call spawns
    assert report(fetchsync("push", "--json", env=env))["connection"] == "ssh"
    assert wait_for(lambda: serving(runtime))
    (good,) = masters(runtime)
    argv = Path(f"/proc/{good}/cmdline").read_bytes().split(b"\0")[:-1]
    os.kill(good, signal.SIGTERM)
    assert wait_for(lambda: not masters(runtime) and not serving(runtime))
    if b"--lock-fd" in argv:
        at = argv.index(b"--lock-fd")
        del argv[at : at + 2]
    # the same master, whose robot now accepts TCP and never speaks
    silent = Silent()
    try:
        home = make_ssh_home(tmp_path / "home-silent", sshd=sshd, port=silent.port)
        stuck = subprocess.Popen(
            argv,
            env=dict(env, HOME=str(home.home)),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            assert wait_for(lambda: silent.accepted and connecting(runtime))
            (local / "my_pkg" / "stalled.txt").write_text("lands once\n")
            first, wait1 = one_call(env, trace)
            assert first["ok"] and first["connection"] == "ssh"
            assert "no step" in trace.read_text()
            assert wait1 < mux.MASTER_WAIT, wait1  # was MASTER_WAIT: 5 s
            assert tree_of(local) == tree_of(remote_dir / "src")
            # the master is still stuck, and the call left no second master beside it
            assert stuck.poll() is None and connecting(runtime)
            assert masters(runtime) == [stuck.pid]
            # a call after it does not wait again: the master's last step is too old
            (local / "my_pkg" / "stalled.txt").write_text("lands once, then again\n")
            second, wait2 = one_call(env, trace)
            assert second["ok"] and second["connection"] == "ssh"
            assert wait2 < mux.MASTER_STALL, wait2
            print(f"waited for the stuck master: {wait1:.3f} s, then {wait2:.3f} s")
            assert tree_of(local) == tree_of(remote_dir / "src")
        finally:
            silent.close()  # the stuck master's connect fails: it exits
            try:
                stuck.wait(timeout=30)
            finally:
                if stuck.poll() is None:
                    stuck.kill()
    finally:
        silent.close()
    # the next call leaves a master that serves, and a push through it changes only what
    # changed since (nothing of the direct pushes is replayed)
    assert not connecting(runtime)
    assert report(fetchsync("push", "--json", env=env))["connection"] == "ssh"
    assert wait_for(lambda: serving(runtime))
    (local / "my_pkg" / "after.txt").write_text("through the master\n")
    r = report(fetchsync("push", "--json", env=env))
    assert r["ok"] and r["connection"] == "master"
    assert tree_of(local) == tree_of(remote_dir / "src")
