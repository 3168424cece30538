"""How bytes reach a robot: the transport interface and the ``local`` robot.

A transport runs a command on the robot and hands back a :class:`Channel`, a
plain byte stream to the command's stdin/stdout (stderr kept apart). The sync
protocol knows nothing else of SSH: ``fetchsync.link.ssh.SSHTransport`` implements
this over paramiko, :class:`LocalTransport` over a local subprocess, so tests
and the quickstart can use the robot-side endpoint without an SSH server.
"""

from __future__ import annotations

import io
import os
import select
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, cast

from fetchsync.config import LOCAL_ROBOT
from fetchsync.environ import inheritable
from fetchsync.errors import ConnectError, LinkLostError
from fetchsync.places import local_robot_home as local_robot_home  # callers import it here too
from fetchsync.places import robot_id as robot_id  # its old home: callers import it here

if TYPE_CHECKING:
    import subprocess


# subprocess, signal and shlex are imported where the local robot uses them: a push
# through SSH or a connection master needs none (subprocess is ~3-5 ms of its start)


class Channel(Protocol):
    """A running remote command: its stdin, stdout and stderr as byte streams."""

    def send_all(self, data: bytes | memoryview) -> None:
        """Write all of ``data`` to the command's stdin (raises LinkLostError)."""

    def recv(self, n: int) -> bytes:
        """Up to ``n`` bytes of stdout; ``b""`` at end of stream."""

    def recv_stderr(self, n: int) -> bytes:
        """Up to ``n`` bytes of stderr; ``b""`` at end of stream."""

    def ready(self) -> bool:
        """Whether ``recv`` would return at once: stdout has bytes, or has ended."""

    def shutdown_write(self) -> None:
        """Close the command's stdin (EOF), keep reading."""

    def exit_status(self, timeout: float | None = None) -> int | None:
        """Wait up to ``timeout`` seconds for the exit status; None if still running."""

    def close(self) -> None:
        """Close the channel; the remote command gets EOF/SIGHUP."""


@dataclass(frozen=True)
class Capabilities:
    """What a transport can do besides running commands, declared rather than probed.

    ``keepalive``: :meth:`Transport.is_alive` sends a keepalive the robot must answer,
    and ``ping()`` sends one without waiting (see ``SSHTransport.ping``), so a caller
    waiting on a silent link can tell a dead link from a slow robot (SSH); without it,
    ``is_alive`` only says the transport was not closed, and a dead endpoint shows as
    the end of its channel (the ``local`` robot, a connection master's socket).
    """

    keepalive: bool = False


class Transport(Protocol):
    """Something that runs commands on one robot."""

    name: str
    capabilities: Capabilities

    def exec(
        self, command: str, *, env: dict[str, str] | None = None, pty: bool = False
    ) -> Channel:
        """Start ``command`` (a shell command line) on the robot."""

    def is_alive(self, timeout: float | None = None) -> bool:
        """Whether the robot still answers (see :class:`Capabilities`)."""

    def close(self) -> None:
        """Drop the connection."""


class _ProcessChannel:
    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        self._proc = proc
        self._lock = threading.Lock()
        self._eof_sent = False

    def send_all(self, data: bytes | memoryview) -> None:
        assert self._proc.stdin is not None
        try:
            self._proc.stdin.write(data)
            self._proc.stdin.flush()
        except (BrokenPipeError, ValueError, OSError) as exc:
            raise LinkLostError("the local robot's endpoint went away") from exc

    def recv(self, n: int) -> bytes:
        assert self._proc.stdout is not None
        try:
            return cast(io.BufferedReader, self._proc.stdout).read1(n)
        except (ValueError, OSError) as exc:
            raise LinkLostError("the local robot's endpoint went away") from exc

    def ready(self) -> bool:
        # a poll of the pipe: right while nothing was read yet, as when the endpoint
        # starts; after a read, bytes may wait in the reader's buffer instead
        assert self._proc.stdout is not None
        try:
            return bool(select.select([self._proc.stdout], [], [], 0)[0])
        except (ValueError, OSError):
            return True  # closed: recv returns at once

    def recv_stderr(self, n: int) -> bytes:
        assert self._proc.stderr is not None
        try:
            return cast(io.BufferedReader, self._proc.stderr).read1(n)
        except (ValueError, OSError):
            return b""

    def shutdown_write(self) -> None:
        self._eof_sent = True
        if self._proc.stdin is not None and not self._proc.stdin.closed:
            try:
                self._proc.stdin.close()
            except (OSError, ValueError):
                pass

    def exit_status(self, timeout: float | None = None) -> int | None:
        import subprocess

        try:
            return self._proc.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def close(self) -> None:
        import signal
        import subprocess

        if self._proc.poll() is None:
            if not self._eof_sent:
                # an abandoned session (a stalled endpoint, Ctrl-C): end the endpoint's
                # whole group at once, even stopped; closing a pipe first would wait on
                # the thread blocked writing it (see connection._Watchdog)
                try:
                    os.killpg(self._proc.pid, signal.SIGKILL)
                except OSError:
                    pass
            self._proc.terminate()
            try:
                self._proc.wait(2)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        self.shutdown_write()
        for stream in (self._proc.stdout, self._proc.stderr):
            if stream is not None:
                try:
                    stream.close()
                except (OSError, ValueError):
                    pass


class LocalTransport:
    """The ``local`` robot: commands run here, with HOME set to the robot's home."""

    name = LOCAL_ROBOT
    capabilities = Capabilities()

    def __init__(self, home: Path | None = None) -> None:
        self.home = home if home is not None else local_robot_home()

    def is_alive(self, timeout: float | None = None) -> bool:
        return True  # a local endpoint that dies ends its pipes

    def exec(
        self, command: str, *, env: dict[str, str] | None = None, pty: bool = False
    ) -> Channel:
        try:
            self.home.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConnectError(
                f"cannot create the local robot's home {self.home}: {exc.strerror}"
            ) from exc
        import subprocess

        full_env = inheritable(os.environ)  # no password of the call's (fetchsync.environ)
        full_env["HOME"] = str(self.home)
        full_env.pop("XDG_CACHE_HOME", None)
        if env:
            full_env.update(env)
        try:
            proc = subprocess.Popen(
                ["/bin/sh", "-c", command],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                env=full_env,
                cwd=str(self.home),
                start_new_session=True,
            )
        except OSError as exc:
            raise ConnectError(f"cannot start the local robot: {exc.strerror}") from exc
        return _ProcessChannel(proc)

    def close(self) -> None:
        pass

    def __repr__(self) -> str:
        import shlex

        return f"LocalTransport(home={shlex.quote(str(self.home))})"
