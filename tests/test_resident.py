"""The resident: a warm process that makes plain one-shot pushes (issue 24, resident track).

A plain push that went the normal way leaves a resident behind
(fetchsync.agent.resident); the next plain push is made by it. These tests hold
that it answers exactly what a fresh process would: a fresh edit goes, a robot-side
edit is kept as a conflict, a push made without it meanwhile (``--force``) is not
undone, its own code changing makes it step aside, and a resident killed mid-push
leaves the client's push to end right the normal way.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import tempfile
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import fetchsync, report, ssh_env, tree_of
from test_mux_spare import masters, wait_for

pytestmark = pytest.mark.ssh


def residents(runtime: Path) -> list[int]:
    """Resident processes whose socket is in ``runtime``."""
    out = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes()
        except OSError:
            continue
        if b"fetchsync.agent.resident" in cmd and str(runtime).encode() in cmd:
            out.append(int(proc.name))
    return out


def resident_env(home: Path, remote_dir: Path, tmp_path: Path) -> Iterator[dict[str, str]]:
    """A push's environment with residents on (60 s) in a runtime directory of its own,
    traced; the residents and masters started there are stopped after."""
    runtime = Path(tempfile.mkdtemp(prefix="fsres", dir="/tmp"))  # short: AF_UNIX path limit
    yield ssh_env(
        home,
        remote_dir,
        tmp_path,
        FETCHSYNC_PERSIST="60",
        FETCHSYNC_RESIDENT="60",
        XDG_RUNTIME_DIR=str(runtime),
        FETCHSYNC_TRACE=str(tmp_path / "trace"),
        FSMARK=uuid.uuid4().hex[:12],
    )
    for pid in residents(runtime) + masters(runtime):
        try:
            os.kill(pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    shutil.rmtree(runtime, ignore_errors=True)


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    yield from resident_env(ssh_home.home, remote_dir, tmp_path)


def traced(env: dict[str, str]) -> list[str]:
    path = Path(env["FETCHSYNC_TRACE"])
    return path.read_text().splitlines() if path.exists() else []


def resident_up(env: dict[str, str]) -> int:
    """Push once the normal way (leaving a resident) and wait for the resident's link."""
    runtime = Path(env["XDG_RUNTIME_DIR"])
    first = report(fetchsync("push", "--json", env=env))
    assert first["connection"] in ("ssh", "master")
    if first["connection"] == "ssh":  # the master was left by that one: once more
        assert wait_for(lambda: bool(masters(runtime)))
        report(fetchsync("push", "--json", env=env))
    assert wait_for(lambda: bool(residents(runtime)))
    assert wait_for(lambda: any("resident: connected" in ln for ln in traced(env)))
    return residents(runtime)[0]


def push_json(env: dict[str, str], *args: str, check: bool = True) -> dict:
    return report(fetchsync("push", "--json", *args, env=env, check=check))


def test_a_push_through_the_resident_sends_a_fresh_edit(env, remote_dir):
    resident_up(env)
    ws = Path(env["FETCHSYNC_WORKSPACE"])
    edited = next(p for p in sorted((ws / "src").rglob("*")) if p.is_file())
    edited.write_text("edited after the resident started\n")
    got = push_json(env)
    assert got["connection"] == "resident"
    assert got["files"] == 1
    assert tree_of(ws / "src") == tree_of(remote_dir / "src")
    # and a no-op through it changes nothing
    again = push_json(env)
    assert again["connection"] == "resident" and again["files"] == 0


def test_a_robot_side_edit_is_still_a_conflict_and_kept(env, remote_dir):
    resident_up(env)
    ws = Path(env["FETCHSYNC_WORKSPACE"])
    (remote_dir / "src/my_pkg/package.xml").write_text("edited on the robot\n")
    (ws / "src/my_pkg/package.xml").write_text("edited here\n")
    proc = fetchsync("push", "--json", env=env)
    got = report(proc)
    assert got["connection"] == "resident"
    assert [c["path"] for c in got["conflicts"]] == ["my_pkg/package.xml"]
    kept = remote_dir / got["conflicts"][0]["kept"]
    assert kept.read_text() == "edited on the robot\n"
    assert (remote_dir / "src/my_pkg/package.xml").read_text() == "edited here\n"


