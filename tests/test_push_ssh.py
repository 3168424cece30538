"""push and pull over a real OpenSSH sshd: the product as users run it."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from helpers import fetchsync, report, ssh_env, tree_of, without_where

pytestmark = pytest.mark.ssh

PY38 = "/root/.pyenv/versions/3.8.18/bin/python3.8"


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    return ssh_env(ssh_home.home, remote_dir, tmp_path)


@pytest.mark.slow
def test_push_and_edit_and_pull_over_ssh(env, remote_dir):
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    r = report(fetchsync("push", "--json", env=env))
    assert r["ok"] and r["files"] == 5
    assert tree_of(local) == tree_of(remote_dir / "src")
    # one edit by delta, one rename by reuse, one delete, in one push
    data = local / "my_pkg/data.txt"
    data.write_text("// first line\n" + data.read_text())
    (local / "my_pkg/package.xml").rename(local / "my_pkg/package2.xml")
    (local / "my_pkg/src/node.cpp").unlink()
    r = report(fetchsync("push", "--json", env=env))
    assert (r["deltas"], r["reused"], r["deleted"]) == (1, 1, 2)
    assert tree_of(local) == tree_of(remote_dir / "src")
    (remote_dir / "src/my_pkg/from_robot.txt").write_text("robot\n")
    r = report(fetchsync("pull", "--json", "--yes", env=env))
    assert r["ok"] and (local / "my_pkg/from_robot.txt").read_text() == "robot\n"


def test_push_creates_a_missing_remote_workspace(env, remote_dir):
    target = remote_dir / "deeper" / "ws"
    env = dict(env, FETCHSYNC_REMOTE_WORKSPACE=str(target))
    fetchsync("push", env=env)
    assert (target / "src/my_pkg/package.xml").exists()


def test_tilde_remote_workspace_is_the_robots_home(env, tmp_path):
    name = f"fetchsync-test-{os.getpid()}-{tmp_path.name}"
    env = dict(env, FETCHSYNC_REMOTE_WORKSPACE=f"~/{name}")
    try:
        fetchsync("push", env=env)
        assert (Path(os.path.expanduser("~root")) / name / "src/my_pkg/package.xml").exists()
    finally:
        shutil.rmtree(Path(os.path.expanduser("~root")) / name, ignore_errors=True)


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists(PY38), reason="Python 3.8 not installed here")
def test_endpoint_runs_on_python_3_8(env, remote_dir):
    env = dict(env, FETCHSYNC_REMOTE_PYTHON=PY38)
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    fetchsync("push", env=env)
    data = local / "my_pkg/data.txt"
    data.write_text("x\n" + data.read_text())
    assert report(fetchsync("push", "--json", env=env))["deltas"] == 1
    assert tree_of(local) == tree_of(remote_dir / "src")


def test_unknown_host_key_is_refused_with_its_fingerprint(env, ssh_home, remote_dir):
    ssh_home.known_hosts.write_text("")
    proc = fetchsync("push", env=env, check=False)
    assert proc.returncode != 0
    err = proc.stderr.decode()
    assert ssh_home.sshd.host_key_fingerprint in err and "Traceback" not in err
    assert len(without_where(err)) == 1
    assert not (remote_dir / "src").exists()
    fetchsync("push", "--accept-host-key", ssh_home.sshd.host_key_fingerprint, env=env)
    assert (remote_dir / "src/my_pkg/package.xml").exists()


def test_missing_python_on_the_robot_is_a_clear_error(env):
    env = dict(env, FETCHSYNC_REMOTE_PYTHON="/nonexistent/python3")
    proc = fetchsync("push", env=env, check=False)
    assert proc.returncode == 3
    assert b"python3 was not found" in proc.stderr and b"Traceback" not in proc.stderr
