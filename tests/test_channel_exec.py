"""A command starts without waiting for the robot's reply to its exec request
(channels.send_exec), against the real sshd: the caller goes on at once, the command
runs, and its output and exit status come as before."""

from __future__ import annotations

import threading
from typing import Any

import paramiko
import pytest
from test_ssh import run

from fetchsync.link.ssh import SSHTransport

pytestmark = pytest.mark.ssh


def test_exec_returns_before_the_robot_replies(
    robot_transport: SSHTransport, monkeypatch: pytest.MonkeyPatch
) -> None:
    release = threading.Event()
    replied = threading.Event()
    success = paramiko.Channel._request_success

    def held(self: Any, m: Any) -> None:  # the reply is read, and held, on paramiko's thread
        release.wait(10)
        replied.set()
        success(self, m)

    from paramiko.common import MSG_CHANNEL_SUCCESS

    table = paramiko.Transport._channel_handler_table  # what paramiko's thread dispatches by
    monkeypatch.setitem(table, MSG_CHANNEL_SUCCESS, held)
    chan = robot_transport.exec("echo started")
    went_on = not replied.is_set()  # exec returned while the reply was held
    release.set()
    try:
        assert went_on
        out = b""
        while chunk := chan.recv(65536):
            out += chunk
        assert out == b"started\n" and chan.exit_status(10) == 0
        assert replied.wait(10)
    finally:
        chan.close()


def test_a_command_that_fails_reports_its_status_and_stderr(
    robot_transport: SSHTransport,
) -> None:
    assert run(robot_transport, "echo oops >&2; exit 3") == (b"", b"oops\n", 3)
