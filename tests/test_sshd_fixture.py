"""The real-sshd robot fixture works the way the product tests rely on."""

from __future__ import annotations

import os
import pwd
import subprocess
from pathlib import Path

import paramiko
import pytest
from sshd import SSHD, SSHHome, fingerprint

pytestmark = pytest.mark.ssh

_TIMEOUT = 20


def _run(argv: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        argv,
        check=False,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        timeout=_TIMEOUT,
    )


def _paramiko_client(sshd: SSHD, known_hosts: Path) -> paramiko.SSHClient:
    client = paramiko.SSHClient()
    client.load_host_keys(str(known_hosts))
    client.set_missing_host_key_policy(paramiko.RejectPolicy())
    return client


def test_openssh_client_runs_a_command(ssh_home: SSHHome) -> None:
    result = _run(ssh_home.ssh_argv("echo", "hello"))
    assert result.returncode == 0, result.stderr
    assert result.stdout == "hello\n"


def test_session_config_reaches_the_robot(sshd: SSHD) -> None:
    result = _run(sshd.ssh_argv("id", "-un"))
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == sshd.user


def test_robot_home_is_the_login_users_real_home(ssh_home: SSHHome) -> None:
    result = _run(ssh_home.ssh_argv('printf %s "$HOME"'))
    assert result.returncode == 0, result.stderr
    assert result.stdout == pwd.getpwnam(ssh_home.sshd.user).pw_dir
    assert result.stdout != str(ssh_home.home)


def test_rsync_copies_a_file_to_the_robot(
    ssh_home: SSHHome, remote_dir: Path, tmp_path: Path
) -> None:
    src = tmp_path / "src"
    (src / "pkg").mkdir(parents=True)
    (src / "pkg" / "CMakeLists.txt").write_bytes(b"project(pkg)\n" + bytes(range(256)))
    remote_shell = f"ssh -F {ssh_home.config} -o BatchMode=yes"
    result = _run(["rsync", "-a", "-e", remote_shell, f"{src}/", f"robot:{remote_dir}/src/"])
    assert result.returncode == 0, result.stderr
    copied = remote_dir / "src" / "pkg" / "CMakeLists.txt"
    assert copied.read_bytes() == (src / "pkg" / "CMakeLists.txt").read_bytes()


def test_paramiko_connects_with_the_client_key(sshd: SSHD) -> None:
    with _paramiko_client(sshd, sshd.known_hosts) as client:
        client.connect(
            sshd.host,
            port=sshd.port,
            username=sshd.user,
            key_filename=str(sshd.client_key),
            look_for_keys=False,
            allow_agent=False,
            timeout=_TIMEOUT,
        )
        _, stdout, _ = client.exec_command("echo $((6 * 7))", timeout=_TIMEOUT)
        assert stdout.read() == b"42\n"
        assert stdout.channel.recv_exit_status() == 0


def test_paramiko_reads_the_robot_from_home_ssh_config(ssh_home: SSHHome) -> None:
    assert os.environ["HOME"] == str(ssh_home.home)
    assert "SSH_AUTH_SOCK" not in os.environ
    config = paramiko.SSHConfig.from_path(os.path.expanduser("~/.ssh/config"))
    robot = config.lookup("robot")
    sshd = ssh_home.sshd
    assert robot["hostname"] == sshd.host
    assert int(robot["port"]) == sshd.port
    assert robot["user"] == sshd.user
    assert robot["identityfile"] == [str(ssh_home.identity)]
    assert robot["userknownhostsfile"] == str(ssh_home.known_hosts)
    assert robot["stricthostkeychecking"] == "yes"
    with _paramiko_client(sshd, Path(robot["userknownhostsfile"])) as client:
        client.connect(
            robot["hostname"],
            port=int(robot["port"]),
            username=robot["user"],
            key_filename=robot["identityfile"],
            look_for_keys=False,
            allow_agent=False,
            timeout=_TIMEOUT,
        )
        key = client.get_transport().get_remote_server_key()  # type: ignore[union-attr]
        assert f"{key.get_name()} {key.get_base64()}" == sshd.host_key_pub


def test_unknown_host_key_is_refused_by_ssh(ssh_home: SSHHome) -> None:
    ssh_home.known_hosts.write_text("")
    result = _run(ssh_home.ssh_argv("echo", "hello"))
    assert result.returncode == 255
    assert "hello" not in result.stdout
    assert "Host key verification failed" in result.stderr
    assert ssh_home.known_hosts.read_text() == ""


def test_changed_host_key_is_refused_by_ssh(ssh_home: SSHHome) -> None:
    # Another key under the robot's name, as after a reinstall or a MITM.
    other = ssh_home.home / "other_key"
    subprocess.run(
        ["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(other)],
        check=True,
        capture_output=True,
    )
    other_pub = " ".join(other.with_suffix(".pub").read_text().split()[:2])
    ssh_home.known_hosts.write_text(f"{ssh_home.sshd.known_hosts_name} {other_pub}\n")
    result = _run(ssh_home.ssh_argv("echo", "hello"))
    assert result.returncode == 255
    assert "hello" not in result.stdout
    assert "REMOTE HOST IDENTIFICATION HAS CHANGED" in result.stderr


def test_unknown_host_key_is_refused_by_paramiko(sshd: SSHD, tmp_path: Path) -> None:
    empty = tmp_path / "known_hosts"
    empty.write_text("")
    refused = pytest.raises(paramiko.SSHException, match="not found in known_hosts")
    with _paramiko_client(sshd, empty) as client, refused:
        client.connect(
            sshd.host,
            port=sshd.port,
            username=sshd.user,
            key_filename=str(sshd.client_key),
            look_for_keys=False,
            allow_agent=False,
            timeout=_TIMEOUT,
        )


def test_host_key_fingerprint_matches_ssh_keygen(sshd: SSHD) -> None:
    result = _run(["ssh-keygen", "-l", "-f", str(sshd.known_hosts)])
    assert result.returncode == 0, result.stderr
    assert sshd.host_key_fingerprint in result.stdout.split()
    assert fingerprint(sshd.host_key_pub) == sshd.host_key_fingerprint


def test_password_logins_are_offered(sshd: SSHD) -> None:
    # create-account tests log in with passwords; the server must offer them.
    transport = paramiko.Transport((sshd.host, sshd.port))
    try:
        transport.start_client(timeout=_TIMEOUT)
        with pytest.raises(paramiko.BadAuthenticationType) as exc_info:
            transport.auth_none(sshd.user)
        assert "password" in exc_info.value.allowed_types
        assert "publickey" in exc_info.value.allowed_types
    finally:
        transport.close()


def test_sshd_logs_the_logins(sshd: SSHD) -> None:
    result = _run(sshd.ssh_argv("true"))
    assert result.returncode == 0, result.stderr
    assert f"Accepted publickey for {sshd.user}" in sshd.log_text()


def test_remote_dir_is_fresh_and_absolute(remote_dir: Path) -> None:
    assert remote_dir.is_absolute()
    assert remote_dir.is_dir()
    assert list(remote_dir.iterdir()) == []
