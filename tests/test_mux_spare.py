"""The connection master's one spare endpoint (issue 22 items 9 and 21, issue 23 item 1).

The master keeps one robot endpoint started and waiting after its hello, so a push
through it does not wait for sshd's session start, the robot's Python and the loader.
These tests hold what the spare must not cost: a spare that died is replaced within
the call that finds it dead, and a spare opens nothing before the client asks, so the
endpoint's checks at open hold for it as for a fresh one.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
import time
import uuid
from pathlib import Path

import pytest
from helpers import fetchsync, report, ssh_env, tree_of

pytestmark = pytest.mark.ssh


def masters(runtime: Path) -> list[int]:
    out = subprocess.run(
        ["pgrep", "-f", f"fetchsync.link.mux.*{runtime}"], check=False, capture_output=True
    )
    return [int(x) for x in out.stdout.split()]


def serving(runtime: Path) -> bool:
    return bool(masters(runtime)) and any((runtime / "fetchsync").glob("mux-*.sock"))


def wait_for(cond, timeout=60.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.1)
    return False


def robot_endpoints(mark: str) -> list[int]:
    """The robot-side Python processes started with this test's marked interpreter."""
    out = subprocess.run(
        ["pgrep", "-f", f"^[^ ]*python3 -X fsmark={mark} "], check=False, capture_output=True
    )
    return [int(p) for p in out.stdout.split()]


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    runtime = Path(tempfile.mkdtemp(prefix="fsrun", dir="/tmp"))  # short: AF_UNIX path limit
    mark = uuid.uuid4().hex[:12]
    yield ssh_env(
        ssh_home.home,
        remote_dir,
        tmp_path,
        FETCHSYNC_PERSIST="60",
        XDG_RUNTIME_DIR=str(runtime),
        FETCHSYNC_MUX_LOG=str(tmp_path / "mux.log"),
        FETCHSYNC_REMOTE_PYTHON=f"python3 -X fsmark={mark}",
        FSMARK=mark,
    )
    for pid in masters(runtime):
        os.kill(pid, signal.SIGTERM)
    shutil.rmtree(runtime, ignore_errors=True)


def spare_ready(env: dict[str, str]) -> list[int]:
    """Push once so a master is left behind, and wait until its spare endpoint runs
    (the only marked endpoint once no call is running); its pids."""
    runtime = Path(env["XDG_RUNTIME_DIR"])
    if not serving(runtime):
        assert report(fetchsync("push", "--json", env=env))["connection"] == "ssh"
        assert wait_for(lambda: serving(runtime))
    seen: list[list[int]] = []

    def one_settled() -> bool:
        # the robot's python3 may be a shim (pyenv) that forks on its way to Python
        seen.append(robot_endpoints(env["FSMARK"]))
        return len(seen) >= 10 and len(seen[-1]) == 1 and all(p == seen[-1] for p in seen[-10:])

    ok = wait_for(one_settled)
    assert ok, (
        seen[-3:],
        [
            ln[:160]
            for ln in subprocess.run(
                ["ps", "-eo", "pid,ppid,args"], capture_output=True, text=True
            ).stdout.splitlines()
            if env["FSMARK"] in ln
        ],
    )
    return seen[-1]


def mux_log(env: dict[str, str]) -> str:
    return Path(env["FETCHSYNC_MUX_LOG"]).read_text()


@pytest.mark.slow
def test_a_push_through_the_master_takes_its_spare_which_had_opened_nothing(env, remote_dir):
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    (pid,) = spare_ready(env)
    # the spare waits after its hello: no file of the robot's workspace is open
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        assert not target.startswith(str(remote_dir)), target
    (local / "my_pkg" / "spare.txt").write_text("through the spare\n")
    r = report(fetchsync("push", "--json", env=env))
    assert r["connection"] == "master" and r["ok"]
    assert mux_log(env).count("took the spare endpoint") == 1
    assert tree_of(local) == tree_of(remote_dir / "src")
    # and the master started the next spare
    assert spare_ready(env) != [pid]


@pytest.mark.slow
def test_a_killed_spare_does_not_fail_the_next_push(env, remote_dir):
    """A spare whose robot-side process died (killed, OOM, the robot's Python gone) is
    noticed when a push takes it and replaced by a fresh start in that same push."""
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    for i in range(2):
        pids = spare_ready(env)
        for pid in pids:
            os.kill(pid, signal.SIGKILL)
        assert wait_for(lambda pids=pids: not set(pids) & set(robot_endpoints(env["FSMARK"])))
        time.sleep(0.5)  # sshd has reported the exit to the master
        (local / "my_pkg" / f"after_kill{i}.txt").write_text(f"{i}\n")
        proc = fetchsync("push", "--json", env=env, check=False)
        assert proc.returncode == 0, proc.stderr.decode()
        r = report(proc)
        assert r["connection"] == "master" and r["ok"]
        assert tree_of(local) == tree_of(remote_dir / "src")
    assert mux_log(env).count("the spare endpoint had ended") == 2


@pytest.mark.slow
def test_a_robot_src_swapped_for_a_symlink_after_the_spare_started_is_refused(
    env, remote_dir, tmp_path
):
    """The spare checked nothing of the workspace ahead: the endpoint's checks at open
    see the robot's tree as it is when the push comes."""
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    spare_ready(env)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "keep.txt").write_text("not fetchsync's\n")
    shutil.rmtree(remote_dir / "src")
    (remote_dir / "src").symlink_to(elsewhere)
    (local / "my_pkg" / "new.txt").write_text("must not land elsewhere\n")
    proc = fetchsync("push", env=env, check=False)
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr.decode()
    assert "took the spare endpoint" in mux_log(env)
    assert sorted(p.name for p in elsewhere.iterdir()) == ["keep.txt"]
    assert (elsewhere / "keep.txt").read_text() == "not fetchsync's\n"


@pytest.mark.slow
def test_a_spare_dying_after_the_masters_check_does_not_fail_the_push(env, remote_dir):
    """Issue 22 item 21: the spare passes the master's liveness check and dies before the
    client has read anything of it (FETCHSYNC_TEST_SPARE_DIES makes the master close it
    right then, once). Nothing was asked of it: the push starts another endpoint within
    the same call and succeeds."""
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    env = dict(env, FETCHSYNC_TEST_SPARE_DIES="1")  # the master inherits it from the first push
    spare_ready(env)
    (local / "my_pkg" / "after_late_death.txt").write_text("still lands\n")
    proc = fetchsync("push", "--json", env=env, check=False)
    assert proc.returncode == 0, proc.stderr.decode()
    r = report(proc)
    assert r["connection"] == "master" and r["ok"]
    assert mux_log(env).count("took the spare endpoint") >= 1
    assert (remote_dir / "src" / "my_pkg" / "after_late_death.txt").read_text() == "still lands\n"
    assert tree_of(local) == tree_of(remote_dir / "src")
