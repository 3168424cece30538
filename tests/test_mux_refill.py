"""When the connection master starts its next spare endpoint (issue 24, start track).

A spare's start (a session through the link, sshd's fork, the robot's Python and the
loader) competes for both ends' CPU and the link with the call that took the spare, so
the master starts the next one once that call has ended (or REFILL_AFTER seconds into a
call that lives on), not as it hands the spare over.
"""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
from test_mux_spare import env, robot_endpoints, spare_ready, wait_for  # noqa: F401

from fetchsync.link import mux

pytestmark = pytest.mark.ssh

HOLD = """
import sys
from fetchsync.cli.common import resolve
from fetchsync.link.session import connect
with connect(resolve(None, None, None, None)) as conn:
    print(type(conn.transport).__name__, flush=True)
    sys.stdin.readline()
"""


@pytest.mark.slow
def test_the_next_spare_starts_when_the_call_that_took_one_ends(env):  # noqa: F811
    mark = env["FSMARK"]
    (spare,) = spare_ready(env)
    call = subprocess.Popen(
        [sys.executable, "-c", HOLD],
        env=env,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert call.stdout is not None and call.stdin is not None
        assert call.stdout.readline().strip() == "MuxTransport"
        # the call holds the spare; for a while no other endpoint starts beside it
        held = time.monotonic()
        while time.monotonic() - held < mux.REFILL_AFTER * 0.6:
            assert robot_endpoints(mark) == [spare]
            time.sleep(0.1)
        call.stdin.write("\n")
        call.stdin.flush()
        assert call.wait(30) == 0, call.stderr.read() if call.stderr else ""
    finally:
        if call.poll() is None:
            call.kill()
            call.wait()
    # once it has ended, the next spare is started
    assert wait_for(lambda: len(robot_endpoints(mark)) == 1 and robot_endpoints(mark) != [spare])
