"""The connection master keeps the SSH connection open between one-shot calls."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import pytest
from helpers import check_ready, fetchsync, make_workspace, report, ssh_env, tree_of

pytestmark = pytest.mark.ssh


def masters(runtime: Path) -> list[int]:
    out = subprocess.run(["pgrep", "-f", f"fetchsync.agent.mux.*{runtime}"], check=False,
                         capture_output=True)
    return [int(x) for x in out.stdout.split()]


def serving(runtime: Path) -> bool:
    """A master is up and listening: a push leaves one behind as it ends, and it needs
    its own handshake before its socket appears."""
    return bool(masters(runtime)) and any((runtime / "fetchsync").glob("mux-*.sock"))


def wait_for(cond, timeout=15.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.1)
    return False


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    # short: AF_UNIX socket paths are limited to 108 bytes
    runtime = Path(tempfile.mkdtemp(prefix="fsrun", dir="/tmp"))
    yield ssh_env(ssh_home.home, remote_dir, tmp_path, FETCHSYNC_PERSIST="60",
                  XDG_RUNTIME_DIR=str(runtime), FETCHSYNC_MUX_LOG=str(tmp_path / "mux.log"))
    for pid in masters(runtime):
        os.kill(pid, signal.SIGTERM)
    shutil.rmtree(runtime, ignore_errors=True)


def test_socket_path_falls_back_to_a_short_directory(tmp_path, monkeypatch):
    from fetchsync.agent import mux
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / ("x" * 120)))
    path = mux.socket_path("robot", None)
    assert len(os.fsencode(path)) <= mux.MAX_SOCKET_PATH
    assert path.parent.stat().st_mode & 0o077 == 0


def test_second_call_goes_through_the_master_and_a_dead_master_is_replaced(env, remote_dir):
    runtime = Path(env["XDG_RUNTIME_DIR"])
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    assert report(fetchsync("push", "--json", env=env))["connection"] == "ssh"
    assert wait_for(lambda: list((runtime / "fetchsync").glob("mux-*.sock")))
    sock = next((runtime / "fetchsync").glob("mux-*.sock"))
    assert sock.stat().st_mode & 0o077 == 0
    (local / "my_pkg/new.txt").write_text("via the master\n")
    r = report(fetchsync("push", "--json", env=env))
    assert r["connection"] == "master" and r["files"] == 1
    assert tree_of(local) == tree_of(remote_dir / "src")
    # pull goes through it too
    (remote_dir / "src/my_pkg/robot.txt").write_text("robot\n")
    assert report(fetchsync("pull", "--json", "--yes", env=env))["connection"] == "master"
    assert (local / "my_pkg/robot.txt").read_text() == "robot\n"
    # a killed master leaves a stale socket: the next call connects directly
    for pid in masters(runtime):
        os.kill(pid, signal.SIGKILL)
    assert wait_for(lambda: not masters(runtime))
    r = report(fetchsync("push", "--json", env=env))
    assert r["connection"] == "ssh"


def test_a_command_through_the_master_tells_when_output_is_waiting(env):
    """MuxChannel.ready(): not before the command writes, then at once, and at its end."""
    from fetchsync.agent.mux import MuxTransport

    runtime = Path(env["XDG_RUNTIME_DIR"])
    fetchsync("push", env=env)
    assert wait_for(lambda: serving(runtime))
    transport = MuxTransport.attach(next((runtime / "fetchsync").glob("mux-*.sock")), "robot")
    assert transport is not None
    check_ready(transport.exec("sleep 1; echo hi; sleep 0.5"))


def test_master_exits_when_idle(env):
    env = dict(env, FETCHSYNC_PERSIST="1")
    runtime = Path(env["XDG_RUNTIME_DIR"])
    fetchsync("push", env=env)
    assert wait_for(lambda: bool(masters(runtime)), 10)
    assert wait_for(lambda: not masters(runtime), 15)
    assert not list((runtime / "fetchsync").glob("mux-*.sock"))


def prewarmed_endpoints() -> list[int]:
    """Robot endpoints (this machine's) holding an inotify instance: scanned ahead of need."""
    out = subprocess.run(["pgrep", "-f", "fetchsync.protocol.server"], check=False,
                         capture_output=True)
    found = []
    for pid in out.stdout.split():
        try:
            fds = os.listdir(f"/proc/{int(pid)}/fd")
            if any(os.readlink(f"/proc/{int(pid)}/fd/{fd}") == "anon_inode:inotify" for fd in fds):
                found.append(int(pid))
        except OSError:
            continue
    return found


def test_robot_changes_after_a_warm_endpoint_scanned_are_still_seen(env, remote_dir):
    """A spare endpoint scans the workspace ahead of the next call and keeps that scan
    current with inotify: what someone does on the robot meanwhile must not be missed."""
    runtime = Path(env["XDG_RUNTIME_DIR"])
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    fetchsync("push", env=env)
    assert wait_for(lambda: serving(runtime))
    assert report(fetchsync("push", "--json", env=env))["connection"] == "master"
    assert wait_for(lambda: len(prewarmed_endpoints()) >= 1)
    time.sleep(0.5)  # its scan (of a few files) is done: what follows is only in its events
    robot = remote_dir / "src"
    (robot / "my_pkg/src/node.cpp").write_text("int main() { return 1; }  // fixed on the robot\n")
    (robot / "my_pkg/launch/robot_only.launch").write_text("<launch/>\n")
    (robot / "my_pkg/robot_dir/deep").mkdir(parents=True)
    (robot / "my_pkg/robot_dir/deep/x.yaml").write_text("a: 1\n")
    (robot / "my_pkg/package.xml").unlink()
    (robot / "my_pkg/scripts/run.py").chmod(0o644)
    r = report(fetchsync("push", "--json", env=env))
    assert r["connection"] == "master"
    assert tree_of(local) == tree_of(robot)
    kept = {c["path"] for c in r["conflicts"]}
    assert {"my_pkg/src/node.cpp", "my_pkg/launch/robot_only.launch"} <= kept
    # and the robot's version of the edited file is in .fetchsync/conflicts
    copies = list((remote_dir / ".fetchsync" / "conflicts").rglob("node.cpp"))
    assert copies and "fixed on the robot" in copies[0].read_text()


def test_the_master_keeps_the_local_scan_current(env, remote_dir):
    """The master watches the local tree (inotify) and answers a push's scan from it:
    every kind of local change made meanwhile must still be pushed."""
    runtime = Path(env["XDG_RUNTIME_DIR"])
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    fetchsync("push", env=env)
    assert wait_for(lambda: serving(runtime))
    assert wait_for(lambda: report(fetchsync("push", "--json", env=env))["scan"] == "watched")
    pkg = local / "my_pkg"
    (pkg / "src/node.cpp").write_text("int main() { return 2; }\n")
    (pkg / "new_dir/deeper").mkdir(parents=True)
    (pkg / "new_dir/deeper/n.h").write_text("#pragma once\n")
    (pkg / "package.xml").unlink()
    (pkg / "scripts/run.py").chmod(0o700)
    (pkg / "launch").rename(pkg / "launch_moved")
    (pkg / "rel_link").unlink()
    (pkg / "rel_link").symlink_to("CMakeLists.txt")
    (pkg / "CMakeLists.txt.swp").write_text("editor swap: ignored\n")
    r = report(fetchsync("push", "--json", env=env))
    assert r["scan"] == "watched" and r["connection"] == "master"
    assert tree_of(local) == {k: v for k, v in tree_of(remote_dir / "src").items()} | {
        "my_pkg/CMakeLists.txt.swp": tree_of(local)["my_pkg/CMakeLists.txt.swp"]}
    assert not (remote_dir / "src/my_pkg/CMakeLists.txt.swp").exists()
    # and a push with nothing changed is a no-op from the watched scan
    r = report(fetchsync("push", "--json", env=env))
    assert r["scan"] == "watched" and r["files"] == r["deleted"] == r["chmods"] == 0


def test_the_master_a_push_leaves_behind_watches_its_tree_from_the_start(env, remote_dir):
    """The push that leaves a master behind names its local tree: the master watches it
    at once, so the very first push through it has its scan ready, rather than asking
    for it, scanning for itself meanwhile, and competing with the master's own scan."""
    runtime = Path(env["XDG_RUNTIME_DIR"])
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    log = Path(env["FETCHSYNC_MUX_LOG"])
    fetchsync("push", env=env)
    assert wait_for(lambda: serving(runtime))
    assert wait_for(lambda: log.exists() and f"watching {local}: its scans are ready" in log.read_text())
    (local / "my_pkg" / "first.txt").write_text("the first push through the master\n")
    r = report(fetchsync("push", "--json", env=env))
    assert r["connection"] == "master" and r["scan"] == "watched" and r["files"] == 1
    assert tree_of(local) == tree_of(remote_dir / "src")


def test_the_masters_scan_answers_only_what_a_fresh_scan_would(tmp_path):
    import marshal

    from fetchsync.agent.mux import SCAN_VERSION, Master
    from fetchsync.protocol.store import is_temp
    from fetchsync.protocol.tree import scan
    from fetchsync.sync import build_rules

    src = make_workspace(tmp_path / "ws") / "src"
    rules = build_rules()
    master = Master(transport=None, path=tmp_path / "sock", idle=60, warm=None)
    request = {"scan": str(src), "rules": rules.to_wire(), "v": SCAN_VERSION}

    def answer():
        return marshal.loads(master._scan(request))["entries"]

    def fresh():
        return {p: tuple(e) for p, e in scan(str(src), rules, is_temp=is_temp).entries.items()}

    with pytest.raises(ValueError, match="starting"):
        master._scan(request)  # the first request only starts the watch
    assert wait_for(lambda: master.trees.get(json.dumps([str(src), rules.to_wire()])) is not None)
    assert answer() == fresh()
    (src / "my_pkg/src/node.cpp").write_text("changed\n")
    (src / "my_pkg/new").mkdir()
    assert answer() == fresh()
    assert answer() == fresh()  # the cached reply, nothing moved
    (src / "my_pkg/.fetchsyncignore").write_text("*.txt\n")
    with pytest.raises(ValueError, match="lost"):
        master._scan(request)  # the rules changed: it rescans from scratch
    os.mkfifo(src / "my_pkg/fifo")
    with pytest.raises(ValueError, match="starting"):
        master._scan(request)
    assert wait_for(lambda: master.trees.get(json.dumps([str(src), rules.to_wire()])) is not None)
    with pytest.raises(ValueError, match="skips"):
        master._scan(request)  # a FIFO is reported by a real scan: the caller must scan
    with pytest.raises(ValueError, match="unknown"):
        master._scan({"scan": str(src), "v": 99})


def watched_inodes(pid: int) -> set[int]:
    """The inodes of the directories a process watches with inotify (from /proc fdinfo)."""
    out = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            if os.readlink(f"/proc/{pid}/fd/{fd}") != "anon_inode:inotify":
                continue
            with open(f"/proc/{pid}/fdinfo/{fd}") as fh:
                for line in fh:
                    if line.startswith("inotify wd:"):
                        out.add(int(line.split(" ino:")[1].split()[0], 16))
        except OSError:
            continue
    return out


def test_calls_through_the_master_take_its_spares_once_the_interpreter_is_noted(env, remote_dir, tmp_path):
    """A direct connection notes the robot's interpreter (connection.interpreter_note);
    calls through the master still run ``python3`` by name, the command its spares were
    started with, so each takes a spare instead of waiting for a new endpoint."""
    env = dict(env, XDG_CACHE_HOME=str(tmp_path / "cache"))
    runtime = Path(env["XDG_RUNTIME_DIR"])
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    assert report(fetchsync("push", "--json", env=env))["connection"] == "ssh"
    assert list((tmp_path / "cache" / "fetchsync").glob("python-*"))  # noted
    assert wait_for(lambda: serving(runtime))
    for i in range(3):
        assert wait_for(lambda: len(prewarmed_endpoints()) >= 2, timeout=10)
        (local / "my_pkg" / f"n{i}.txt").write_text(f"{i}\n")
        assert report(fetchsync("push", "--json", env=env))["connection"] == "master"
    assert tree_of(local) == tree_of(remote_dir / "src")
    assert "no endpoint started ahead" not in Path(env["FETCHSYNC_MUX_LOG"]).read_text()


def test_spare_endpoints_follow_the_workspace_opened_last(env, remote_dir, tmp_path):
    """Spares started before the first push to another workspace switch to it."""
    runtime = Path(env["XDG_RUNTIME_DIR"])
    fetchsync("push", env=env)
    assert wait_for(lambda: serving(runtime))
    assert report(fetchsync("push", "--json", env=env))["connection"] == "master"
    first_ino = os.stat(remote_dir / "src").st_ino
    # both spares have prepared the first workspace
    assert wait_for(lambda: sum(first_ino in watched_inodes(pid)
                                for pid in prewarmed_endpoints()) >= 2, timeout=10)
    other = dict(env, FETCHSYNC_REMOTE_WORKSPACE=str(remote_dir) + "-other",
                 XDG_STATE_HOME=str(tmp_path / "state-other"))
    assert report(fetchsync("push", "--json", env=other))["connection"] == "master"
    src_ino = os.stat(str(remote_dir) + "-other/src").st_ino

    def spares_watch_other() -> bool:
        return sum(src_ino in watched_inodes(pid) for pid in prewarmed_endpoints()) >= 2

    assert wait_for(spares_watch_other, timeout=10)
