"""push --install-deps with the real rosdep on the sshd robot, offline.

The robot's environment (its workspace's install/setup.bash, sourced before
rosdep as for any command) points rosdep at a local sources list whose rule
maps the key ``fetchsync_test_dep`` to the Debian package
``fetchsync-test-dep``, built here with dpkg-deb into a local apt repository
that apt reaches through ``APT_CONFIG`` (the machine's own apt sources stay
untouched). As root (the tests' robot user) rosdep installs it for real; a
throwaway sudo user shows that the sudo password goes to ``sudo -S`` on stdin
and nowhere else.
"""

from __future__ import annotations

import hashlib
import os
import secrets
import shutil
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import fetchsync, ssh_env

pytestmark = [
    pytest.mark.ssh,
    pytest.mark.skipif(shutil.which("rosdep") is None, reason="rosdep not installed"),
    pytest.mark.skipif(
        os.geteuid() != 0 or shutil.which("dpkg-deb") is None or shutil.which("apt-get") is None,
        reason="installing a Debian package needs root, dpkg-deb and apt-get",
    ),
]

DEB = "fetchsync-test-dep"
PACKAGE_XML = """<?xml version="1.0"?>
<package format="3">
  <name>needs_dep</name>
  <version>0.0.1</version>
  <description>A package with a system dependency.</description>
  <maintainer email="dev@example.com">dev</maintainer>
  <license>BSD</license>
  <depend>fetchsync_test_dep</depend>
  <export><build_type>cmake</build_type></export>
</package>
"""


def _installed() -> bool:
    out = subprocess.run(
        ["dpkg-query", "-W", "-f=${Status}", DEB], capture_output=True, text=True, check=False
    )
    return out.returncode == 0 and out.stdout.endswith(" installed")


def _apt_repo(root: Path) -> Path:
    """A local apt repository holding the package; the apt.conf that uses only it."""
    pkg = root / "pkg"
    (pkg / "DEBIAN").mkdir(parents=True)
    (pkg / "DEBIAN/control").write_text(
        f"Package: {DEB}\nVersion: 1.0\nArchitecture: all\nMaintainer: dev <dev@example.com>\n"
        "Description: a package for fetchsync's rosdep test\n"
    )
    (pkg / f"usr/share/doc/{DEB}").mkdir(parents=True)
    (pkg / f"usr/share/doc/{DEB}/README").write_text("installed by fetchsync's tests\n")
    repo = root / "repo"
    repo.mkdir()
    deb = repo / f"{DEB}_1.0_all.deb"
    subprocess.run(["dpkg-deb", "--build", str(pkg), str(deb)], check=True, capture_output=True)
    data = deb.read_bytes()
    control = (pkg / "DEBIAN/control").read_text()
    (repo / "Packages").write_text(
        control + f"Filename: ./{deb.name}\nSize: {len(data)}\n"
        f"SHA256: {hashlib.sha256(data).hexdigest()}\n\n"
    )
    apt = root / "apt"
    for d in ("lists/partial", "cache/archives/partial", "parts"):
        (apt / d).mkdir(parents=True)
    (apt / "sources.list").write_text(f"deb [trusted=yes] file:{repo} ./\n")
    conf = apt / "apt.conf"
    conf.write_text(
        f'Dir::Etc::SourceList "{apt}/sources.list";\n'
        f'Dir::Etc::SourceParts "{apt}/parts";\n'
        f'Dir::State::Lists "{apt}/lists";\nDir::Cache "{apt}/cache";\n'
    )
    subprocess.run(
        ["apt-get", "update", "-q"],
        env=dict(os.environ, APT_CONFIG=str(conf)),
        check=True,
        capture_output=True,
    )
    return conf


