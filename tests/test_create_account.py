"""create-account: skeleton and key lookup, and real accounts made on the test robot.

The robot is this machine, so the SSH tests create real users (``fstest...``,
``fsadmin...``) and remove them, their homes and their sudoers files in
finalizers. They need root (to be root on the robot, and to clean up).
"""

from __future__ import annotations

import json
import os
import pwd
import secrets
import shutil
import subprocess
import sys
import threading
import zipfile
from pathlib import Path
from typing import Callable, Iterator

import paramiko
import pytest
from click.testing import CliRunner
from helpers import clean_env

from fetchsync.chores import account
from fetchsync.chores.account import (
    AccountRequest,
    builtin_skeleton,
    find_public_key,
    find_skeleton,
    load_skeleton,
    read_public_key,
)
from fetchsync.cli import cli
from fetchsync.errors import ConfigError, UsageError

REPO = Path(__file__).resolve().parent.parent
BUILTIN_FILES = {".bashrc.d/10-shell.sh", ".bashrc.d/40-ros.sh"}
PY38 = "/root/.pyenv/versions/3.8.18/bin/python3.8"
PY36 = "/root/.pyenv/versions/3.6.15/bin/python3.6"  # Ubuntu 18.04's, Fetch's Melodic image


# --- without a robot ------------------------------------------------------------------------


def _skeleton_dir(path: Path, marker: str) -> Path:
    path.mkdir(parents=True)
    (path / "initialize.sh").write_text(f"echo {marker}\n")
    return path


