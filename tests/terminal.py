"""Running fetchsync on a pseudo-terminal, as a user at a terminal does (PTY tests)."""

from __future__ import annotations

import fcntl
import os
import pty
import select
import struct
import subprocess
import sys
import termios
import time


class Terminal:
    """fetchsync on a pseudo-terminal of ours, as a user at a terminal starts it."""

    def __init__(self, args: list[str], env: dict[str, str], *, rows: int = 24, cols: int = 80):
        self.master, slave = pty.openpty()
        self.resize(rows, cols, fd=slave)
        # setsid -c: a session of its own whose controlling terminal is ours
        self.proc = subprocess.Popen(
            ["setsid", "-c", sys.executable, "-m", "fetchsync", *args],
            env=env,
            stdin=slave,
            stdout=slave,
            stderr=slave,
        )
        os.close(slave)
        self.output = b""

    def resize(self, rows: int, cols: int, *, fd: int | None = None) -> None:
        fcntl.ioctl(
            self.master if fd is None else fd,
            termios.TIOCSWINSZ,
            struct.pack("HHHH", rows, cols, 0, 0),
        )

    def read_until(self, needle: bytes, timeout: float = 30.0) -> bytes:
        deadline = time.monotonic() + timeout
        while needle not in self.output:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"timed out waiting for {needle!r}; got {self.output!r}")
            ready, _, _ = select.select([self.master], [], [], left)
            if ready:
                try:
                    data = os.read(self.master, 4096)
                except OSError:  # EIO: the other side closed
                    data = b""
                if not data:
                    raise AssertionError(f"ended before {needle!r}; got {self.output!r}")
                self.output += data
        return self.output

    def send(self, data: bytes) -> None:
        os.write(self.master, data)

    def wait(self, timeout: float = 30.0) -> int:
        deadline = time.monotonic() + timeout
        while self.proc.poll() is None and time.monotonic() < deadline:
            ready, _, _ = select.select([self.master], [], [], 0.1)
            if ready:
                try:
                    self.output += os.read(self.master, 4096)
                except OSError:
                    pass
        code = self.proc.wait(timeout=1)
        self._drain()
        return code

    def _drain(self) -> None:
        """What the process wrote before it exited: a process that writes its last line
        and exits at once (os._exit) is seen gone by poll() before that line is read,
        and the line was lost (test_errors_cli.py::test_wrong_password, once in CI)."""
        while select.select([self.master], [], [], 0.2)[0]:
            try:
                data = os.read(self.master, 4096)
            except OSError:  # EIO: every writer gone and nothing left
                return
            if not data:
                return
            self.output += data

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        os.close(self.master)
