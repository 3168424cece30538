"""Every bad connection or bad robot is one line on stderr naming the cause and the fix.

The real CLI in a subprocess against the real sshd (the robot): for each cause,
a non-zero exit code from ``fetchsync.errors``, exactly one line on stderr, no
traceback, the cause named and what to do about it. Causes that need a robot
configured differently (key exchange it cannot agree on, no python3 on PATH)
get a second sshd of their own, shared by the module, with the session sshd's
host key and authorized keys. Password logins use a throwaway account (root
only: useradd, chpasswd from stdin), removed at the end of the module, and a
pseudo-terminal for the prompt.
"""

from __future__ import annotations

import contextlib
import os
import pwd
import re
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Iterator

import pytest
from helpers import ssh_env, without_where
from sshd import SSHD, find_sshd, make_ssh_home
from terminal import Terminal

pytestmark = pytest.mark.ssh

CONNECT_EXIT = 3  # fetchsync.errors.TransportError
CONFIG_EXIT = 2  # fetchsync.errors.ConfigError
RUN_LINK_EXIT = 255  # fetchsync run: could not run the command (as ssh)
KEX_PARAMIKO_LACKS = "sntrup761x25519-sha512@openssh.com"


def old_python() -> str | None:
    """A Python older than 3.6 on this machine (the robot), if there is one: a python3.5 or
    3.4 on PATH, else one that pyenv installed (CI's pyenv has a 2.7, whose answer to the
    endpoint's version check is the same: too old)."""
    for candidate in ("python3.5", "python3.4"):
        found = shutil.which(candidate)
        if found:
            return found
    pyenv = shutil.which("pyenv")
    if pyenv is None:
        return None
    versions = Path(pyenv).resolve().parents[1] / "versions"
    for python in sorted(versions.glob("*/bin/python[23].[0-9]")):
        m = re.fullmatch(r"python(\d)\.(\d+)", python.name)
        if m and (int(m.group(1)), int(m.group(2))) < (3, 6) and os.access(python, os.X_OK):
            return str(python)
    return None


def cli(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    """The real CLI without a controlling terminal (as in CI): it must never prompt."""
    return subprocess.run(
        [sys.executable, "-m", "fetchsync", *args],
        check=False,
        capture_output=True,
        env=env,
        stdin=subprocess.DEVNULL,
        timeout=120,
        start_new_session=True,
    )


def one_line(proc: subprocess.CompletedProcess, code: int) -> str:
    """The single stderr line of a failed run, after checking the exit code."""
    err = proc.stderr.decode("utf-8", "replace")
    assert proc.returncode == code, f"exit {proc.returncode}, wanted {code}:\n{err}"
    assert "Traceback" not in err, err
    lines = without_where(err)  # the line saying where a push goes may precede it
    assert len(lines) == 1, f"wanted one line on stderr, got {len(lines)}:\n{err}"
    assert lines[0].startswith("fetchsync: error: "), lines[0]
    return lines[0]


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path) -> dict[str, str]:
    return ssh_env(ssh_home.home, str(remote_dir), tmp_path)


# -- a second robot, configured to fail --------------------------------------