def _rosdep_sources(root: Path) -> dict[str, str]:
    """Variables that point rosdep at a local rule and an empty distribution index."""
    root.mkdir(parents=True)
    (root / "rules.yaml").write_text(f"fetchsync_test_dep:\n  debian: [{DEB}]\n")
    (root / "sources").mkdir()
    (root / "sources/10-local.list").write_text(f"yaml file://{root}/rules.yaml\n")
    (root / "index.yaml").write_text("%YAML 1.1\n---\ndistributions: {}\ntype: index\nversion: 4\n")
    return {
        "ROSDEP_SOURCE_PATH": str(root / "sources"),
        "ROS_HOME": str(root / "ros-home"),
        "ROSDISTRO_INDEX_URL": f"file://{root}/index.yaml",
        "ROS_DISTRO": "noetic",
        "ROS_PYTHON_VERSION": "3",
    }


def _robot_environment(remote_ws: Path, variables: dict[str, str]) -> None:
    (remote_ws / "install").mkdir(parents=True, exist_ok=True)
    (remote_ws / "install/setup.bash").write_text(
        "".join(f"export {k}='{v}'\n" for k, v in variables.items())
    )


def _env(ssh_home, local_ws: Path, remote_ws: Path, tmp_path: Path) -> dict[str, str]:
    return ssh_env(
        ssh_home.home, remote_ws, tmp_path, make_ws=False, FETCHSYNC_WORKSPACE=str(local_ws)
    )


@pytest.fixture
def deps(tmp_path: Path) -> Iterator[dict[str, str]]:
    """rosdep's and apt's local sources; the package is removed before and after."""
    subprocess.run(["dpkg", "-r", DEB], capture_output=True, check=False)
    variables = _rosdep_sources(tmp_path / "rosdep")
    variables["APT_CONFIG"] = str(_apt_repo(tmp_path / "debs"))
    yield variables
    subprocess.run(["dpkg", "-r", DEB], capture_output=True, check=False)


def _workspace(root: Path) -> Path:
    (root / "src/needs_dep").mkdir(parents=True)
    (root / "src/needs_dep/package.xml").write_text(PACKAGE_XML)
    return root


def test_install_deps_installs_the_debian_package_with_the_real_rosdep(
    ssh_home, remote_dir, tmp_path, deps
):
    assert not _installed()
    local = _workspace(tmp_path / "ws")
    _robot_environment(remote_dir, deps)
    proc = fetchsync("push", "--install-deps", env=_env(ssh_home, local, remote_dir, tmp_path))
    out = proc.stdout.decode() + proc.stderr.decode()
    assert "rosdep install --from-paths src --ignore-src -y (on robot)" in out
    assert "#All required rosdeps installed successfully" in out, out
    assert _installed()
    assert (Path(deps["ROS_HOME"]) / "rosdep/sources.cache").is_dir()  # rosdep update ran


def test_a_robot_without_rosdep_is_one_clear_line(ssh_home, remote_dir, tmp_path):
    local = _workspace(tmp_path / "ws")
    # A PATH without rosdep (pip's is in pyenv, Debian's python3-rosdep2 in /usr/bin):
    # only the programs the probe uses besides rosdep.
    bin_dir = tmp_path / "robot-bin"
    bin_dir.mkdir()
    for program in ("id", "sudo"):
        (bin_dir / program).symlink_to(shutil.which(program, path="/usr/bin:/bin") or "/bin/false")
    _robot_environment(remote_dir, {"PATH": str(bin_dir)})
    proc = fetchsync(
        "push", "--install-deps", env=_env(ssh_home, local, remote_dir, tmp_path), check=False
    )
    err = proc.stderr.decode()
    assert proc.returncode == 127
    assert "fetchsync: error: rosdep is not installed on robot" in err, err
    assert "python3-rosdep" in err and "Traceback" not in err


