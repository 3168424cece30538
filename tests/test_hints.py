"""Every hint a user may paste into a shell does what it says, and nothing else (issue 22 item 26)."""

from __future__ import annotations

import os
import shlex
import subprocess
from pathlib import Path

import pytest
from sshd import SSHHome

from fetchsync.errors import ConnectError, HostKeyError
from fetchsync.link.ssh import SSHTransport, shell_path

pytestmark = pytest.mark.ssh


def pasted(command: str, home: Path) -> subprocess.CompletedProcess:
    """``command`` pasted into bash by a user whose HOME is ``home``."""
    return subprocess.run(
        ["bash", "-c", command],
        env=dict(os.environ, HOME=str(home)),
        capture_output=True,
        text=True,
        check=False,
        timeout=30,
    )


def test_the_changed_key_hint_removes_the_old_key_when_pasted(ssh_home: SSHHome, tmp_path: Path):
    sshd = ssh_home.sshd
    other = tmp_path / "other_host_key"
    subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(other)], check=True)
    key_type, data = other.with_suffix(".pub").read_text().split()[:2]
    ssh_home.known_hosts.write_text(f"{sshd.known_hosts_name} {key_type} {data}\n")
    with pytest.raises(HostKeyError) as info:
        SSHTransport.connect("robot", connect_timeout=5.0)
    hint = info.value.hint or ""
    command = hint.split("remove the old key with ", 1)[1].split(" and check", 1)[0]
    assert command.startswith("ssh-keygen -R ") and " -f ~/" in command, command
    done = pasted(command, ssh_home.home)
    assert done.returncode == 0, done.stderr
    assert data not in ssh_home.known_hosts.read_text()


@pytest.mark.parametrize("known", [True, False])
def test_a_hint_built_from_a_hostile_user_name_runs_nothing(
    known, ssh_home: SSHHome, tmp_path: Path
):
    marker = tmp_path / "ran"
    user = f"$(touch {marker})"
    if not known:
        ssh_home.known_hosts.write_text("")
    with pytest.raises(ConnectError) as info:
        SSHTransport.connect("robot", user=user, connect_timeout=5.0)
    hint = info.value.hint or ""
    quoted = shlex.quote(f"{user}@robot")
    verb = "ssh-copy-id " if known else "ssh "
    assert f"{verb}{quoted}" in hint or f"{verb}-p {ssh_home.sshd.port} {quoted}" in hint, hint
    done = pasted(f"printf '%s' {quoted}", ssh_home.home)
    assert done.stdout == f"{user}@robot" and not marker.exists(), done


def test_shell_path_keeps_the_tilde_and_quotes_the_rest(monkeypatch, tmp_path: Path):
    home = tmp_path / "home"
    monkeypatch.setenv("HOME", str(home))
    assert shell_path(str(home / ".ssh/known_hosts")) == "~/.ssh/known_hosts"
    odd = str(home / "my keys/$(id)")
    assert shell_path(odd) == "~/'my keys/$(id)'"
    assert pasted(f"printf %s {shell_path(odd)}", home).stdout == odd
    assert shell_path("/etc/ssh/known hosts") == "'/etc/ssh/known hosts'"
