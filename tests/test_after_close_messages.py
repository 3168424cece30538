"""A message of ours for a channel the robot's sshd has freed, against the real sshd.

channels.py sends EOF and data only while no CLOSE of ours can be on its way (sshd drops
the whole connection for those). paramiko builds two more kinds of channel message
while the channel is open and sends them after, so one can follow our CLOSE:

- a window adjust (``Channel.recv``): sshd logs it and goes on (checked here);
- a channel request: the PTY's ``window-change`` (``console.resizer``: at the start of
  each command under a PTY, and at every SIGWINCH). sshd disconnects ("unknown
  channel"): a terminal resized as a build step ends lost the build's connection, and
  the steps after it.
"""

from __future__ import annotations

import threading
from typing import Any

import pytest
from paramiko.common import (
    cMSG_CHANNEL_CLOSE,
    cMSG_CHANNEL_REQUEST,
    cMSG_CHANNEL_WINDOW_ADJUST,
)
from paramiko.message import Message
from sshd import SSHHome
from test_session_channels import held_until_closed, run

from fetchsync.console import resizer
from fetchsync.link.ssh import SSHTransport

pytestmark = pytest.mark.ssh


def _wait_unlinked(t: Any, raw: Any) -> None:
    """Until paramiko's reader thread has handled the robot's CLOSE (and sent ours)."""
    for _ in range(3000):
        if t._channels.get(raw.get_id()) is not raw:
            return
        threading.Event().wait(0.01)
    raise AssertionError("the command's channel never closed")


def _freed(transport: SSHTransport) -> Any:
    """A channel whose command ended, with both ends' CLOSE sent and sshd past ours."""
    t: Any = transport._transport  # type: ignore[attr-defined]
    closes: list[int] = []
    real_send = t._send_message

    def send(m: Message) -> None:
        data = m.asbytes()
        if data[:1] == cMSG_CHANNEL_CLOSE:
            closes.append(int.from_bytes(data[1:5], "big"))
        real_send(m)

    t._send_message = send
    try:
        chan = transport.exec("true")
        assert chan.exit_status(30) == 0
        raw = chan._chan  # type: ignore[attr-defined]
        _wait_unlinked(t, raw)
        for _ in range(3000):  # paramiko's reader unlinks the channel, then sends our CLOSE
            if raw.remote_chanid in closes:
                break
            threading.Event().wait(0.01)
        else:
            raise AssertionError("our CLOSE never went out")
    finally:
        t._send_message = real_send
    # a round trip behind our CLOSE: sshd has handled it and freed the channel
    t.global_request("keepalive@openssh.com", wait=True)
    return raw


def _still_there(transport: SSHTransport) -> None:
    assert run(transport, "echo still here") == (0, b"still here\n")
    assert transport.is_alive(10)


def test_a_window_adjust_after_our_close_keeps_the_connection(robot_transport: SSHTransport):
    """What paramiko's recv sends after reading the last data of a command that ended
    meanwhile: sshd only logs it ("window adjust for non-open channel"), so recv needs
    no guard."""
    raw = _freed(robot_transport)
    m = Message()
    m.add_byte(cMSG_CHANNEL_WINDOW_ADJUST)
    m.add_int(raw.remote_chanid)
    m.add_int(1 << 20)
    robot_transport._transport._send_user_message(m)  # type: ignore[attr-defined]
    _still_there(robot_transport)


def test_sshd_drops_the_connection_for_a_request_after_our_close(ssh_home: SSHHome):
    """Why the resize needs its guard: any channel request for a freed channel ends the
    connection, with every command on it (OpenSSH's server_input_channel_req)."""
    transport = SSHTransport.connect("robot", connect_timeout=10.0)
    try:
        raw = _freed(transport)
        m = Message()
        m.add_byte(cMSG_CHANNEL_REQUEST)
        m.add_int(raw.remote_chanid)
        m.add_string("window-change")
        m.add_boolean(False)
        for n in (80, 24, 0, 0):
            m.add_int(n)
        transport._transport._send_user_message(m)  # type: ignore[attr-defined]
        with pytest.raises(Exception):  # noqa: B017 - however the lost link shows
            run(transport, "echo still here")
    finally:
        transport.close()


def test_a_resize_as_the_command_ends_keeps_the_connection(robot_transport: SSHTransport):
    """The terminal resized (SIGWINCH, or attach's first sizing) as a command under a
    PTY ends: the window-change built while the channel was open must not follow our
    CLOSE (a build's next step runs on the same connection)."""
    chan = robot_transport.exec("true", pty=True)
    resize = resizer(chan)
    assert resize is not None

    def closed(t: Any, raw: Any) -> None:
        _wait_unlinked(t, raw)
        threading.Event().wait(0.2)  # sshd has our CLOSE: the channel is freed there

    with held_until_closed(robot_transport, chan, closed):
        resize(100, 30)
    chan.close()
    _still_there(robot_transport)
