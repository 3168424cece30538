"""The watch agent end to end: live mirroring, status, flush, push through it, link loss."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import helpers
import pytest
from helpers import fetchsync, ssh_env, tree_of


def wait_for(cond, timeout=60.0, what="condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


class Watch:
    def __init__(self, env: dict, log: Path) -> None:
        self.env = env
        self.log = log
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "fetchsync", "watch"],
            env=env,
            stdout=open(log, "wb"),
            stderr=subprocess.STDOUT,
        )

    def status(self) -> dict:
        out = fetchsync("status", "--json", env=self.env, check=False)
        return json.loads(out.stdout) if out.stdout.strip() else {}

    def stop(self) -> float:
        t = time.monotonic()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return time.monotonic() - t


def same(local: Path, robot: Path) -> bool:
    try:
        return tree_of(local) == tree_of(robot)
    except OSError:
        return False


@pytest.fixture
def runtime():
    d = Path(tempfile.mkdtemp(prefix="fsw", dir="/tmp"))  # AF_UNIX paths are short
    d.chmod(0o700)
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def local_env(tmp_path: Path, runtime: Path) -> dict:
    """The agent's environment against the local robot."""
    return helpers.local_env(tmp_path, XDG_RUNTIME_DIR=str(runtime))


@pytest.fixture(params=["local", pytest.param("sshd", marks=pytest.mark.ssh)])
def robot_env(request, tmp_path: Path, runtime: Path) -> dict:
    """The agent's environment, against the local robot and against the real sshd."""
    if request.param == "local":
        return helpers.local_env(tmp_path, XDG_RUNTIME_DIR=str(runtime))
    home = request.getfixturevalue("ssh_home")
    remote = tmp_path / "robot-home" / "robot_ws"
    remote.parent.mkdir()
    return ssh_env(
        home.home,
        remote,
        tmp_path,
        XDG_RUNTIME_DIR=str(runtime),
        FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "robot-home"),
    )


@pytest.fixture
def watch(robot_env, tmp_path):
    w = Watch(robot_env, tmp_path / "watch.log")
    wait_for(lambda: w.status().get("state") == "live", what="the agent to be live")
    yield w
    w.stop()


def paths(env):
    return Path(env["FETCHSYNC_WORKSPACE"]) / "src", Path(
        env["FETCHSYNC_LOCAL_ROBOT_HOME"]
    ) / "robot_ws" / "src"


def test_changes_are_mirrored_as_they_happen(watch, robot_env):
    src, robot = paths(robot_env)
    assert same(src, robot)  # the start reconciles
    (src / "my_pkg/src/node.cpp").write_text("int main() { return 3; }\n")  # in place
    tmp = src / "my_pkg/.config.yaml.tmp"  # write temp, rename
    tmp.write_text("a: 1\n")
    tmp.rename(src / "my_pkg/config.yaml")
    (src / "my_pkg/scripts/run.py").chmod(0o700)  # chmod
    (src / "my_pkg/launch").rename(src / "my_pkg/launch2")  # move a directory
    (src / "my_pkg/link").symlink_to("package.xml")  # symlink
    (src / "my_pkg/CMakeLists.txt").unlink()  # delete
    wait_for(lambda: same(src, robot), what="the robot to match")
    assert not list(robot.rglob("*.tmp"))


def test_a_burst_of_files_arrives_whole(watch, robot_env):
    src, robot = paths(robot_env)
    (src / "burst").mkdir()
    for i in range(500):
        (src / "burst" / f"f{i}.txt").write_text(f"file {i}\n")
    wait_for(lambda: same(src, robot), 30, what="the burst to arrive")


def test_flush_returns_once_the_file_is_there(watch, robot_env):
    src, robot = paths(robot_env)
    f = src / "my_pkg/saved.txt"
    f.write_text("saved by an editor\n")
    fetchsync("flush", str(f), env=robot_env)
    assert (robot / "my_pkg/saved.txt").read_text() == "saved by an editor\n"
    fetchsync("flush", env=robot_env)  # no path: everything
    assert same(src, robot)


def test_status_push_and_a_second_agent(watch, robot_env):
    st = watch.status()
    assert (
        st["state"] == "live" and st["robot"] == robot_env["FETCHSYNC_ROBOT"] and st["pending"] == 0
    )
    out = fetchsync("push", "--json", env=robot_env)
    assert json.loads(out.stdout)["connection"] == "agent"
    second = fetchsync("watch", env=robot_env, check=False)
    assert second.returncode == 2
    assert b"already watching" in second.stderr and len(second.stderr.strip().splitlines()) == 1


def test_sigterm_stops_it_promptly_and_status_says_so(watch, robot_env):
    assert watch.stop() < 3.0
    out = fetchsync("status", "--json", env=robot_env, check=False)
    assert out.returncode == 3 and json.loads(out.stdout)["state"] == "stopped"


def test_flush_without_an_agent_pushes(local_env):
    src, robot = paths(local_env)
    fetchsync("flush", env=local_env)
    assert same(src, robot)


@pytest.mark.slow
@pytest.mark.ssh
def test_link_loss_is_survived(proxied_home, fault_proxy, remote_dir, tmp_path, runtime):
    e = ssh_env(proxied_home.home, remote_dir, tmp_path, XDG_RUNTIME_DIR=str(runtime))
    src, robot = tmp_path / "ws" / "src", remote_dir / "src"
    w = Watch(e, tmp_path / "watch.log")
    try:
        wait_for(lambda: w.status().get("state") == "live", 30, what="live")
        # the robot drives out of range: packets stop, no reset
        fault_proxy.blackhole()
        (src / "my_pkg/while_away.txt").write_text("written while offline\n")
        wait_for(lambda: w.status().get("state") == "offline", 30, what="offline to be noticed")
        assert w.status()["offline_since"]
        fault_proxy.pass_through()
        wait_for(lambda: same(src, robot), 40, what="the change to arrive after reconnecting")
        wait_for(lambda: w.status().get("state") == "live", 10, what="live again")
        # the robot reboots: connections end and new ones are refused for a while
        fault_proxy.cut()
        (src / "my_pkg/after_reboot.txt").write_text("written while rebooting\n")
        time.sleep(1.0)
        fault_proxy.pass_through()
        wait_for(lambda: same(src, robot), 40, what="the change to arrive after the reboot")
        assert w.proc.poll() is None  # same process, no user action
    finally:
        w.stop()
        print((tmp_path / "watch.log").read_text())
