"""The resident a push leaves behind holds nothing of its caller's but what it needs.

A push run by a harness that hands it an extra pipe (a CI runner's, ``make -j``'s
jobserver, a script's ``exec 3>``), or under ``ssh laptop fetchsync push``: the caller
waits for the end of every pipe it gave out. A resident that kept such a descriptor
(posix_spawn closes none) held its caller for the resident's whole life (10 minutes by
default), as a daemon that keeps its terminal would.
"""

from __future__ import annotations

import os
import select
import subprocess
import sys
import time

import pytest
from helpers import report
from test_mux_spare import wait_for
from test_resident import env, residents  # noqa: F401 - the fixture

pytestmark = pytest.mark.ssh


def push_holding(environ: dict[str, str]) -> tuple[dict, int]:
    """A plain push given the write end of a pipe as its fd 3 (closed here); the report
    and the read end."""
    r, w = os.pipe()
    proc = subprocess.run(
        [sys.executable, "-m", "fetchsync", "push", "--json"],
        env=environ,
        capture_output=True,
        pass_fds=(w,),
        timeout=120,
    )
    os.close(w)
    assert proc.returncode == 0, proc.stderr
    return report(proc), r


def closed_within(fd: int, seconds: float) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if select.select([fd], [], [], max(0.0, end - time.monotonic()))[0]:
            if os.read(fd, 1 << 16) == b"":
                return True
    return False


def test_the_resident_keeps_no_descriptor_of_its_caller(env):  # noqa: F811
    from pathlib import Path

    runtime = Path(env["XDG_RUNTIME_DIR"])
    _first, r = push_holding(env)  # it leaves the master and the resident
    try:
        assert wait_for(lambda: bool(residents(runtime)))
        assert closed_within(r, 10), "the resident holds its caller's pipe"
    finally:
        os.close(r)
