"""The connection master keeps the SSH connection open between one-shot calls."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import pytest
from helpers import check_ready, fetchsync, report, ssh_env, tree_of

pytestmark = pytest.mark.ssh


def masters(runtime: Path) -> list[int]:
    out = subprocess.run(
        ["pgrep", "-f", f"fetchsync.link.mux.*{runtime}"], check=False, capture_output=True
    )
    return [int(x) for x in out.stdout.split()]


def serving(runtime: Path) -> bool:
    """A master is up and listening: a push leaves one behind as it ends, and it needs
    its own handshake before its socket appears."""
    return bool(masters(runtime)) and any((runtime / "fetchsync").glob("mux-*.sock"))


def wait_for(cond, timeout=60.0):
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
    yield ssh_env(
        ssh_home.home,
        remote_dir,
        tmp_path,
        FETCHSYNC_PERSIST="60",
        XDG_RUNTIME_DIR=str(runtime),
        FETCHSYNC_MUX_LOG=str(tmp_path / "mux.log"),
    )
    for pid in masters(runtime):
        os.kill(pid, signal.SIGTERM)
    shutil.rmtree(runtime, ignore_errors=True)


def test_socket_path_falls_back_to_a_short_directory(tmp_path, monkeypatch):
    from fetchsync.link import mux

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / ("x" * 120)))
    path = mux.socket_path("robot", None)
    assert len(os.fsencode(path)) <= mux.MAX_SOCKET_PATH
    assert path.parent.stat().st_mode & 0o077 == 0


@pytest.mark.slow
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
    from fetchsync.link.mux import MuxTransport

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


def test_robot_changes_between_pushes_through_the_master_are_seen(env, remote_dir):
    """What someone does on the robot between two pushes through a master is not missed."""
    runtime = Path(env["XDG_RUNTIME_DIR"])
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    fetchsync("push", env=env)
    assert wait_for(lambda: serving(runtime))
    assert report(fetchsync("push", "--json", env=env))["connection"] == "master"
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


@pytest.mark.slow
@pytest.mark.parametrize("change", ["changed", "removed"])
def test_a_live_master_is_not_used_once_known_hosts_no_longer_trusts_the_robot(
    change, env, ssh_home, remote_dir, tmp_path
):
    """Issue 22 item 16: the master re-checks the robot's host key against known_hosts
    before each call it serves: a key changed or removed since it connected is refused
    as a fresh connection refuses it, and that master goes away."""
    runtime = Path(env["XDG_RUNTIME_DIR"])
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    fetchsync("push", env=env)
    assert wait_for(lambda: serving(runtime))
    assert report(fetchsync("push", "--json", env=env))["connection"] == "master"
    trusted = ssh_home.known_hosts.read_text()
    if change == "changed":
        other = tmp_path / "other_host_key"
        subprocess.run(
            ["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(other)], check=True
        )
        name = trusted.split()[0]
        ssh_home.known_hosts.write_text(
            f"{name} {other.with_suffix('.pub').read_text().split()[0]} "
            f"{other.with_suffix('.pub').read_text().split()[1]}\n"
        )
    else:
        ssh_home.known_hosts.write_text("")
    (local / "my_pkg" / "after.txt").write_text("must not reach the robot\n")
    proc = fetchsync("push", "--json", env=env, check=False)
    err = proc.stderr.decode()
    assert proc.returncode == 3, err
    assert ("HAS CHANGED" if change == "changed" else "is not known") in err
    assert not (remote_dir / "src/my_pkg/after.txt").exists()
    assert wait_for(lambda: not masters(runtime))
    ssh_home.known_hosts.write_text(trusted)
    r = report(fetchsync("push", "--json", env=env))
    assert r["connection"] == "ssh" and (remote_dir / "src/my_pkg/after.txt").exists()


def robot_endpoints(mark: str) -> list[int]:
    out = subprocess.run(
        ["pgrep", "-f", f"^[^ ]*python3 -X fsmark={mark} "], check=False, capture_output=True
    )
    return [int(p) for p in out.stdout.split()]


@pytest.mark.slow
def test_each_next_push_through_a_master_works_in_the_same_call(env, remote_dir):
    """Issue 22 item 21: an idle master holds one spare endpoint and no more (see
    test_mux_spare.py for one that dies); a robot workspace deleted under a warm
    master, and pushes with other options (--exclude, --dry-run) in between, leave
    the next push working at once."""
    import uuid

    mark = uuid.uuid4().hex[:12]
    env = dict(env, FETCHSYNC_REMOTE_PYTHON=f"python3 -X fsmark={mark}")
    runtime = Path(env["XDG_RUNTIME_DIR"])
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    fetchsync("push", env=env)
    assert wait_for(lambda: serving(runtime))
    assert report(fetchsync("push", "--json", env=env))["connection"] == "master"
    assert wait_for(lambda: len(robot_endpoints(mark)) == 1)  # the spare: nothing else left
    shutil.rmtree(remote_dir)  # the robot's workspace goes while the master is warm
    r = report(fetchsync("push", "--json", env=env))
    assert r["connection"] == "master" and tree_of(local) == tree_of(remote_dir / "src")
    for i in range(3):
        (local / "my_pkg" / f"round{i}.txt").write_text(f"{i}\n")
        fetchsync("push", "--exclude", "launch", env=env)
        (local / "my_pkg" / f"dry{i}.txt").write_text(f"{i}\n")
        fetchsync("push", "--dry-run", env=env)
        r = report(fetchsync("push", "--json", env=env))
        assert r["connection"] == "master" and r["ok"]
        assert tree_of(local) == tree_of(remote_dir / "src")


BUNDLE = Path("/work/shared/data/rclcpp.bundle")
RELEASES = ["29.3.0", "18.0.0", "29.3.0", "8.2.0", "23.2.0", "0.7.4", "29.3.0"]


@pytest.mark.slow
@pytest.mark.skipif(not BUNDLE.exists(), reason="needs the rclcpp bundle")
def test_release_switches_through_a_master_leave_the_robot_identical(env, remote_dir):
    """Issue 22 item 6: ``git checkout`` between releases deletes and re-creates
    directories (an inode number may come back); every push through a persistent
    connection master leaves the robot's tree identical to the laptop's."""
    runtime = Path(env["XDG_RUNTIME_DIR"])
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    repo = local / "rclcpp"
    subprocess.run(["git", "clone", "-q", str(BUNDLE), str(repo)], check=True)
    commits = dict(
        line.split(" ", 1)[::-1]
        for line in subprocess.run(
            ["git", "-C", str(repo), "log", "--format=%h %s"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.splitlines()
    )

    def synced() -> dict:
        return {
            k: v
            for k, v in tree_of(local).items()
            if k != "rclcpp/.git" and not k.startswith("rclcpp/.git/")
        }

    via = []
    for release in RELEASES:
        subprocess.run(["git", "-C", str(repo), "checkout", "-q", commits[release]], check=True)
        # --force: a switch to an old release deletes most files (the mass-deletion guard)
        r = report(fetchsync("push", "--json", "--force", env=env))
        via.append(r["connection"])
        assert synced() == tree_of(remote_dir / "src"), f"after switching to {release}"
        if len(via) == 1:
            assert wait_for(lambda: serving(runtime))
    assert via[1:] == ["master"] * (len(RELEASES) - 1)


def test_garbage_on_the_masters_socket_runs_nothing_and_breaks_nothing(env, remote_dir, tmp_path):
    """The master's socket protocol, fuzzed: malformed requests get an error frame or a
    closed socket, never a command run, a crash or a hang; the next push still uses it."""
    import json as _json
    import random
    import socket as _socket

    runtime = Path(env["XDG_RUNTIME_DIR"])
    fetchsync("push", env=env)
    assert wait_for(lambda: serving(runtime))
    sock_path = str(next((runtime / "fetchsync").glob("mux-*.sock")))
    marker = tmp_path / "ran"
    rng = random.Random(int(os.environ.get("FETCHSYNC_FUZZ_SEED", "22")))
    shapes = [
        lambda: rng.randbytes(rng.randrange(0, 300)),
        lambda: rng.randbytes(rng.randrange(1, 50)) + b"\n" + rng.randbytes(20),
        lambda: (
            _json.dumps(
                rng.choice(
                    [
                        [],
                        5,
                        "x",
                        None,
                        {"exec": 5},
                        {"exec": None},
                        {"exec": ["touch", str(marker)]},
                        {"check": "yes"},
                        {"scan": "/etc", "v": 1},
                        {"Exec": f"touch {marker}"},
                        {},
                    ]
                )
            ).encode()
            + b"\n"
        ),
        lambda: b"{" * rng.randrange(1, 5000) + b"\n",
        lambda: b"x" * (1 << 17),  # a line longer than the master reads
        lambda: _json.dumps({"exec": f"touch {marker}"}).encode()[: rng.randrange(1, 20)],
    ]
    for _ in range(int(os.environ.get("FETCHSYNC_FUZZ_EXAMPLES", "150"))):
        s = _socket.socket(_socket.AF_UNIX)
        s.settimeout(10)
        try:
            s.connect(sock_path)
            s.sendall(rng.choice(shapes)())
            s.shutdown(_socket.SHUT_WR)
            while s.recv(1 << 16):
                pass
        except (BrokenPipeError, ConnectionResetError):
            pass
        finally:
            s.close()
    assert not marker.exists()
    assert masters(runtime)
    (Path(env["FETCHSYNC_WORKSPACE"]) / "src/my_pkg/after_fuzz.txt").write_text("still served\n")
    r = report(fetchsync("push", "--json", env=env))
    assert r["connection"] == "master" and tree_of(
        Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    ) == tree_of(remote_dir / "src")


@pytest.mark.slow
def test_a_directory_deleted_and_re_created_between_pushes_through_a_master_is_pushed(
    env, remote_dir
):
    """Issue 22 item 6 in small: a directory removed and made again (its inode number may
    come back, as after a git checkout), with other files in it, is pushed whole."""
    runtime = Path(env["XDG_RUNTIME_DIR"])
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    pkg = local / "my_pkg"
    fetchsync("push", env=env)
    assert wait_for(lambda: serving(runtime))
    for round_ in range(6):
        fetchsync("push", env=env)
        time.sleep(0.6)  # the master's view, if it keeps one, has caught up
        for name in ("launch", "src"):
            shutil.rmtree(pkg / name, ignore_errors=True)
            (pkg / name).mkdir()
            for i in range(3):
                (pkg / name / f"r{round_}_{i}.txt").write_text(f"{round_} {i}\n")
        r = report(fetchsync("push", "--json", "--force", env=env))
        assert r["connection"] == "master"
        assert tree_of(local) == tree_of(remote_dir / "src"), f"round {round_}"
