"""Attaching a command running on the robot to this process's terminal and streams.

:func:`attach` pumps a :class:`~fetchsync.link.transport.Channel` until the remote
command ends and returns its exit status:

- the command's stdout and stderr go to ours, each as soon as it arrives and
  kept apart (with a PTY the robot merges them, as a terminal does);
- our stdin goes to the command; its end becomes the command's EOF (without a
  PTY; with one, ``^D`` is just a key);
- with ``pty=True`` and a terminal on our stdin, the terminal is put in raw
  mode for the duration, so every key (``^C`` included) reaches the robot's
  PTY, and window size changes are passed on.

A :class:`~fetchsync.errors.LinkLostError` from the channel propagates; so does
``KeyboardInterrupt`` (the caller closes the channel).
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import select
import threading
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

from fetchsync.errors import LinkLostError

if TYPE_CHECKING:
    from fetchsync.link.transport import Channel

# C0 and C1 controls, DEL, the bidirectional overrides and isolates (they reorder
# what a line shows), and undecodable bytes (surrogate escapes of os.fsdecode)
_UNPRINTABLE = re.compile("[\x00-\x1f\x7f-\x9f\u200e\u200f\u202a-\u202e\u2066-\u2069\udc80-\udcff]")


def _escape(match: re.Match[str]) -> str:
    code = ord(match.group())
    if 0xDC80 <= code <= 0xDCFF:
        return f"\\x{code - 0xDC00:02x}"  # the byte that did not decode
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


def printable(text: object) -> str:
    """``text`` safe to print on a terminal: every control character, escape sequence
    introducer, bidirectional override and undecodable byte shown as ``\\xNN`` /
    ``\\uNNNN``. For anything a robot (or any file name) controls: a name holding
    ``ESC ]52;...`` would otherwise write the clipboard, retitle or clear the terminal."""
    return _UNPRINTABLE.sub(_escape, str(text))


NO_STATUS = -1
"""What :func:`attach` returns when the command ended without an exit status."""

_CHUNK = 65536


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        written = os.write(fd, view)
        view = view[written:]


def window_size(fd: int = 1) -> tuple[int, int]:
    """(columns, lines) of the terminal on ``fd``, or of the first of our streams that is one."""
    for candidate in (fd, 0, 1, 2):
        try:
            size = os.get_terminal_size(candidate)
            return size.columns, size.lines
        except OSError:
            continue
    import shutil  # only without a terminal on the standard streams

    size = shutil.get_terminal_size()
    return size.columns, size.lines


def resizer(channel: Channel) -> Callable[[int, int], None] | None:
    """How to pass a new window size to ``channel``'s PTY, if its transport can."""
    resize = getattr(channel, "resize_pty", None)
    if resize is None:
        # a channel without a resize of its own: its paramiko channel's, if any
        inner = getattr(channel, "_chan", None)
        resize = getattr(inner, "resize_pty", None)
    if resize is None:
        return None

    def apply(columns: int, lines: int) -> None:
        try:
            resize(width=columns, height=lines)
        except Exception as exc:  # noqa: BLE001 - a lost link shows up on the stream instead
            import logging  # not at the top: the fast path of a push prints through here

            logging.getLogger(__name__).debug("cannot resize the robot's terminal: %s", exc)

    return apply


class _StdinPump:
    """Copies our stdin to the channel in a thread that can be told to stop."""

    def __init__(self, channel: Channel, fd: int, *, send_eof: bool) -> None:
        self._channel = channel
        self._fd = fd
        self._send_eof = send_eof
        self._stop_r, self._stop_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="fetchsync-stdin", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        try:
            while True:
                try:
                    ready, _, _ = select.select([self._fd, self._stop_r], [], [])
                except (OSError, ValueError):
                    ready = [self._fd]  # a closed stdin: read() reports the end below
                if self._stop_r in ready:
                    return
                try:
                    data = os.read(self._fd, _CHUNK)
                except OSError as exc:
                    if exc.errno in (errno.EAGAIN, errno.EINTR):
                        continue
                    data = b""
                if not data:
                    if self._send_eof:
                        self._channel.shutdown_write()
                    return
                self._channel.send_all(data)
        except LinkLostError:
            return  # the stdout side reports it

    def stop(self) -> None:
        with contextlib.suppress(OSError):
            os.write(self._stop_w, b"x")
        self._thread.join(timeout=1.0)
        if not self._thread.is_alive():
            os.close(self._stop_r)
            os.close(self._stop_w)


