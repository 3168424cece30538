"""Opening a session with a robot: resolve the target, connect, load the state.

Shared by every verb that talks to a robot, so they all resolve robot, user
and workspaces the same way and go through the same connection object.
"""

from __future__ import annotations

import logging
import os
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

from fetchsync.config import Target
from fetchsync.errors import ConfigError, ConnectError, LinkLostError
from fetchsync.link.connection import Connection, remote_python
from fetchsync.link.transport import LocalTransport, Transport, local_robot_home, robot_id
from fetchsync.trace import mark

__all__ = ["robot_id"]  # its home is link/transport.py (light: the fast path of a push)

log = logging.getLogger(__name__)


def terminal_prompt() -> Callable[[str], str | None] | None:
    """Ask for a password or passphrase on the controlling terminal, as ssh does.

    None when there is no terminal (CI, cron, a service): the connection then
    fails with one line instead of waiting for an answer nobody can give. The
    answer is read without echo and goes only to the SSH server: never to a
    log, a command line or the environment.
    """
    try:
        fd = os.open("/dev/tty", os.O_RDWR | os.O_NOCTTY)
    except OSError:
        return None
    os.close(fd)

    def ask(prompt: str) -> str | None:
        import getpass
        import warnings

        with warnings.catch_warnings():
            # without echo control getpass warns and reads anyway; refuse instead
            warnings.simplefilter("error", getpass.GetPassWarning)
            try:
                return getpass.getpass(prompt)
            except (EOFError, getpass.GetPassWarning):
                return None

    return lambda prompt: _one_at_a_time(prompt, ask)


def terminal_confirm() -> Callable[[str], str | None] | None:
    """Ask a question on the controlling terminal and read the typed line (echoed), as
    ssh asks whether to accept an unknown host key. None unless we run at a terminal
    (stdin one, and /dev/tty opens): an editor hook, a service or CI gets the one-line
    refusal instead of a question nobody sees."""
    if not os.isatty(0):
        return None
    try:
        fd = os.open("/dev/tty", os.O_RDWR | os.O_NOCTTY)
    except OSError:
        return None
    os.close(fd)

    def ask(prompt: str) -> str | None:
        try:
            fd = os.open("/dev/tty", os.O_RDWR | os.O_NOCTTY)
        except OSError:
            return None
        try:
            os.write(fd, prompt.encode("utf-8", "replace"))
            line = b""
            while not line.endswith(b"\n"):
                chunk = os.read(fd, 1024)  # a line at a time: the terminal is canonical
                if not chunk:
                    return None if not line else line.decode("utf-8", "replace")
                line += chunk
            return line.decode("utf-8", "replace")
        except OSError:
            return None
        finally:
            os.close(fd)

    return lambda prompt: _one_at_a_time(prompt, ask)


_TERMINAL = threading.Lock()


def _one_at_a_time(prompt: str, ask: Callable[[str], str | None]) -> str | None:
    """Ask ``prompt`` on the terminal while no other thread asks. Only the question
    waits: the connections of a fleet's other robots go on meanwhile, so twenty robots'
    handshakes at a terminal take one's time, not the sum (on Wi-Fi ~0.3-0.5 s each:
    6-10 s for twenty). A host key shared by several robots is asked once by ssh.py
    (_UNKNOWN_KEYS). No answer is kept: a passphrase or password lives no longer than
    its login, and a wrong one is asked for again."""
    with _TERMINAL:
        return ask(prompt)


