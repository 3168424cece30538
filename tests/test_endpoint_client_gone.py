"""An endpoint whose client has gone applies no further write request.

The attack (redteam, session 22): the robot's endpoint reads requests ahead of the one
it serves (up to four batches). A push killed while its endpoint sat between two
requests (stopped, or slow) left the next batch queued there; once the endpoint went
on it applied that batch, although nobody was there to answer any more (sshd had
closed the endpoint's output), and after any push made meanwhile that wrote nothing
(the user reverted the edit: ``push`` said it was up to date, and then the robot got
the killed push's content back). The endpoint now looks whether its output is still
read before a write request, and ends without applying it.
"""

from __future__ import annotations

import os
import subprocess
import sys

from endpoint_client import ALG

from fetchsync.protocol import hashing, wire
from fetchsync.protocol import messages as M


def test_a_write_queued_after_the_client_went_is_not_applied(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-c", "from fetchsync.protocol.server import main; main()"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=dict(os.environ, HOME=str(tmp_path)),
    )
    assert proc.stdin is not None and proc.stdout is not None
    reader = wire.Reader(proc.stdout.read1)  # type: ignore[attr-defined]
    reader.read_hello()

    def send(data: bytes) -> None:
        proc.stdin.write(data)  # type: ignore[union-attr]
        proc.stdin.flush()  # type: ignore[union-attr]

    def request(req_id: int, header: dict, blob: bytes = b"") -> None:
        send(wire.encode_frame(wire.Frame(wire.T_REQUEST, req_id, header, blob)))

    try:
        send(wire.encode_hello({"algorithm": ALG}))
        request(1, {"op": "open", "workspace": "~/ws"})
        opened = reader.read_frame()
        assert opened is not None and opened.type == wire.T_RESPONSE
        data = b"the killed push's content\n"
        op = M.Op(
            M.WRITE,
            "late.txt",
            expect=M.ABSENT,
            mode=0o644,
            hash=hashing.digest(ALG, data).hex(),
            size=len(data),
            source=M.SRC_DATA,
            blob=(0, len(data)),
        )
        sync = {
            "op": "sync",
            "ops": [op.to_wire()],
            "policy": "preserve",
            "epoch": opened.header["epoch"],
            "gen": opened.header["gen"],
            "require_fresh": True,
        }
        # the client is gone: nobody reads the endpoint's answers any more (sshd closed
        # the channel) while its last request is still on its way in
        proc.stdout.close()
        request(2, sync, data)
        proc.stdin.close()
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not (tmp_path / "ws/src/late.txt").exists(), "applied for a client that had gone"