@contextlib.contextmanager
def other_sshd(sshd: SSHD, workdir: Path, extra: list[str]) -> Iterator[int]:
    """An sshd like the session's (same host key, same keys) plus ``extra`` lines; its port."""
    sshd_path = find_sshd()
    assert sshd_path is not None
    workdir.mkdir(parents=True, exist_ok=True)
    with socket.socket() as s:
        s.bind((sshd.host, 0))
        port = s.getsockname()[1]
    base = (sshd.workdir / "sshd_config").read_text().splitlines()
    # first: for each keyword sshd keeps the first value it reads
    lines = [*extra, f"Port {port}", f"PidFile {workdir / 'sshd.pid'}"]
    lines += [line for line in base if not line.startswith(("Port ", "PidFile "))]
    config = workdir / "sshd_config"
    config.write_text("\n".join(lines) + "\n")
    log = open(workdir / "sshd.log", "ab")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(
        [sshd_path, "-D", "-e", "-f", str(config)],
        stdin=subprocess.DEVNULL,
        stdout=log,
        stderr=log,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 10
        while True:
            assert proc.poll() is None, (workdir / "sshd.log").read_text()
            with contextlib.suppress(OSError), socket.create_connection((sshd.host, port), 1) as c:
                if c.recv(8).startswith(b"SSH-"):
                    break
            assert time.monotonic() < deadline, "the second sshd did not come up"
            time.sleep(0.05)
        yield port
    finally:
        proc.terminate()
        proc.wait(5)
        log.close()


@pytest.fixture(scope="module")
def kex_robot(sshd: SSHD, tmp_path_factory) -> Iterator[int]:
    """A robot whose sshd allows only a key exchange paramiko does not implement."""
    import paramiko

    known = subprocess.run(["ssh", "-Q", "kex"], capture_output=True, text=True, check=False)
    if KEX_PARAMIKO_LACKS not in known.stdout.split():
        pytest.skip(f"this OpenSSH lacks {KEX_PARAMIKO_LACKS}")
    assert KEX_PARAMIKO_LACKS not in paramiko.Transport._preferred_kex  # else pick another
    with other_sshd(
        sshd, tmp_path_factory.mktemp("sshd-kex"), [f"KexAlgorithms {KEX_PARAMIKO_LACKS}"]
    ) as port:
        yield port


@pytest.fixture(scope="module")
def no_python_robot(sshd: SSHD, tmp_path_factory) -> Iterator[int]:
    """A robot where a login's PATH has a shell but no python3."""
    # outside pytest's private tmp: the robot's user must be able to reach it
    bin_dir = Path(tempfile.mkdtemp(prefix="fetchsync-no-python-"))
    try:
        bin_dir.chmod(0o755)
        for tool in ("sh", "bash", "env", "basename"):
            found = shutil.which(tool)
            if found:
                (bin_dir / tool).symlink_to(found)
        with other_sshd(
            sshd, tmp_path_factory.mktemp("sshd-nopy"), [f"SetEnv PATH={bin_dir}"]
        ) as port:
            yield port
    finally:
        shutil.rmtree(bin_dir, ignore_errors=True)


def home_for(sshd: SSHD, port: int, tmp_path: Path, name: str) -> Path:
    return make_ssh_home(tmp_path / name, sshd=sshd, port=port).home


# -- host keys ---------------------------------------------------------------


def test_unknown_host_key(env, ssh_home, remote_dir) -> None:
    ssh_home.known_hosts.write_text("")
    fp = ssh_home.sshd.host_key_fingerprint
    for verb in (["push"], ["pull", "--yes"]):
        line = one_line(cli(*verb, env=env), CONNECT_EXIT)
        assert "host key of robot" in line and "not known" in line
        assert f"--accept-host-key {fp}" in line and f"ssh -p {ssh_home.sshd.port}" in line
    line = one_line(cli("run", "true", env=env), RUN_LINK_EXIT)
    assert fp in line
    assert not (remote_dir / "src").exists()


def test_changed_host_key(env, ssh_home, remote_dir, tmp_path) -> None:
    other = tmp_path / "other_host_key"
    subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(other)], check=True)
    kind, blob = other.with_suffix(".pub").read_text().split()[:2]
    name = ssh_home.sshd.known_hosts_name
    ssh_home.known_hosts.write_text(f"{name} {kind} {blob}\n")
    # even the new key's fingerprint given to accept does not get past a changed key
    line = one_line(
        cli("push", "--accept-host-key", ssh_home.sshd.host_key_fingerprint, env=env), CONNECT_EXIT
    )
    assert "REMOTE HOST IDENTIFICATION HAS CHANGED" in line
    assert ssh_home.sshd.host_key_fingerprint in line
    assert f"ssh-keygen -R '{name}'" in line
    assert not (remote_dir / "src").exists()


def test_no_acceptable_key_exchange(kex_robot, sshd, remote_dir, tmp_path) -> None:
    env = ssh_env(home_for(sshd, kex_robot, tmp_path, "kex-home"), str(remote_dir), tmp_path)
    line = one_line(cli("push", env=env), CONNECT_EXIT)
    assert "no acceptable kex algorithm" in line
    assert f"it offers {KEX_PARAMIKO_LACKS};" in line  # theirs
    assert "curve25519-sha256" in line  # ours
    assert "to KexAlgorithms in the robot's sshd_config" in line


# -- authentication ----------------------------------------------------------


