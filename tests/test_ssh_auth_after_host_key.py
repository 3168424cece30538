"""Nothing of a login is sent, nor anything signed with the user's key, before the
robot's host key is checked: a robot whose key is not the one known_hosts lists (a
man in the middle) gets no service request, no login request and no signature, also
now that the publickey login is pipelined behind the service request
(ssh._PipelinedAuth) and a remembered route opened before the config is parsed
(fetchsync.link.early). Against the real sshd, known_hosts listing another key."""

from __future__ import annotations

from typing import Any

import paramiko
import pytest
from sshd import SSHHome
from test_ssh_auth_pipelined import _recorded

from fetchsync.errors import HostKeyError
from fetchsync.link import early
from fetchsync.link.ssh import SSHTransport

pytestmark = pytest.mark.ssh


@pytest.fixture(autouse=True)
def _own_cache(tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(early, "SETTLED_NS", 0)


@pytest.mark.parametrize("route", ["fresh", "early"])
def test_a_changed_host_key_gets_no_login_and_no_signature(
    ssh_home: SSHHome, monkeypatch: pytest.MonkeyPatch, route: str
) -> None:
    if route == "early":  # a first connection remembers the route
        SSHTransport.connect("robot", connect_timeout=10.0).close()
    signed: list[str] = []
    for cls in (paramiko.Ed25519Key, paramiko.ECDSAKey, paramiko.RSAKey):
        original = cls.sign_ssh_data

        def sign(self: Any, *args: Any, _original: Any = original, **kwargs: Any) -> Any:
            signed.append(self.get_name())
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(cls, "sign_ssh_data", sign)
    events = _recorded(monkeypatch)
    line = ssh_home.known_hosts.read_text().split("\n")[0].split()
    other = paramiko.Ed25519Key.from_private_key_file(str(ssh_home.identity))
    ssh_home.known_hosts.write_text(f"{line[0]} {other.get_name()} {other.get_base64()}\n")
    link = early.start("robot") if route == "early" else None
    assert (link is not None) == (route == "early")
    with pytest.raises(HostKeyError, match="CHANGED"):
        SSHTransport.connect("robot", connect_timeout=10.0, early=link)
    assert events == [] and signed == [], (events, signed)