# --------------------------------------------------------------------------- sudo
@pytest.fixture
def sudo_user(ssh_home) -> Iterator[tuple[str, str]]:
    """A throwaway robot account with a password and a sudoers entry: (name, password)."""
    if not all(shutil.which(t) for t in ("sudo", "useradd", "userdel", "chpasswd")):
        pytest.skip("needs sudo, useradd, userdel and chpasswd")
    name = f"fsdeps{os.getpid() % 100000}{secrets.randbelow(1000)}"
    password = "pw-" + secrets.token_urlsafe(12)
    sudoers = Path(f"/etc/sudoers.d/fetchsync-test-{name}")
    subprocess.run(["useradd", "-m", "-s", "/bin/bash", name], check=True, capture_output=True)
    try:
        subprocess.run(
            ["chpasswd"], input=f"{name}:{password}\n", text=True, check=True, capture_output=True
        )
        sudoers.write_text(f"{name} ALL=(ALL:ALL) ALL\n")
        sudoers.chmod(0o440)
        ssh_dir = Path(os.path.expanduser(f"~{name}")) / ".ssh"
        ssh_dir.mkdir(mode=0o700)
        shutil.copyfile(ssh_home.identity.with_suffix(".pub"), ssh_dir / "authorized_keys")
        subprocess.run(["chown", "-R", f"{name}:{name}", str(ssh_dir)], check=True)
        yield name, password
    finally:
        sudoers.unlink(missing_ok=True)
        subprocess.run(["userdel", "-r", "-f", name], check=False, capture_output=True)


def test_sudo_gets_the_password_on_stdin_only(ssh_home, tmp_path, sudo_user):
    name, password = sudo_user
    # the robot workspace of that user; rosdep is a stand-in there (pyenv's is root's only)
    remote = Path(f"/tmp/fsdeps-{name}")
    shutil.rmtree(remote, ignore_errors=True)
    (remote / "bin").mkdir(parents=True)
    log = remote / "rosdep.log"
    (remote / "bin/rosdep").write_text(
        f'#!/bin/sh\necho "rosdep $1 as $(id -u) home=$ROS_HOME stdin=$(cat)" >> {log}\n'
    )
    (remote / "bin/rosdep").chmod(0o755)
    _robot_environment(remote, {"PATH": f"{remote}/bin:/usr/bin:/bin"})
    subprocess.run(["chown", "-R", f"{name}:{name}", str(remote)], check=True)
    local = _workspace(tmp_path / "ws")
    env = _env(ssh_home, local, remote, tmp_path)
    env["FETCHSYNC_USER"] = name
    try:
        # no terminal and no password: one line saying what to do, nothing installed
        proc = fetchsync("push", "--install-deps", env=env, check=False)
        assert proc.returncode == 2, proc.stderr
        assert b"rosdep install needs sudo on robot" in proc.stderr
        assert b"FETCHSYNC_SUDO_PASSWORD" in proc.stderr
        assert not log.exists()
        seen: list[str] = []
        stop = threading.Event()

        def watch() -> None:
            while not stop.is_set():
                ps = subprocess.run(
                    ["ps", "-eo", "args"], capture_output=True, text=True, check=False
                ).stdout
                seen.extend(line for line in ps.splitlines() if password in line)
                stop.wait(0.02)

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        try:
            proc = fetchsync(
                "push", "--install-deps", env=dict(env, FETCHSYNC_SUDO_PASSWORD=password)
            )
        finally:
            stop.set()
            watcher.join()
        uid = subprocess.run(
            ["id", "-u", name], capture_output=True, text=True, check=True
        ).stdout.strip()
        home = Path(os.path.expanduser(f"~{name}"))
        assert log.read_text().splitlines() == [
            f"rosdep update as {uid} home= stdin=",
            f"rosdep install as 0 home={home}/.ros stdin=",  # root, reading the user's index
        ]
        assert seen == []
        assert password.encode() not in proc.stdout + proc.stderr
        # a wrong password: sudo's refusal and its exit status reach the user
        proc = fetchsync(
            "push", "--install-deps", env=dict(env, FETCHSYNC_SUDO_PASSWORD="nope"), check=False
        )
        assert proc.returncode != 0 and b"failed on robot" in proc.stderr
        assert len(log.read_text().splitlines()) == 3
    finally:
        shutil.rmtree(remote, ignore_errors=True)