def test_a_push_made_without_the_resident_is_not_undone_by_it(env, remote_dir):
    """A --force push (made the normal way) between two of the resident's: the resident
    reads the state again, so the file edited back to what the resident last pushed goes
    to the robot, and nothing the --force push did is taken for a robot-side edit."""
    resident_up(env)
    ws = Path(env["FETCHSYNC_WORKSPACE"])
    node = ws / "src/my_pkg/src/node.cpp"
    node.write_text("version one\n")
    assert push_json(env)["connection"] == "resident"
    node.write_text("version two\n")
    forced = push_json(env, "--force")
    assert forced["connection"] != "resident" and forced["files"] == 1
    node.write_text("version one\n")  # back to what the resident pushed last
    got = push_json(env)
    assert got["connection"] == "resident"
    assert got["conflicts"] == [] and got["files"] == 1
    assert tree_of(ws / "src") == tree_of(remote_dir / "src")


def test_the_resident_exits_when_its_code_changes(env, remote_dir, tmp_path, monkeypatch):
    """Its own copy of the package (as an editable install's checkout): a file touched
    there (a git pull, an upgrade) and it declines and exits; the push still goes."""
    copy = tmp_path / "code"
    shutil.copytree(
        Path(__file__).resolve().parent.parent / "fetchsync",
        copy / "fetchsync",
        ignore=shutil.ignore_patterns("__pycache__"),
    )
    env["PYTHONPATH"] = str(copy)
    monkeypatch.chdir(tmp_path)  # python -m imports from the working directory first
    runtime = Path(env["XDG_RUNTIME_DIR"])
    pid = resident_up(env)
    assert push_json(env)["connection"] == "resident"
    module = copy / "fetchsync/sync/plan.py"
    os.utime(module, ns=(time.time_ns(), time.time_ns() + 10**9))
    ws = Path(env["FETCHSYNC_WORKSPACE"])
    (ws / "src/my_pkg/package.xml").write_text("after the upgrade\n")
    got = push_json(env)
    assert got["connection"] != "resident"
    assert tree_of(ws / "src") == tree_of(remote_dir / "src")
    assert wait_for(lambda: pid not in residents(runtime), timeout=20)


def test_a_resident_killed_mid_push_leaves_the_push_to_end_right(env, remote_dir):
    import subprocess
    import sys

    runtime = Path(env["XDG_RUNTIME_DIR"])
    pid = resident_up(env)
    ws = Path(env["FETCHSYNC_WORKSPACE"])
    (ws / "src/my_pkg/big.bin").write_bytes(os.urandom(48 << 20))
    proc = subprocess.Popen(
        [sys.executable, "-m", "fetchsync", "push", "--json"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    asked = wait_for(lambda: any("resident: push asked" in ln for ln in traced(env)), timeout=30)
    time.sleep(0.05)
    os.kill(pid, signal.SIGKILL)
    out, err = proc.communicate(timeout=120)
    assert asked
    assert proc.returncode == 0, err.decode()
    got = json.loads(out.decode().splitlines()[-1])
    assert got["connection"] != "resident"
    assert tree_of(ws / "src") == tree_of(remote_dir / "src")
    assert pid not in residents(runtime)


def test_watch_takes_over_from_the_resident_and_a_push_then_uses_the_watch(
    env, remote_dir, tmp_path
):
    import subprocess
    import sys

    runtime = Path(env["XDG_RUNTIME_DIR"])
    pid = resident_up(env)
    status = json.loads(fetchsync("status", "--json", env=env).stdout)
    assert status["state"] == "resident" and status["pid"] == pid
    log = tmp_path / "watch.log"
    watch = subprocess.Popen(
        [sys.executable, "-m", "fetchsync", "watch"],
        env=env,
        stdout=open(log, "wb"),
        stderr=subprocess.STDOUT,
    )
    try:

        def live() -> bool:
            out = fetchsync("status", "--json", env=env, check=False)
            return bool(out.stdout.strip()) and json.loads(out.stdout).get("state") == "live"

        assert wait_for(live, timeout=60), log.read_text()
        assert pid not in residents(runtime)
        ws = Path(env["FETCHSYNC_WORKSPACE"])
        (ws / "src/my_pkg/package.xml").write_text("while watching\n")
        Path(env["FETCHSYNC_TRACE"]).write_text("")
        got = push_json(env)
        assert got["connection"] == "agent"
        marks = Path(env["FETCHSYNC_TRACE"]).read_text()
        assert "agent: pushed" in marks and "push: start" not in marks  # no click, no engine
        assert tree_of(ws / "src") == tree_of(remote_dir / "src")
        assert not residents(runtime)  # a push through the watch starts none
    finally:
        watch.send_signal(signal.SIGTERM)
        watch.wait(20)