def test_key_refused(env, ssh_home, tmp_path) -> None:
    stranger = tmp_path / "stranger"
    subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(stranger)], check=True)
    shutil.copyfile(stranger, ssh_home.identity)
    user = ssh_home.sshd.user
    for verb in (["push"], ["pull", "--yes"]):
        line = one_line(cli(*verb, env=env), CONNECT_EXIT)
        assert f"permission denied for {user}@robot" in line and "~/.ssh/id_ed25519" in line
        # the fixture's robot also takes passwords; without a terminal none is asked
        assert "there is no terminal" in line
        assert f"ssh-copy-id {user}@robot" in line


@pytest.fixture(scope="module")
def keys_only_robot(sshd: SSHD, tmp_path_factory) -> Iterator[int]:
    """A robot whose sshd takes keys only, as many are set up."""
    with other_sshd(
        sshd,
        tmp_path_factory.mktemp("sshd-keys-only"),
        ["PasswordAuthentication no", "KbdInteractiveAuthentication no"],
    ) as port:
        yield port


def test_key_refused_by_a_robot_without_passwords(
    keys_only_robot, sshd, remote_dir, tmp_path
) -> None:
    home = make_ssh_home(tmp_path / "keys-home", sshd=sshd, port=keys_only_robot)
    subprocess.run(
        ["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(tmp_path / "k")], check=True
    )
    shutil.copyfile(tmp_path / "k", home.identity)
    env = ssh_env(home.home, str(remote_dir), tmp_path)
    # on a terminal too: no password prompt for a robot that would refuse any password
    term = Terminal(["push"], env)
    try:
        code = term.wait()
    finally:
        term.close()
    text = term.output.decode("utf-8", "replace")
    lines = without_where(text.replace("\r", ""))
    assert code == CONNECT_EXIT and len(lines) == 1, text
    assert "password" not in lines[0] and "terminal" not in lines[0]
    assert lines[0].startswith(f"fetchsync: error: permission denied for {sshd.user}@robot")
    assert f"ssh-copy-id {sshd.user}@robot installs your public key" in lines[0]


@pytest.fixture(scope="module")
def password_user(sshd: SSHD) -> Iterator[tuple[str, str]]:
    """A throwaway account on the robot: a password (PAM, as root only) and a plain /bin/sh.

    It also logs in with the fixture's key, from its own ~/.ssh/authorized_keys.
    """
    if os.geteuid() != 0 or not shutil.which("useradd") or not shutil.which("chpasswd"):
        pytest.skip("creating an account needs root, useradd and chpasswd")
    name = f"fspw{uuid.uuid4().hex[:8]}"
    password = secrets.token_urlsafe(12)
    subprocess.run(["useradd", "-m", "-s", "/bin/sh", name], check=True, capture_output=True)
    try:
        # on stdin: never a password in a command line
        subprocess.run(
            ["chpasswd"], input=f"{name}:{password}\n".encode(), check=True, capture_output=True
        )
        account = pwd.getpwnam(name)
        ssh_dir = Path(account.pw_dir) / ".ssh"
        ssh_dir.mkdir(mode=0o700)
        shutil.copyfile(sshd.client_key.with_suffix(".pub"), ssh_dir / "authorized_keys")
        for path in (ssh_dir, ssh_dir / "authorized_keys"):
            os.chown(path, account.pw_uid, account.pw_gid)
        yield name, password
    finally:
        subprocess.run(["userdel", "-f", "-r", name], check=False, capture_output=True)


@pytest.fixture
def password_env(sshd, password_user, tmp_path) -> dict[str, str]:
    home = make_ssh_home(tmp_path / "pw-home", sshd=sshd)
    home.identity.unlink()  # no key to offer: the robot wants the password
    env = ssh_env(home.home, "~/ws", tmp_path)
    env["FETCHSYNC_USER"] = password_user[0]
    return env


def test_password_without_a_terminal(password_env, password_user) -> None:
    line = one_line(cli("push", env=password_env), CONNECT_EXIT)
    assert f"permission denied for {password_user[0]}@robot" in line
    assert "asks for a password and there is no terminal" in line
    assert "run fetchsync in a terminal" in line and f"ssh-copy-id {password_user[0]}@robot" in line


def test_password_is_asked_on_the_terminal(password_env, password_user) -> None:
    name, password = password_user
    term = Terminal(["push"], password_env)
    try:
        term.read_until(f"{name}@robot's password: ".encode())
        term.send(password.encode() + b"\r")
        assert term.wait() == 0, term.output
    finally:
        term.close()
    assert password.encode() not in term.output  # not echoed
    assert (Path(pwd.getpwnam(name).pw_dir) / "ws/src/my_pkg/package.xml").exists()


def test_wrong_password(password_env, password_user) -> None:
    name, password = password_user
    prompt = f"{name}@robot's password: ".encode()
    term = Terminal(["push"], password_env)
    try:
        term.read_until(prompt)
        term.output = b""
        term.send(b"not-" + password.encode() + b"\r")
        # asked again, as ssh does; an empty answer gives up (each wrong one costs PAM's delay)
        term.read_until(b"Permission denied, please try again.")
        term.read_until(prompt)
        term.output = b""
        term.send(b"\r")
        code = term.wait()
    finally:
        term.close()
    text = term.output.decode("utf-8", "replace")
    assert code == CONNECT_EXIT, text
    lines = without_where(text.replace("\r", ""))
    assert "Traceback" not in text and len(lines) == 1, text
    assert lines[0].startswith(f"fetchsync: error: permission denied for {name}@robot")
    assert "wrong password (1 try" in lines[0] and "check the password" in lines[0]


# -- the robot's python --------------------------------------------------------


def test_no_python3_on_the_robot(no_python_robot, sshd, password_user, tmp_path) -> None:
    # the throwaway account: no shell startup file of its own puts python3 back on PATH
    env = ssh_env(home_for(sshd, no_python_robot, tmp_path, "nopy-home"), "~/ws", tmp_path)
    env["FETCHSYNC_USER"] = password_user[0]
    line = one_line(cli("push", env=env), CONNECT_EXIT)
    assert "python3 was not found on robot" in line and ">= 3.6" in line
    assert "install it (sudo apt install python3)" in line
    # run needs no python3 on the robot (it only loses the reaper)
    ran = cli("run", "echo", "ran", env=env)
    assert ran.returncode == 0 and ran.stdout == b"ran\n", ran


@pytest.mark.skipif(old_python() is None, reason="no Python older than 3.6 here")
def test_python3_too_old_on_the_robot(env) -> None:
    python = old_python()
    assert python is not None
    version = subprocess.run(
        [python, "-c", "import sys; print('%d.%d.%d' % sys.version_info[:3])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    env = dict(env, FETCHSYNC_REMOTE_PYTHON=python)
    line = one_line(cli("push", env=env), CONNECT_EXIT)
    assert f"python {version} on the robot is too old" in line and "python3 >= 3.6" in line
    assert "apt install python3" in line and "FETCHSYNC_REMOTE_PYTHON" in line


# -- the remote workspace -------------------------------------------------------


def test_remote_workspace_not_writable(env, remote_dir) -> None:
    if (
        os.geteuid() != 0
        or subprocess.run(
            ["chattr", "+i", str(remote_dir)], check=False, capture_output=True
        ).returncode
        != 0
    ):
        pytest.skip("chattr +i needs root and a file system that supports it")
    try:
        line = one_line(cli("push", env=env), 4)  # fetchsync.errors.RemoteError
        assert str(remote_dir) in line and "Operation not permitted" in line
        assert (
            "not writable" in line and f"check the permissions of {remote_dir} on the robot" in line
        )
    finally:
        subprocess.run(["chattr", "-i", str(remote_dir)], check=True)
    assert not (remote_dir / "src").exists()


@pytest.mark.parametrize("where", ["/", "//", "~", "~/", "~/."])
def test_whole_disk_or_home_as_remote_workspace(env, where) -> None:
    line = one_line(cli("push", "--remote-workspace", where, env=env), CONFIG_EXIT)
    assert f"remote workspace {where!r} (from --remote-workspace)" in line
    assert "that is the whole" in line and "pass --remote-workspace ~/DIR" in line


def test_fetch_remote_workspace_root(env) -> None:
    env = dict(env, FETCH_REMOTE_WORKSPACE="/")
    del env["FETCHSYNC_REMOTE_WORKSPACE"]
    for verb in (["push"], ["pull", "--yes"], ["run", "true"]):
        line = one_line(cli(*verb, env=env), CONFIG_EXIT)
        assert "(from FETCH_REMOTE_WORKSPACE)" in line and "whole file system" in line
