"""The push right after the one that left a connection master behind (issue 24).

The master is started as a first (direct) push ends, and takes a while to connect
(its Python, paramiko, the SSH handshake). A push that comes meanwhile waits for it
(a lock beside the socket says a master is connecting) instead of making a handshake
of its own and leaving a second master behind.
"""

from __future__ import annotations

import fcntl
import os
import subprocess
import time
from pathlib import Path

import pytest
from helpers import fetchsync, report
from test_mux_spare import env, masters, mux_log, serving, wait_for  # noqa: F401

pytestmark = pytest.mark.ssh


def connecting(runtime: Path) -> bool:
    """Whether a master holds the lock that says it is connecting."""
    for lock in (runtime / "fetchsync").glob("mux-*.sock.starting"):
        fd = os.open(lock, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        finally:
            os.close(fd)
    return False


@pytest.mark.slow
def test_a_push_while_the_master_connects_waits_for_it(env):  # noqa: F811
    runtime = Path(env["XDG_RUNTIME_DIR"])
    env = dict(env, FETCHSYNC_TEST_MASTER_SLOW="2")  # the master inherits it
    assert report(fetchsync("push", "--json", env=env))["connection"] == "ssh"
    assert not serving(runtime)  # still connecting: 2 s more
    assert connecting(runtime)  # said from the spawn on, before the master's Python runs
    second = report(fetchsync("push", "--json", env=env))
    assert second["connection"] == "master" and second["ok"]
    time.sleep(1)
    assert len(masters(runtime)) == 1, mux_log(env)


@pytest.mark.slow
def test_a_second_master_leaves_it_to_the_one_connecting(env):  # noqa: F811
    runtime = Path(env["XDG_RUNTIME_DIR"])
    slow = dict(env, FETCHSYNC_TEST_MASTER_SLOW="3")
    assert report(fetchsync("push", "--json", env=slow))["connection"] == "ssh"
    assert wait_for(lambda: connecting(runtime))
    (first,) = masters(runtime)
    argv = Path(f"/proc/{first}/cmdline").read_bytes().split(b"\0")[:-1]
    if b"--lock-fd" in argv:  # the lock its caller took and handed over: not ours
        at = argv.index(b"--lock-fd")
        del argv[at : at + 2]
    again = subprocess.run(argv, env=env, capture_output=True, timeout=30, check=False)
    assert again.returncode == 0
    assert b"another connection master" in again.stderr and b"is starting" in again.stderr
    assert masters(runtime) == [first]
    assert wait_for(lambda: serving(runtime))
