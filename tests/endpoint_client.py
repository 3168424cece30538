"""A bare client of the real robot-side endpoint, run as a subprocess over pipes (the
``local`` robot's way), for tests that speak the protocol request by request."""

from __future__ import annotations

import os
import subprocess
import sys
from typing import Any

from fetchsync.protocol import wire

ALG = "blake2b-128"


class Endpoint:
    def __init__(self, home: str, **env: str) -> None:
        e = dict(os.environ, HOME=home, **env)
        self.proc = subprocess.Popen(
            [sys.executable, "-c", "from fetchsync.protocol.server import main; main()"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=e,
        )
        assert self.proc.stdout is not None and self.proc.stdin is not None
        self.reader = wire.Reader(self.proc.stdout.read1)  # type: ignore[attr-defined]
        self.hello = self.reader.read_hello()
        self.proc.stdin.write(wire.encode_hello({"algorithm": ALG}))
        self.proc.stdin.flush()
        self.next_id = 1

    def request(self, header: dict[str, Any], blob: bytes = b"") -> wire.Frame:
        req_id, self.next_id = self.next_id, self.next_id + 1
        assert self.proc.stdin is not None
        self.proc.stdin.write(wire.encode_frame(wire.Frame(wire.T_REQUEST, req_id, header, blob)))
        self.proc.stdin.flush()
        frame = self.reader.read_frame()
        assert frame is not None and frame.req_id == req_id
        return frame

    def peak_rss(self) -> int:
        """The endpoint's peak resident memory so far, in bytes (VmHWM: its own, unlike
        ru_maxrss, which keeps the forking parent's peak across exec)."""
        with open(f"/proc/{self.proc.pid}/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
        raise AssertionError("no VmHWM")

    def close(self) -> tuple[int, bytes]:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(30)
        assert self.proc.stderr is not None
        return self.proc.returncode, self.proc.stderr.read()

    def __enter__(self) -> "Endpoint":
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.proc.poll() is None:
            self.close()