def open_transport(
    target: Target, *, accept_fingerprint: str | None = None, persistent: bool = True
) -> Transport:
    """A transport to the target's robot.

    ``persistent`` goes through (or leaves behind) a connection master; pass
    False for commands that need a PTY or an environment, which only a direct
    SSH connection runs.
    """
    if target.is_local:
        home = local_robot_home()
        remote = target.remote_workspace
        resolved = Path(
            os.path.normpath(os.path.join(home, remote[2:]) if remote.startswith("~/") else remote)
        )
        if resolved.resolve() == target.workspace.resolve():
            raise ConfigError(
                f"the local robot's workspace {resolved} is the local workspace itself",
                hint="pass --remote-workspace with another path",
            )
        return LocalTransport(home)
    from fetchsync.link import mux

    path = None
    if persistent and mux.persist_seconds() > 0:
        try:
            path = mux.socket_path(target.host, target.user)
        except ConnectError as exc:  # this call goes direct: only the master needs the socket
            log.warning("fetchsync: no connection master: %s", exc)
    if path is not None:
        mark("session: asking the master")
        mux.wait_while_starting(path)
        attached = mux.MuxTransport.attach(path, target.robot)
        mark("session: the master " + ("answered" if attached else "is not there"))
        if attached is not None:
            return attached
    from fetchsync.link import early

    # the route this host took last time, opened before paramiko's import (~60 ms) that
    # the fresh resolution needs: its first answer comes meanwhile (see early)
    route = early.start(target.host, user=target.user)
    try:
        from fetchsync.link.ssh import SSHTransport  # paramiko is slow to import: only when needed
    except BaseException:
        if route is not None:
            route.close()
        raise
    transport = SSHTransport.connect(
        target.host,
        user=target.user,
        accept_fingerprint=accept_fingerprint,
        password_callback=terminal_prompt(),
        confirm_callback=terminal_confirm(),
        early=route,
    )
    # a master authenticates on its own, without a terminal: after a password
    # login it would only add a failed login to the robot's log
    if path is not None and transport.auth_method != "password":
        # this call paid for the handshake; leave a master behind for the next
        # ones, once it is done: a master starting now would take the CPU this
        # call needs. It keeps a spare of the endpoint this call started (see mux).
        transport.on_close = lambda: mux.spawn_master(target.host, target.user, path, spare=True)
    return transport


def open_connection(
    target: Target,
    transport: Transport,
    *,
    accept_fingerprint: str | None = None,
    meanwhile: Callable[[Callable[[], bool]], Any] | None = None,
) -> tuple[Transport, Connection]:
    """Start the endpoint over ``transport``; through a connection master, make sure it
    answers before anything is asked of it, and once, start another if it does not.

    The master hands over the spare endpoint it started ahead of the call, checked alive
    just before (see mux); it can still die after that check (killed, OOM) and fail the
    call with "went away" before it has answered anything. Nothing was asked of it then,
    so this call starts a fresh endpoint in its place (through the master again, whose
    spare it took, or directly if the master is gone) instead of failing a push that the
    next call would do. A ping is the proof: no request of the caller's is sent before
    it is answered, so no write is ever replayed. It is sent with our hello, while the
    caller's ``meanwhile`` work runs (Connection.open), so its round trip is paid only
    where that work is shorter.
    Returns the transport in use (a new one after a retry) and the connection.
    """
    from fetchsync.link import mux

    if not isinstance(transport, mux.MuxTransport):
        return transport, Connection.open(transport, python=remote_python(), meanwhile=meanwhile)
    conn: Connection | None = None
    try:
        conn = Connection.open(transport, python=remote_python(), meanwhile=meanwhile, ping=True)
        assert conn.ping_id is not None
        conn.wait(conn.ping_id)
        mark("session: the endpoint answered a ping")
        return transport, conn
    except (LinkLostError, ConnectError) as exc:
        log.info(
            "the endpoint from the connection master failed before any request (%s): "
            "starting another",
            exc,
        )
        if conn is not None:
            conn.close()
        transport.close()
    transport = open_transport(target, accept_fingerprint=accept_fingerprint)
    try:
        return transport, Connection.open(transport, python=remote_python())
    except BaseException:
        transport.close()
        raise


@contextmanager
def connect(
    target: Target,
    *,
    accept_fingerprint: str | None = None,
    meanwhile: Callable[[Callable[[], bool]], Any] | None = None,
) -> Iterator[Connection]:
    """A connection to the target's endpoint; ``meanwhile`` runs while the endpoint
    starts (see :meth:`Connection.open`)."""
    transport = open_transport(target, accept_fingerprint=accept_fingerprint)
    try:
        transport, conn = open_connection(
            target, transport, accept_fingerprint=accept_fingerprint, meanwhile=meanwhile
        )
    except BaseException:
        transport.close()
        raise
    try:
        try:
            yield conn
        finally:
            conn.close()
            mark("session: the endpoint's channel closed")
    finally:
        transport.close()
        mark("session: the transport closed")
