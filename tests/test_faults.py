"""Link, process and disk faults during push and pull, end to end.

Each test breaks something real while a transfer is under way (the fault
proxy in front of the real sshd, a SIGKILL, a full tmpfs) and then checks two
things: the CLI failed with one clear line and no traceback, and the next
push or pull converges with no temporaries left behind.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import fetchsync, make_workspace, report, tree_of

pytestmark = pytest.mark.ssh

# Every fault must end a blocked CLI well within this (keepalives are 5 s).
FAULT_DEADLINE = 60


def temporaries(root: Path) -> list[str]:
    """Leftover temporaries of an interrupted write anywhere under ``root``."""
    out = []
    for dirpath, dirs, files in os.walk(root):
        for name in dirs + files:
            if "fetchsync-tmp" in name:
                out.append(os.path.join(dirpath, name))
    return out


def assert_one_line_failure(proc: subprocess.CompletedProcess | tuple[int, bytes]) -> str:
    code, err = (proc.returncode, proc.stderr) if not isinstance(proc, tuple) else proc
    text = err.decode("utf-8", "replace")
    assert code not in (0, None), text
    assert "Traceback" not in text, text
    lines = [line for line in text.strip().splitlines() if line.strip()]
    assert len(lines) == 1, text
    return lines[0]


def start(args: list[str], env: dict) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "fetchsync", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def finish(proc: subprocess.Popen, timeout: float = FAULT_DEADLINE) -> tuple[int, bytes]:
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        pytest.fail(f"fetchsync hung for {timeout} s after the fault:\n{err.decode()}")
    return proc.returncode, err


def wait_for(cond, timeout: float = 30, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.02)


def bulky_files(src: Path, *, count: int = 40, size: int = 64 * 1024) -> None:
    """Incompressible files, so a throttled link takes a while to carry them."""
    bulk = src / "bulk"
    bulk.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        (bulk / f"blob{i:03}.bin").write_bytes(os.urandom(size))


@pytest.fixture
def env(proxied_home, remote_dir, tmp_path):
    e = dict(os.environ)
    for k in ("FETCH_ROBOT", "FETCH_USER", "ROS_MASTER_URI", "FETCHSYNC_USER"):
        e.pop(k, None)
    e.update(HOME=str(proxied_home.home), FETCHSYNC_ROBOT="robot",
             FETCHSYNC_WORKSPACE=str(tmp_path / "ws"), FETCHSYNC_REMOTE_WORKSPACE=str(remote_dir),
             XDG_STATE_HOME=str(tmp_path / "state"))
    make_workspace(tmp_path / "ws")
    return e


def local_src(env: dict) -> Path:
    return Path(env["FETCHSYNC_WORKSPACE"]) / "src"


@pytest.mark.parametrize("fault", ["blackhole", "cut"])
def test_link_fault_mid_push_fails_cleanly_and_the_next_push_converges(env, fault_proxy,
                                                                       remote_dir, fault):
    bulky_files(local_src(env))
    fault_proxy.throttle(bytes_per_second=200_000)
    proc = start(["push"], env)
    wait_for(lambda: (remote_dir / "src").exists() or proc.poll() is not None, what="the push to start")
    time.sleep(0.5)
    getattr(fault_proxy, fault)()
    line = assert_one_line_failure(finish(proc))
    assert "robot" in line
    fault_proxy.throttle()
    fault_proxy.pass_through()
    fetchsync("push", env=env)
    assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
    assert temporaries(remote_dir) == []


@pytest.mark.parametrize("fault", ["blackhole", "cut"])
def test_link_fault_mid_pull_leaves_the_local_tree_consistent(env, fault_proxy, remote_dir, fault):
    fetchsync("push", env=env)
    before = tree_of(local_src(env))
    # robot-side content the pull must fetch, big enough to take a while throttled
    bulky_files(remote_dir / "src", count=40)
    fault_proxy.throttle(bytes_per_second=200_000)
    proc = start(["pull", "--yes"], env)
    time.sleep(1.5)
    getattr(fault_proxy, fault)()
    assert_one_line_failure(finish(proc))
    # whatever arrived is whole: every local file is either as before or the robot's
    after = tree_of(local_src(env))
    robot = tree_of(remote_dir / "src")
    for path, entry in after.items():
        assert entry == before.get(path) or entry == robot.get(path), path
    assert temporaries(local_src(env).parent) == []
    fault_proxy.throttle()
    fault_proxy.pass_through()
    fetchsync("pull", "--yes", env=env)
    assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
    assert temporaries(local_src(env).parent) == []


def test_slow_link_push_is_correct(env, fault_proxy, remote_dir):
    fault_proxy.throttle(bytes_per_second=400_000, latency=0.05)
    fetchsync("push", env=env)
    assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
    data = local_src(env) / "my_pkg/data.txt"
    data.write_text("// edited over a slow link\n" + data.read_text())
    (local_src(env) / "my_pkg/package.xml").rename(local_src(env) / "my_pkg/package2.xml")
    r = report(fetchsync("push", "--json", env=env))
    assert r["ok"] and r["deltas"] == 1
    assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
    assert temporaries(remote_dir) == []
