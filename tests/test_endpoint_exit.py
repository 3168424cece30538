"""The endpoint ends cleanly after a bye, whether or not its stdin is still open.

After the bye the endpoint's read-ahead thread is still blocked reading stdin (the
client closes its side a moment later, or, through a connection master, later
still); finalizing the interpreter under it aborted the process ("Fatal Python
error: _enter_buffered_busy", SIGABRT) on the robot: a first push, whose endpoint
runs from the zip while its tree is extracted, met it in 3 of 3 runs on the
bench's wifi link.
"""

from __future__ import annotations

import time

from endpoint_client import Endpoint

from fetchsync.protocol import wire


def test_a_bye_ends_the_endpoint_at_once_with_status_0_while_stdin_is_open(tmp_path):
    ep = Endpoint(str(tmp_path))
    try:
        assert ep.request({"op": "ping"}).type == wire.T_RESPONSE
        assert ep.proc.stdin is not None
        ep.proc.stdin.write(wire.encode_frame(wire.Frame(wire.T_REQUEST, 99, {"op": "bye"}, b"")))
        ep.proc.stdin.flush()
        deadline = time.monotonic() + 30
        while ep.proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        # it ended on its own, stdin still open: its read-ahead thread was blocked in it
        assert ep.proc.returncode == 0, ep.proc.returncode
        assert ep.proc.stderr is not None
        err = ep.proc.stderr.read()
        assert b"Fatal Python error" not in err, err
    finally:
        if ep.proc.poll() is None:
            ep.proc.kill()
        ep.proc.wait()