class _StderrPump:
    def __init__(self, channel: Channel, fd: int) -> None:
        self._channel = channel
        self._fd = fd
        self._thread = threading.Thread(target=self._run, name="fetchsync-stderr", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        closed = False
        while True:
            data = self._channel.recv_stderr(_CHUNK)
            if not data:
                return
            if closed:
                continue
            try:
                _write_all(self._fd, data)
            except OSError:
                closed = True  # keep draining, or the robot would block on a full window

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)


@contextlib.contextmanager
def raw_terminal(fd: int) -> Iterator[None]:
    """Our terminal in raw mode (every byte to the robot's PTY), restored afterwards."""
    import termios
    import tty

    saved = termios.tcgetattr(fd)
    tty.setraw(fd, termios.TCSANOW)
    try:
        yield
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


@contextlib.contextmanager
def _window_changes(resize: Callable[[int, int], None] | None) -> Iterator[None]:
    if resize is None or threading.current_thread() is not threading.main_thread():
        yield
        return

    import signal  # only for a PTY's window (a push imports this module too)

    def changed(_signum: int, _frame: Any) -> None:
        resize(*window_size())

    previous = signal.signal(signal.SIGWINCH, changed)
    try:
        yield
    finally:
        signal.signal(signal.SIGWINCH, previous)


def attach(
    channel: Channel, *, pty: bool = False, stdin: int | None = 0, stdout: int = 1, stderr: int = 2
) -> int:
    """Pump ``channel`` to and from our streams until the command ends; its exit status.

    ``stdin=None`` gives the command an empty stdin. ``stdout``/``stderr``
    are file descriptors (pass 2 as ``stdout`` to keep our stdout clean).
    Returns :data:`NO_STATUS` when the command ended without a status.
    Raises ``BrokenPipeError`` when our stdout was closed (the caller closes
    the channel, which stops the command).
    """
    raw = pty and stdin is not None and os.isatty(stdin)
    pump = _StdinPump(channel, stdin, send_eof=not pty) if stdin is not None else None
    if pump is None:
        channel.shutdown_write()
    errors = _StderrPump(channel, stderr)
    with contextlib.ExitStack() as stack:
        if raw:
            assert stdin is not None
            resize = resizer(channel)
            if resize is not None:
                # the PTY was sized from our stdout, which need not be the terminal
                resize(*window_size(stdin))
            stack.enter_context(raw_terminal(stdin))
            stack.enter_context(_window_changes(resize))
        errors.start()
        if pump is not None:
            pump.start()
            stack.callback(pump.stop)
        while True:
            data = channel.recv(_CHUNK)
            if not data:
                break
            _write_all(stdout, data)
        errors.join()
    status = channel.exit_status()
    return NO_STATUS if status is None or status < 0 else status


# the line that says where an answer goes (here: the fast path of a push prints it too)
ARROW = "\u2192"
BOTH = "\u2194"


def robot_place(target: Any, remote: str | None) -> str:
    """``user@robot:remote`` as the user would type it for scp (``local:...`` for the local
    robot; without ``:remote`` when there is no remote path)."""
    from fetchsync.config import login_name

    login = login_name(target)
    who = f"{login}@{target.robot}" if login else target.robot
    return f"{who}:{remote}" if remote else who


def where_line(
    verb: str, target: Any, *, local: Any = None, remote: str | None = None, direction: str = "to"
) -> str:
    """``push ~/noetic/src → fetch@freight0:~/noetic/src``: the verb, the local place (``~``
    for home), the robot's place with its user; ``direction`` is ``to`` the robot, ``from``
    it, or ``both`` (a comparison)."""
    from fetchsync.config import home_relative

    there = printable(robot_place(target, remote))  # a name may hold escape sequences
    if local is None:
        return f"{verb} {there}"
    here = printable(home_relative(local))
    if direction == "from":
        return f"{verb} {there} {ARROW} {here}"
    return f"{verb} {here} {BOTH if direction == 'both' else ARROW} {there}"
