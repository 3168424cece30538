"""A hostile robot against the pipelined publickey login (ssh._PipelinedAuth): one that
refuses the ``ssh-userauth`` service (SSH_DISCONNECT_SERVICE_NOT_AVAILABLE) although the
signed login already follows the request, and one that refuses the key and offers only
another method. Each is a clear one-line failure at once (not the deadline's), never a login claimed. The robot is a paramiko server (its host key accepted by fingerprint)."""

from __future__ import annotations

import socket
import threading
from typing import Any

import paramiko
import pytest
from sshd import SSHHome
from test_ssh import extra_config

from fetchsync.errors import ConnectError, FetchsyncError
from fetchsync.link import ssh
from fetchsync.link.ssh import SSHTransport

pytestmark = pytest.mark.ssh


class _Robot(paramiko.ServerInterface):  # type: ignore[misc]
    def get_allowed_auths(self, username: str) -> str:
        return "password"

    def check_auth_publickey(self, username: str, key: Any) -> int:
        return paramiko.AUTH_FAILED

    def check_auth_password(self, username: str, password: str) -> int:
        return paramiko.AUTH_FAILED


@pytest.fixture
def hostile(ssh_home: SSHHome, monkeypatch: pytest.MonkeyPatch):
    """(fingerprint, transports) of a paramiko robot on a local port, ``Host hostile``."""
    key = paramiko.ECDSAKey.generate()
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(4)
    port = server.getsockname()[1]
    transports: list[paramiko.Transport] = []

    def serve() -> None:
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            t = paramiko.Transport(conn)
            t.add_server_key(key)
            transports.append(t)
            try:
                t.start_server(server=_Robot())
            except Exception:
                pass

    threading.Thread(target=serve, daemon=True).start()
    extra_config(ssh_home, f"Host hostile\n    HostName 127.0.0.1\n    Port {port}\n{{common}}")
    yield ssh.host_key_fingerprint(key), transports
    server.close()
    for t in transports:
        t.close()


def _connect(fingerprint: str) -> BaseException:
    with pytest.raises(FetchsyncError) as caught:
        SSHTransport.connect("hostile", connect_timeout=30.0, accept_fingerprint=fingerprint)
    return caught.value


def test_a_robot_refusing_the_service_is_one_line(hostile, monkeypatch) -> None:
    fingerprint, _ = hostile

    def refuse(self: Any, m: Any) -> None:
        if self.transport.server_mode:
            self._disconnect_service_not_available()

    monkeypatch.setattr(paramiko.auth_handler.AuthHandler, "_parse_service_request", refuse)
    error = _connect(fingerprint)
    assert isinstance(error, ConnectError), repr(error)
    assert "\n" not in str(error) and "timed out" not in str(error), str(error)
    print(error)


def test_a_robot_refusing_the_key_and_offering_another_method_is_one_line(hostile) -> None:
    fingerprint, _ = hostile
    error = _connect(fingerprint)
    assert isinstance(error, ConnectError), repr(error)
    assert "\n" not in str(error) and "timed out" not in str(error), str(error)
    print(error)
