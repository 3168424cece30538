"""A publickey login in one round trip (ssh._PipelinedAuth), against the real sshd: the
signed request goes right behind the service request, before the robot accepted the
service; the login succeeds, and a key the robot refuses is followed by the next one."""

from __future__ import annotations

import threading
from typing import Any

import pytest
from sshd import SSHHome
from test_ssh import extra_config, run

from fetchsync.link import ssh
from fetchsync.link.ssh import SSHTransport

pytestmark = pytest.mark.ssh

SERVICE_REQUEST, USERAUTH_REQUEST = 5, 50


def _recorded(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """What the login sent and received, in order; a request sent while paramiko's
    transport thread handled an answer (the acceptance) says so."""
    events: list[str] = []
    send = ssh._Transport._send_message
    accept = ssh._PipelinedAuth._parse_service_accept

    def sending(self: Any, m: Any) -> None:
        kind = m.asbytes()[0]
        if kind in (SERVICE_REQUEST, USERAUTH_REQUEST):
            what = "service request" if kind == SERVICE_REQUEST else "login"
            on_answer = threading.current_thread() is self  # the transport's own thread
            events.append(f"sent {what}" + (" on an answer" if on_answer else ""))
        send(self, m)

    def accepted(self: Any, m: Any) -> None:
        events.append("service accepted")
        accept(self, m)

    monkeypatch.setattr(ssh._Transport, "_send_message", sending)
    monkeypatch.setattr(ssh._PipelinedAuth, "_parse_service_accept", accepted)
    return events


def test_the_login_goes_before_the_service_is_accepted(
    ssh_home: SSHHome, monkeypatch: pytest.MonkeyPatch
) -> None:
    events = _recorded(monkeypatch)
    transport = SSHTransport.connect("robot", connect_timeout=10.0)
    try:
        assert transport.auth_method == "publickey"
        assert run(transport, "echo in") == (b"in\n", b"", 0)
    finally:
        transport.close()
    # the login went from the caller's thread, right behind the service request: not
    # from paramiko's, once the acceptance was read
    assert [e for e in events if e.startswith("sent")] == ["sent service request", "sent login"]
    assert events.count("service accepted") == 1


def test_a_refused_key_is_followed_by_the_next_one(
    ssh_home: SSHHome, monkeypatch: pytest.MonkeyPatch, tmp_path: Any
) -> None:
    import paramiko

    stranger = tmp_path / "stranger"
    key = paramiko.ECDSAKey.generate()  # a key the robot does not know
    key.write_private_key_file(str(stranger))
    extra_config(
        ssh_home,
        "Host twokeys\n    HostName {host}\n    Port {port}\n"
        f"    IdentityFile {stranger}\n{{common}}    IdentitiesOnly yes\n",
    )
    events = _recorded(monkeypatch)
    transport = SSHTransport.connect("twokeys", connect_timeout=10.0)
    try:
        assert run(transport, "echo second") == (b"second\n", b"", 0)
    finally:
        transport.close()
    sent = [e for e in events if e.startswith("sent")]
    assert sent == ["sent service request", "sent login"] * 2
