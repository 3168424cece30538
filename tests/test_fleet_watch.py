"""``watch`` of several robots (issue 27) against the real sshd: one watcher, one agent per
robot. ``fetch1`` is the sshd; ``flaky`` is the same sshd behind a FaultProxy whose port is
closed at the start (a robot that is off) and opened later (the robot is back)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from helpers import fetchsync, ssh_env, tree_of
from test_watch import same, wait_for

pytestmark = pytest.mark.ssh

ROBOTS = ("fetch1", "flaky")


@pytest.fixture
def env(ssh_home, fault_proxy, tmp_path: Path):
    runtime = Path(tempfile.mkdtemp(prefix="fsf", dir="/tmp"))  # AF_UNIX paths are short
    runtime.chmod(0o700)
    config = ssh_home.config.read_text()
    block = config[config.index("Host robot") :]
    extra = block.replace("Host robot", "Host fetch1", 1)
    extra += block.replace("Host robot", "Host flaky", 1).replace(
        f"Port {ssh_home.sshd.port}", f"Port {fault_proxy.port}"
    )
    ssh_home.config.write_text(config + "\n" + extra)
    with ssh_home.known_hosts.open("a") as f:
        f.write(f"[127.0.0.1]:{fault_proxy.port} {ssh_home.sshd.host_key_pub}\n")
    conf = ssh_home.home / ".config/fetchsync"
    conf.mkdir(parents=True)
    (conf / "robots.toml").write_text(
        'pair = ["fetch1", "flaky"]\n\n'
        + "".join(
            f'[robots.{name}]\nremote_workspace = "{tmp_path / f"robot-{name}"}"\n\n'
            for name in ROBOTS
        )
    )
    e = ssh_env(ssh_home.home, tmp_path / "unused", tmp_path, XDG_RUNTIME_DIR=str(runtime))
    for k in ("FETCHSYNC_ROBOT", "FETCHSYNC_REMOTE_WORKSPACE", "XDG_CONFIG_HOME"):
        e.pop(k, None)
    yield e
    shutil.rmtree(runtime, ignore_errors=True)


def _status(env: dict, *args: str) -> tuple[int, list[dict]]:
    proc = fetchsync("status", "--json", *args, env=env, check=False)
    return proc.returncode, (json.loads(proc.stdout) if proc.stdout.strip() else [])


def test_a_fleet_watch_leaves_an_offline_robot_behind_and_catches_it_up(env, fault_proxy, tmp_path):
    src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    robot = {name: tmp_path / f"robot-{name}/src" for name in ROBOTS}
    fault_proxy.cut()  # flaky is off when the watch starts
    log = tmp_path / "watch.log"
    proc = subprocess.Popen(
        [sys.executable, "-m", "fetchsync", "watch", "--robot", "@pair"],
        env=env,
        stdout=open(log, "wb"),
        stderr=subprocess.STDOUT,
    )
    try:
        wait_for(lambda: same(src, robot["fetch1"]), 30, what="fetch1 to match")

        def states() -> dict[str, str]:
            _, sts = _status(env)  # no --robot: the fleet watch of this workspace
            return {st["robot"]: st["state"] for st in sts}

        wait_for(lambda: states() == {"fetch1": "live", "flaky": "offline"}, what="the states")
        out = fetchsync("status", env=env, check=False)
        assert out.returncode == 0, out.stderr.decode()
        lines = out.stdout.decode().splitlines()
        assert [line.split()[:2] for line in lines] == [
            ["[fetch1]", "live:"],
            ["[flaky]", "offline:"],
        ]
        assert "offline since" in lines[1] and "last error:" in lines[1]

        # saves reach the robot that is up; the one that is off does not hold them back
        saved = src / "my_pkg/saved.txt"
        saved.write_text("saved while flaky was off\n")
        flush = fetchsync("flush", str(saved), env=env, check=False)
        assert flush.returncode != 0  # flaky does not have it, and says so
        err = flush.stderr.decode()
        assert "[flaky] not on the robot yet: the robot is offline since" in err
        assert "[fetch1]" not in err
        assert (robot["fetch1"] / "my_pkg/saved.txt").read_text() == "saved while flaky was off\n"
        fetchsync("flush", "--robot", "fetch1", str(saved), env=env)  # one robot: it is there
        (src / "my_pkg/CMakeLists.txt").unlink()
        wait_for(lambda: same(src, robot["fetch1"]), what="fetch1 to follow")
        assert not robot["flaky"].exists()

        # flaky comes back and catches up by itself, with what it missed
        fault_proxy.pass_through()
        wait_for(lambda: same(src, robot["flaky"]), 60, what="flaky to catch up")
        wait_for(lambda: states() == {"fetch1": "live", "flaky": "live"}, what="both live")
        fetchsync("flush", env=env)  # every robot: both have everything
        (src / "my_pkg/after.txt").write_text("after\n")
        fetchsync("flush", "--robot", "fetch1,flaky", str(src / "my_pkg/after.txt"), env=env)
        for name in ROBOTS:
            assert (robot[name] / "my_pkg/after.txt").read_text() == "after\n"
        # each robot has its own agent: the single-robot verbs reach it
        code, st = _status(env, "--robot", "flaky")
        assert code == 0 and st["state"] == "live" and st["robot"] == "flaky"
        # a second fleet watch of the same workspace is refused in one line
        second = fetchsync("watch", "--robot", "fetch1,flaky", env=env, check=False)
        assert second.returncode == 2 and len(second.stderr.strip().splitlines()) == 1
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    text = log.read_text()
    assert "[flaky] offline:" in text and "[flaky] back online" in text, text
    assert proc.returncode == 0, text
    # stopped: the fleet named is said to have no agent
    code, sts = _status(env, "--robot", "@pair")
    assert code == 3 and [st["state"] for st in sts] == ["stopped", "stopped"]
    assert tree_of(robot["fetch1"]) == tree_of(src)


def test_a_service_watches_one_robot(env):
    proc = fetchsync("watch", "--robot", "@pair", "--install-service", env=env, check=False)
    assert proc.returncode == 2
    [line] = proc.stderr.decode().strip().splitlines()
    assert "install one per robot" in line
    assert os.path.exists(env["FETCHSYNC_WORKSPACE"])