def test_skeleton_lookup_order(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    assert find_skeleton() == builtin_skeleton() == REPO / "skeleton"
    fetch = _skeleton_dir(home / ".fetch" / "robot_skeleton", "fetch")
    assert find_skeleton() == fetch
    ours = _skeleton_dir(home / ".fetchsync" / "robot_skeleton", "ours")
    assert find_skeleton() == ours
    given = _skeleton_dir(tmp_path / "given", "given")
    assert find_skeleton(str(given)) == given
    with pytest.raises(ConfigError):
        find_skeleton(str(tmp_path / "missing"))


def test_builtin_skeleton_has_bashrc_d_and_initialize() -> None:
    sk = load_skeleton(REPO / "skeleton")
    assert sk.init is not None and sk.init.startswith(b"#!/usr/bin/env bash")
    files = {f.path for f in sk.files if f.kind == "file"}
    assert files == BUILTIN_FILES
    assert ".bashrc.d" in {f.path for f in sk.files if f.kind == "dir"}


def test_installed_skeleton_is_found_under_the_data_prefix(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A non-editable install: the package sits in site-packages, no checkout
    # around it, and the wheel's data files went to <prefix>/share/fetchsync/.
    site_packages = tmp_path / "lib" / "site-packages"
    (site_packages / "fetchsync").mkdir(parents=True)
    monkeypatch.setattr(account, "__file__", str(site_packages / "fetchsync" / "account.py"))
    prefix = tmp_path / "prefix"
    monkeypatch.setattr(account.sysconfig, "get_path", lambda name, *a: str(prefix))
    monkeypatch.setattr(account.sys, "prefix", str(tmp_path / "nothing"))
    monkeypatch.setattr(account.sys, "base_prefix", str(tmp_path / "nothing"))
    monkeypatch.setattr(account.site, "USER_BASE", str(tmp_path / "nothing"), raising=False)
    assert builtin_skeleton() is None
    installed = prefix / "share" / "fetchsync" / "skeleton"
    shutil.copytree(REPO / "skeleton", installed)
    assert builtin_skeleton() == installed


def test_setuptools_installs_the_skeleton() -> None:
    # pyproject.toml's data-files put skeleton/ where builtin_skeleton() looks
    # after a non-editable install: <prefix>/share/fetchsync/skeleton.
    import warnings

    from setuptools.config.pyprojecttoml import apply_configuration
    from setuptools.dist import Distribution

    cwd = os.getcwd()
    os.chdir(REPO)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            dist = apply_configuration(Distribution(), REPO / "pyproject.toml")
    finally:
        os.chdir(cwd)
    installed = {
        f"{target}/{Path(src).name}" for target, sources in dist.data_files for src in sources
    }
    expected = {f"share/fetchsync/skeleton/{p}" for p in BUILTIN_FILES | {"initialize.sh"}}
    assert installed == expected


def test_wheel_ships_the_skeleton(tmp_path: Path) -> None:
    import importlib.util

    if (
        importlib.util.find_spec("wheel") is None
        and importlib.util.find_spec("setuptools.command.bdist_wheel") is None
    ):
        pytest.skip("no bdist_wheel here without fetching build dependencies")
    # Built from a copy, so the build leaves nothing in the working tree.
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    for name in ("fetchsync", "skeleton"):
        shutil.copytree(
            REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
        )
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "--disable-pip-version-check",
            "-w",
            str(tmp_path / "dist"),
            str(src),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    (wheel,) = (tmp_path / "dist").glob("fetchsync-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    data = {n.split(".data/data/", 1)[1] for n in names if ".data/data/" in n}
    expected = {f"share/fetchsync/skeleton/{p}" for p in BUILTIN_FILES | {"initialize.sh"}}
    assert expected <= data, names


def test_public_key_lookup(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HOME", str(tmp_path))
    ssh = tmp_path / ".ssh"
    ssh.mkdir()
    assert find_public_key() is None
    (ssh / "id_rsa.pub").write_text("ssh-rsa AAAAB3NzaC1yc2E= me@laptop\n")
    assert find_public_key() == ssh / "id_rsa.pub"
    (ssh / "id_ed25519.pub").write_text("ssh-ed25519 AAAAC3NzaC1lZDI1NTE5 me@laptop\n")
    assert find_public_key() == ssh / "id_ed25519.pub"
    (ssh / "other").write_text("-----BEGIN OPENSSH PRIVATE KEY-----\n")
    (ssh / "other.pub").write_text("ecdsa-sha2-nistp256 AAAAE2VjZHNh other\n")
    assert find_public_key(str(ssh / "other")) == ssh / "other.pub"
    assert read_public_key(ssh / "other.pub") == "ecdsa-sha2-nistp256 AAAAE2VjZHNh other"
    with pytest.raises(ConfigError):
        read_public_key(ssh / "other")
    with pytest.raises(ConfigError):
        find_public_key(str(ssh / "missing.pub"))


@pytest.mark.parametrize("name", ["Alice", "-rf", "a b", "a:b", "", "x" * 33, "../x"])
def test_bad_user_names_are_refused(name: str) -> None:
    with pytest.raises(UsageError):
        account.check_user_name(name)


@pytest.mark.parametrize("option", ["--password", "--fetch-password"])
def test_password_options_are_refused(option: str) -> None:
    result = CliRunner().invoke(
        cli, ["create-account", "--robot", "fetch7", "--user", "alice", option, "hunter2"]
    )
    assert result.exit_code == 2
    assert "command line" in result.output


def test_request_repr_hides_the_password() -> None:
    request = AccountRequest(
        user="alice",
        fullname="Alice",
        groups=(),
        key=None,
        skeleton=None,
        env={},
        password="hunter2",
    )
    assert "hunter2" not in repr(request)


def test_the_robot_program_runs_on_python_36() -> None:
    vermin = shutil.which("vermin")
    if vermin is None:
        pytest.skip("vermin not installed")
    proc = subprocess.run(
        [
            vermin,
            "-q",
            "--no-tips",
            "--violations",
            "--target=3.6-",
            str(REPO / "fetchsync" / "robot" / "account_robot.py"),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr


# --- on the test robot ----------------------------------------------------------------------

needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="creating accounts needs root")


@pytest.fixture
def accounts() -> Iterator[Callable[[str], str]]:
    """``accounts(prefix)`` -> a fresh user name, removed (with its home) afterwards."""
    names: list[str] = []

    def make(prefix: str) -> str:
        name = prefix + secrets.token_hex(4)
        names.append(name)
        return name

    yield make
    for name in names:
        subprocess.run(["userdel", "--remove", "--force", name], capture_output=True, check=False)
        Path("/etc/sudoers.d", name).unlink(missing_ok=True)


def _password() -> str:
    return "Pw-" + secrets.token_urlsafe(12) + ":x"


def _create(ssh_home, *args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    full_env = dict(
        os.environ,
        HOME=str(ssh_home.home),
        ROS_DISTRO="noetic",
        FETCHSYNC_REMOTE_WORKSPACE="~/fs_ws",
    )
    for name in (
        "SSH_AUTH_SOCK",
        "FETCHSYNC_NEW_PASSWORD",
        "FETCHSYNC_ADMIN_PASSWORD",
        "FETCHSYNC_ADMIN_USER",
    ):
        full_env.pop(name, None)
    full_env.update(env or {})
    return subprocess.run(
        [sys.executable, "-m", "fetchsync", "create-account", "--robot", "robot", "--json", *args],
        capture_output=True,
        text=True,
        env=full_env,
        stdin=subprocess.DEVNULL,
        timeout=60,
        cwd=REPO,
        check=False,
    )


def _report(proc: subprocess.CompletedProcess) -> dict:
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _password_login(sshd, user: str, password: str, command: str) -> str:
    client = paramiko.SSHClient()
    client.set_missing_host_key_policy(paramiko.AutoAddPolicy())
    client.connect(
        sshd.host,
        port=sshd.port,
        username=user,
        password=password,
        look_for_keys=False,
        allow_agent=False,
        timeout=10,
    )
    try:
        _stdin, stdout, _stderr = client.exec_command(command)
        return stdout.read().decode()
    finally:
        client.close()


def _existing_groups() -> set[str]:
    import grp

    present = set()
    for name in account.GROUPS:
        try:
            grp.getgrnam(name)
        except KeyError:
            continue
        present.add(name)
    return present


def _make_admin(
    accounts: Callable[[str], str], password: str, ssh_home, *, rule: str = "ALL=(ALL:ALL) ALL"
) -> str:
    """A user with sudo rights (that need its password); our key logs it in."""
    if shutil.which("sudo") is None:
        if os.environ.get("CI"):
            pytest.fail("sudo is not installed (.ci/run installs it)")
        pytest.skip("sudo not installed (apt-get install sudo)")
    name = accounts("fsadmin")
    subprocess.run(["useradd", "--create-home", "--shell", "/bin/bash", name], check=True)
    subprocess.run(["chpasswd"], input=f"{name}:{password}\n".encode(), check=True)
    # sshd reads authorized_keys as the user: the fixture's own file is root's only.
    entry = pwd.getpwnam(name)
    ssh_dir = Path(entry.pw_dir, ".ssh")
    ssh_dir.mkdir(mode=0o700)
    shutil.copy(ssh_home.ssh_dir / "id_ed25519.pub", ssh_dir / "authorized_keys")
    for path in (ssh_dir, ssh_dir / "authorized_keys"):
        os.chown(path, entry.pw_uid, entry.pw_gid)
    Path("/etc/sudoers.d").mkdir(exist_ok=True)
    sudoers = Path("/etc/sudoers.d", name)
    sudoers.write_text(f"{name} {rule}\n")
    sudoers.chmod(0o440)
    return name


@pytest.mark.ssh
@needs_root
def test_create_through_root_then_repair(sshd, ssh_home, accounts) -> None:
    name = accounts("fstest")
    password = _password()
    report = _report(
        _create(
            ssh_home,
            "--user",
            name,
            "--admin-user",
            "root",
            "--fullname",
            "Test User",
            env={"FETCHSYNC_NEW_PASSWORD": password},
        )
    )
    assert report["created"] and report["password_set"]
    assert report["initialize"] == "ran"
    entry = pwd.getpwnam(name)
    home = Path(entry.pw_dir)
    assert entry.pw_gecos.split(",")[0] == "Test User"

    # the new password logs in, and the account is in every listed group the robot has
    groups = set(_password_login(sshd, name, password, "id -Gn").split())
    assert _existing_groups() <= groups
    assert set(report["groups_absent"]) == set(account.GROUPS) - _existing_groups()

    our_key = (ssh_home.ssh_dir / "id_ed25519.pub").read_text().strip()
    keys = home / ".ssh" / "authorized_keys"
    assert keys.read_text().splitlines() == [our_key]
    assert keys.stat().st_uid == entry.pw_uid and keys.stat().st_mode & 0o777 == 0o600

    # the skeleton is there, the user's own, and initialize.sh did its work
    for rel in BUILTIN_FILES:
        assert (home / rel).is_file() and (home / rel).stat().st_uid == entry.pw_uid
    assert (home / ".fetchsync" / "initialized").is_file()
    assert (home / "fs_ws" / "src").is_dir()
    saved = (home / ".bashrc.d" / "30-workspace.sh").read_text()
    assert f"FETCH_WORKSPACE={home / 'fs_ws'}" in saved
    assert "fetchsync: read ~/.bashrc.d/*.sh" in (home / ".bashrc").read_text()

    # a re-run says so, repairs what is missing and keeps the password
    keys.unlink()
    (home / ".bashrc.d" / "10-shell.sh").unlink()
    (home / ".bashrc.d" / "40-ros.sh").write_text("# mine\n")
    proc = _create(ssh_home, "--user", name, "--admin-user", "root")
    report = _report(proc)
    assert not report["created"] and not report["password_set"]
    assert report["key"] == "added" and report["skeleton_added"] == [".bashrc.d/10-shell.sh"]
    assert report["initialize"] == "already" and report["groups_added"] == []
    assert keys.read_text().splitlines() == [our_key]
    assert (home / ".bashrc.d" / "40-ros.sh").read_text() == "# mine\n"
    assert _password_login(sshd, name, password, "echo ok").strip() == "ok"

    # and a third run adds nothing, no second key line
    report = _report(_create(ssh_home, "--user", name, "--admin-user", "root"))
    assert report["key"] == "present" and report["skeleton_added"] == []
    assert keys.read_text().splitlines() == [our_key]

    # --reset-password sets a new one
    new = _password()
    report = _report(
        _create(
            ssh_home,
            "--user",
            name,
            "--admin-user",
            "root",
            "--reset-password",
            env={"FETCHSYNC_NEW_PASSWORD": new},
        )
    )
    assert report["password_set"]
    assert _password_login(sshd, name, new, "echo ok").strip() == "ok"


@pytest.mark.ssh
@needs_root
def test_system_accounts_are_refused(sshd, ssh_home) -> None:
    proc = _create(ssh_home, "--user", "daemon", "--admin-user", "root")
    assert proc.returncode == 4
    assert "system account" in proc.stderr


@pytest.mark.slow
@pytest.mark.ssh
@needs_root
def test_create_through_sudo(sshd, ssh_home, accounts, tmp_path) -> None:
    admin_password = _password()
    admin = _make_admin(accounts, admin_password, ssh_home)
    name = accounts("fstest")

    # a wrong admin password stops before anything is changed
    proc = _create(
        ssh_home,
        "--user",
        name,
        "--admin-user",
        admin,
        env={
            "FETCHSYNC_NEW_PASSWORD": _password(),
            "FETCHSYNC_ADMIN_PASSWORD": "wrong-" + admin_password,
        },
    )
    assert proc.returncode == 3, proc.stderr
    assert "sudo refused the password" in proc.stderr
    with pytest.raises(KeyError):
        pwd.getpwnam(name)

    # a skeleton of our own, whose initialize.sh leaves a marker
    skeleton = tmp_path / "skel"
    (skeleton / "bin").mkdir(parents=True)
    (skeleton / "bin" / "hello").write_text("#!/bin/sh\necho hello\n")
    (skeleton / "bin" / "hello").chmod(0o755)
    (skeleton / "initialize.sh").write_text(
        'printf "%s %s %s\\n" "$(id -un)" "$PWD" "$FETCH_WORKSPACE" > init-marker\n'
    )
    password = _password()
    env = {"FETCHSYNC_NEW_PASSWORD": password, "FETCHSYNC_ADMIN_PASSWORD": admin_password}
    if os.path.exists(PY38):  # the robot side runs on an Ubuntu 20.04 robot's Python too
        env["FETCHSYNC_REMOTE_PYTHON"] = PY38
    report = _report(
        _create(
            ssh_home, "--user", name, "--admin-user", admin, "--skeleton", str(skeleton), env=env
        )
    )
    assert report["created"] and report["initialize"] == "ran"
    home = Path(pwd.getpwnam(name).pw_dir)
    # FETCH_WORKSPACE expanded, as fetch_tools handed it (its scripts use it unquoted)
    assert (home / "init-marker").read_text().split() == [name, str(home), str(home / "fs_ws")]
    assert (home / "bin" / "hello").stat().st_mode & 0o777 == 0o755
    assert _password_login(sshd, name, password, "bin/hello").strip() == "hello"
    assert _existing_groups() <= set(_password_login(sshd, name, password, "id -Gn").split())

    # an admin without our key logs in with the same password it gives sudo
    Path(pwd.getpwnam(admin).pw_dir, ".ssh", "authorized_keys").unlink()
    other, other_password = accounts("fstest"), _password()
    env["FETCHSYNC_NEW_PASSWORD"] = other_password
    report = _report(
        _create(
            ssh_home, "--user", other, "--admin-user", admin, "--skeleton", str(skeleton), env=env
        )
    )
    assert report["created"]
    assert _password_login(sshd, other, other_password, "echo ok").strip() == "ok"


@pytest.mark.ssh
@needs_root
def test_create_through_sudo_without_password(sshd, ssh_home, accounts) -> None:
    # NOPASSWD sudo and a key login: no admin password is asked for at all
    admin = _make_admin(accounts, _password(), ssh_home, rule="ALL=(ALL:ALL) NOPASSWD: ALL")
    name, password = accounts("fstest"), _password()
    report = _report(
        _create(
            ssh_home,
            "--user",
            name,
            "--admin-user",
            admin,
            env={"FETCHSYNC_NEW_PASSWORD": password},
        )
    )
    assert report["created"] and report["initialize"] == "ran"
    assert _password_login(sshd, name, password, "echo ok").strip() == "ok"


@pytest.mark.ssh
@needs_root
def test_passwords_never_on_a_command_line(sshd, ssh_home, accounts, tmp_path) -> None:
    admin_password = _password()
    admin = _make_admin(accounts, admin_password, ssh_home)
    name = accounts("fstest")
    password = _password()
    skeleton = tmp_path / "skel"
    skeleton.mkdir()
    # keeps the robot side alive a while, for the poller to see it
    (skeleton / "initialize.sh").write_text("sleep 1\n")

    seen: set[str] = set()
    done = threading.Event()

    def poll() -> None:
        while not done.is_set():
            out = subprocess.run(
                ["ps", "-eo", "args"], capture_output=True, text=True, check=False
            ).stdout
            seen.update(out.splitlines())

    poller = threading.Thread(target=poll, daemon=True)
    poller.start()
    try:
        proc = _create(
            ssh_home,
            "--user",
            name,
            "--admin-user",
            admin,
            "--skeleton",
            str(skeleton),
            env={"FETCHSYNC_NEW_PASSWORD": password, "FETCHSYNC_ADMIN_PASSWORD": admin_password},
        )
    finally:
        done.set()
        poller.join(timeout=10)
    assert _report(proc)["created"]
    # the poller did watch the run: it saw the robot side's bootstrap under sudo
    assert any(line.startswith("sudo -k -S") and "python3 -c" in line for line in seen)
    for secret in (password, admin_password):
        assert not [line for line in seen if secret in line]
        assert secret not in proc.stdout + proc.stderr
        assert secret not in sshd.log_text()


# --- fetch_tools' defaults and push's workspace -----------------------------------------------

_TARGET_VARS = (
    "FETCHSYNC_USER",
    "FETCH_USER",
    "ROS_DISTRO",
    "FETCHSYNC_WORKSPACE",
    "FETCH_WORKSPACE",
    "FETCHSYNC_REMOTE_WORKSPACE",
    "FETCH_REMOTE_WORKSPACE",
    "ROS_MASTER_URI",
    "FETCHSYNC_ROBOT",
    "FETCH_ROBOT",
)


def _create_as_user(
    ssh_home, *args: str, env: dict[str, str], started: Callable[[int], None] | None = None
) -> subprocess.CompletedProcess:
    """create-account as a fetch_tools user runs it: no --user, the environment decides.
    ``started`` is given the laptop process's pid."""
    full_env = clean_env(HOME=str(ssh_home.home), FETCHSYNC_ADMIN_USER="root", **env)
    argv = [
        sys.executable,
        "-m",
        "fetchsync",
        "create-account",
        "--robot",
        "robot",
        "--json",
        *args,
    ]
    with subprocess.Popen(
        argv,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=full_env,
        stdin=subprocess.DEVNULL,
        cwd=REPO,
    ) as proc:
        if started is not None:
            started(proc.pid)
        out, err = proc.communicate(timeout=60)
    return subprocess.CompletedProcess(argv, proc.returncode, out, err)


def _push_remote_workspace(ssh_home, env: dict[str, str], workspace: str | None = None) -> str:
    """What push resolves as the remote workspace in this environment."""
    code = (
        "import sys; from fetchsync.cli.common import resolve; "
        "print(resolve('robot', None, sys.argv[1] or None, None).remote_workspace)"
    )
    full_env = {k: v for k, v in os.environ.items() if k not in _TARGET_VARS}
    full_env.update(HOME=str(ssh_home.home), **env)
    proc = subprocess.run(
        [sys.executable, "-c", code, workspace or ""],
        capture_output=True,
        text=True,
        env=full_env,
        cwd=REPO,
        check=True,
    )
    return proc.stdout.strip()


@pytest.mark.ssh
@needs_root
def test_user_defaults_to_fetch_user_then_user(sshd, ssh_home, accounts) -> None:
    name, other = accounts("fstest"), accounts("fstest")
    report = _report(
        _create_as_user(
            ssh_home,
            "--fullname",
            "Not A. Robot",
            env={"FETCH_USER": name, "USER": "nobody-else", "FETCHSYNC_NEW_PASSWORD": _password()},
        )
    )
    assert report["user"] == name and report["created"]
    assert pwd.getpwnam(name).pw_gecos.split(",")[0] == "Not A. Robot"
    report = _report(
        _create_as_user(ssh_home, env={"USER": other, "FETCHSYNC_NEW_PASSWORD": _password()})
    )
    assert report["user"] == other and report["created"]


@pytest.mark.slow
@pytest.mark.ssh
@needs_root
def test_workspace_is_pushs_and_a_rerun_fixes_a_wrong_one(sshd, ssh_home, accounts) -> None:
    name = accounts("fstest")

    def saved() -> dict[str, str]:
        return account_robot_exports(Path(pwd.getpwnam(name).pw_dir))

    # Before ROS is sourced nothing resolves here: initialize.sh picks (~/catkin_ws, no ROS)
    report = _report(
        _create_as_user(ssh_home, env={"FETCH_USER": name, "FETCHSYNC_NEW_PASSWORD": _password()})
    )
    home = Path(pwd.getpwnam(name).pw_dir)
    assert report["workspace_record"] == "initialize.sh"
    assert saved()["FETCH_WORKSPACE"] == f"{home}/catkin_ws"

    # With ROS sourced, push goes to ~/noetic: a second run records that, saying what it was
    env = {"FETCH_USER": name, "ROS_DISTRO": "noetic"}
    assert _push_remote_workspace(ssh_home, env) == "~/noetic"
    proc = _create_as_user(ssh_home, env=env)
    report = _report(proc)
    assert (report["workspace"], report["workspace_record"]) == ("~/noetic", "updated")
    assert proc.stderr.splitlines()[0] == f"create-account {name}@robot:~/noetic"
    assert report["workspace_was"] == f"{home}/catkin_ws"
    assert saved() == {"ROS_DISTRO": "noetic", "FETCH_WORKSPACE": f"{home}/noetic"}
    # ... and the account's shells see it
    shell = subprocess.run(
        ["su", "-", name, "-c", "bash -ic 'echo \"$FETCH_WORKSPACE\"' 2>/dev/null"],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert shell.stdout.strip().splitlines()[-1] == f"{home}/noetic"

    # fetch_tools' --workspace, resolved as push resolves it; the same again keeps it
    laptop_ws = str(ssh_home.home / "robots_ws")
    assert _push_remote_workspace(ssh_home, env, laptop_ws) == "~/robots_ws"
    report = _report(_create_as_user(ssh_home, "--workspace", laptop_ws, env=env))
    assert (
        report["workspace"] == "~/robots_ws" and saved()["FETCH_WORKSPACE"] == f"{home}/robots_ws"
    )
    report = _report(_create_as_user(ssh_home, "--workspace", laptop_ws, env=env))
    assert report["workspace_record"] == "kept"

    # a file the user wrote is theirs: left alone, and said so
    (home / ".bashrc.d" / "30-workspace.sh").write_text("export FETCH_WORKSPACE=~/mine\n")
    report = _report(_create_as_user(ssh_home, env=env))
    assert report["workspace_record"] == "yours"
    assert (home / ".bashrc.d" / "30-workspace.sh").read_text() == "export FETCH_WORKSPACE=~/mine\n"


def account_robot_exports(home: Path) -> dict[str, str]:
    from fetchsync.robot.account_robot import read_exports

    return read_exports(str(home / ".bashrc.d" / "30-workspace.sh"))


def test_create_account_help_shows_fetch_tools_defaults() -> None:
    result = CliRunner().invoke(cli, ["create-account", "--help"])
    assert result.exit_code == 0
    assert "$FETCH_USER, $USER" in result.output and "--workspace" in result.output


# --- fetch_tools' own skeleton: its ROS set-up and a working sudo ----------------------------

FETCH_TOOLS_BASHRC = """# ~/.bashrc: fetch_tools' skeleton
if [ -d $HOME/.bashrc.d ]; then
  for file in $HOME/.bashrc.d/*.sh; do
    source $file
  done
fi
"""

# As fetch_tools' own initialize.sh: $FETCH_WORKSPACE unquoted, sudo without -S.
LEGACY_INIT = """mkdir -p $FETCH_WORKSPACE/src &&
mkdir -p $FETCH_WORKSPACE/devel &&
echo 'export LEGACY_MARK=sourced-by-40-ros-setup' > $FETCH_WORKSPACE/devel/setup.bash
sudo -n true && echo ok > ~/sudo-n
sudo whoami > ~/sudo-whoami
sudo sh -c 'id -u; sleep 1' > ~/sudo-slow
"""


def _watch_proc(
    secret: bytes, done: threading.Event, seen: list[str], looked: list[int], allowed: set[int]
) -> None:
    """Read every process's cmdline and environ until ``done``; note where ``secret`` is.
    Processes in ``allowed`` are skipped (the test's own, given the secret in its environment)."""
    while not done.is_set():
        for entry in os.scandir("/proc"):
            if not entry.name.isdigit() or int(entry.name) in allowed:
                continue
            for what in ("cmdline", "environ"):
                try:
                    with open(f"/proc/{entry.name}/{what}", "rb") as f:
                        data = f.read()
                except OSError:
                    continue
                looked.append(1)
                if secret in data:
                    seen.append(f"{entry.name} {what}")


@pytest.mark.ssh
@needs_root
@pytest.mark.parametrize("remote_python", [None, PY36], ids=["python3", "python3.6"])
def test_fetch_tools_skeleton_gets_its_ros_setup_and_a_working_sudo(
    sshd, ssh_home, accounts, remote_python
) -> None:
    # On Python 3.6 (no os.memfd_create) the password goes in an unlinked temporary file.
    if remote_python is not None and not os.path.exists(remote_python):
        if os.environ.get("CI"):
            pytest.fail(f"{remote_python} is missing (the test machines have it under pyenv)")
        pytest.skip(f"{remote_python} not installed")
    if shutil.which("sudo") is None:
        pytest.skip("sudo not installed (apt-get install sudo)")
    import grp

    try:
        grp.getgrnam("sudo")
    except KeyError:
        pytest.skip("no sudo group on this machine")
    name, password = accounts("fstest"), _password()
    skeleton = ssh_home.home / ".fetch" / "robot_skeleton"
    skeleton.mkdir(parents=True)
    (skeleton / ".bashrc").write_text(FETCH_TOOLS_BASHRC)
    (skeleton / "initialize.sh").write_text(LEGACY_INIT)

    seen: list[str] = []
    looked: list[int] = []
    done = threading.Event()
    # The laptop process was handed the password in FETCHSYNC_NEW_PASSWORD: that one may hold
    # it; its children (none expected) and every process on the robot side may not.
    allowed = {os.getpid()}
    watcher = threading.Thread(
        target=_watch_proc, args=(password.encode(), done, seen, looked, allowed), daemon=True
    )
    watcher.start()
    try:
        env = {"FETCH_USER": name, "ROS_DISTRO": "noetic", "FETCHSYNC_NEW_PASSWORD": password}
        if remote_python is not None:
            env["FETCHSYNC_REMOTE_PYTHON"] = remote_python
        proc = _create_as_user(ssh_home, "--fullname", "Not A. Robot", env=env, started=allowed.add)
    finally:
        done.set()
        watcher.join(timeout=30)
    # (a scan may have caught the laptop process before its pid was allowed)
    seen = [where for where in seen if int(where.split()[0]) not in allowed]
    report = _report(proc)
    home = Path(pwd.getpwnam(name).pw_dir)
    assert report["created"] and report["initialize"] == "ran", proc.stderr

    # sudo in initialize.sh worked, non-interactively too, without a terminal
    assert (home / "sudo-n").read_text() == "ok\n"
    assert (home / "sudo-whoami").read_text() == "root\n"
    assert (home / "sudo-slow").read_text() == "0\n"
    # ... and the password was in no process's command line or environment, nor any output
    assert looked and seen == []
    assert password not in proc.stdout + proc.stderr
    assert password not in sshd.log_text()
    assert not list((home / ".fetchsync").glob("sudo-*")), "the sudo wrapper is removed"

    # fetch_tools' ROS set-up, for the workspace push uses, read by the account's shells
    setup = (home / ".bashrc.d" / "40-ros-setup.sh").read_text()
    assert "source /opt/ros/noetic/setup.bash" in setup
    assert f"source {home}/noetic/devel/setup.bash" in setup
    assert (report["workspace"], report["workspace_file"]) == (
        "~/noetic",
        ".bashrc.d/40-ros-setup.sh",
    )
    assert (home / "noetic" / "src").is_dir()  # $FETCH_WORKSPACE arrived expanded
    shell = subprocess.run(
        ["su", "-", name, "-c", "bash -ic 'echo \"$LEGACY_MARK\"' 2>/dev/null"],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert shell.stdout.strip().splitlines()[-1] == "sourced-by-40-ros-setup"


def test_a_workspace_file_that_is_a_link_or_fifo_is_left_to_the_user(tmp_path, monkeypatch) -> None:
    from fetchsync.robot import account_robot

    monkeypatch.chdir(tmp_path)
    (tmp_path / ".bashrc.d").mkdir()
    entry = pwd.getpwuid(os.getuid())
    request = {"workspace": "~/noetic", "env": {"ROS_DISTRO": "noetic"}}
    os.mkfifo(tmp_path / ".bashrc.d" / "30-workspace.sh")  # a read would block forever
    import signal

    signal.alarm(20)  # so that a regression fails instead of hanging the suite
    try:
        assert account_robot.record_workspace(entry, request)["workspace_record"] == "yours"
    finally:
        signal.alarm(0)
    (tmp_path / ".bashrc.d" / "30-workspace.sh").unlink()
    (tmp_path / "elsewhere").write_text("# Written by fetchsync create-account\n")
    (tmp_path / ".bashrc.d" / "30-workspace.sh").symlink_to(tmp_path / "elsewhere")
    assert account_robot.record_workspace(entry, request)["workspace_record"] == "yours"
    assert (tmp_path / "elsewhere").read_text() == "# Written by fetchsync create-account\n"
    (tmp_path / ".bashrc.d" / "30-workspace.sh").unlink()
    result = account_robot.record_workspace(entry, request)
    assert (result["workspace_record"], result["workspace"]) == ("written", "~/noetic")
    assert account_robot.read_exports(".bashrc.d/30-workspace.sh") == {
        "ROS_DISTRO": "noetic",
        "FETCH_WORKSPACE": f"{entry.pw_dir}/noetic",
    }
