"""Local files that cannot be read, vanish, or change while a push reads them.

The robot must never lose its copy of a file the laptop cannot read, never
hold a file that is half the old and half the new content, and never keep
upload temporaries; the other files still sync and the problem is named.

End to end over the real sshd: a file and a directory root cannot read (the
CLI runs under ``setpriv`` without CAP_DAC_OVERRIDE/CAP_DAC_READ_SEARCH), and
a large file a real writer keeps appending to. In process over the ``local``
robot, at the read seam ``sync.read_hook``: a file that changes once (read
again), keeps changing (reported, the robot's version kept), shrinks, is
replaced, or vanishes (treated as deleted).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from helpers import local_env, make_workspace, report, ssh_env, tree_of

from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State

SETPRIV = shutil.which("setpriv")


def leftovers_after_the_session(workspace: Path, timeout: float = 60) -> list[str]:
    """``leftovers`` once the endpoint whose connection was just closed has ended its
    session: it clears the upload parts as it exits, which on a busy machine is a moment
    after ``close()`` returns."""
    deadline = time.monotonic() + timeout
    while (left := leftovers(workspace)) and time.monotonic() < deadline:
        time.sleep(0.05)
    return left


def leftovers(workspace: Path) -> list[str]:
    """Temporaries of a write, and upload parts, anywhere in a robot workspace."""
    out = []
    for dirpath, dirs, files in os.walk(workspace):
        for name in dirs + files:
            if "fetchsync-tmp" in name or name.startswith("upload-"):
                out.append(os.path.join(dirpath, name))
    return out


# --------------------------------------------------------------------------- end to end, real sshd
@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    return ssh_env(ssh_home.home, remote_dir, tmp_path)


def run(*args: str, env: dict, unprivileged: bool = False) -> subprocess.CompletedProcess:
    """The real CLI; ``unprivileged`` takes root's power to read anything away."""
    cmd = [sys.executable, "-m", "fetchsync", *args]
    if unprivileged and os.geteuid() == 0:
        cmd = [SETPRIV, "--bounding-set", "-dac_override,-dac_read_search", "--", *cmd]
    return subprocess.run(cmd, check=False, capture_output=True, env=env, timeout=120)


@pytest.mark.ssh
@pytest.mark.skipif(
    os.geteuid() == 0 and SETPRIV is None, reason="needs setpriv (util-linux) as root"
)
def test_unreadable_paths_are_left_on_the_robot_and_reported(env, remote_dir):
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    robot = remote_dir / "src"
    assert report(run("push", "--json", env=env))["ok"]
    before = tree_of(robot)
    (local / "my_pkg/package.xml").write_text("<package>edited, then locked</package>\n")
    (local / "my_pkg/package.xml").chmod(0)
    (local / "my_pkg/src").chmod(0)  # a directory nobody can list
    (local / "my_pkg/CMakeLists.txt").write_text("project(my_pkg)  # edited\n")
    (local / "my_pkg/new.txt").write_text("new\n")
    try:
        proc = run("push", "--json", env=env, unprivileged=True)
        assert proc.returncode == 5, proc.stderr.decode()  # SyncError: some paths failed
        assert b"Traceback" not in proc.stderr
        r = report(proc)
        assert not r["ok"]
        failed = {e["path"]: e["error"] for e in r["errors"]}
        assert "cannot read" in failed["my_pkg/package.xml"], failed
        assert "cannot list" in failed["my_pkg/src"], failed
        assert r["deleted"] == 0
        # the robot's copies are untouched: no delete, no chmod of the directory
        assert tree_of(robot)["my_pkg/package.xml"] == before["my_pkg/package.xml"]
        assert tree_of(robot)["my_pkg/src"] == before["my_pkg/src"]
        assert tree_of(robot)["my_pkg/src/node.cpp"] == before["my_pkg/src/node.cpp"]
        # the others went
        assert (robot / "my_pkg/CMakeLists.txt").read_text() == "project(my_pkg)  # edited\n"
        assert (robot / "my_pkg/new.txt").read_text() == "new\n"
        # the text report names the path; one summary line ends it
        proc = run("push", env=env, unprivileged=True)
        err = proc.stderr.decode()
        assert proc.returncode == 5 and "Traceback" not in err
        assert "error: my_pkg/package.xml: cannot read" in err
        assert err.strip().splitlines()[-1].startswith("fetchsync: error: 2 path(s) failed")
        assert not (remote_dir / ".fetchsync/trash").exists() or not any(
            "package.xml" in n for _d, _s, f in os.walk(remote_dir / ".fetchsync/trash") for n in f
        )
    finally:
        (local / "my_pkg/package.xml").chmod(0o644)
        (local / "my_pkg/src").chmod(0o755)
    # readable again: it goes, and nothing on the robot was set aside as a conflict
    r = report(run("push", "--json", env=env, unprivileged=True))
    assert r["ok"] and r["conflicts"] == []
    assert tree_of(local) == tree_of(robot)
    assert leftovers(remote_dir) == []


INCREMENTAL = """
import json, os, sys
from pathlib import Path
from fetchsync.sync import engine as sync
from fetchsync.link.connection import Connection
from fetchsync.sync.state import State
from fetchsync.link.transport import LocalTransport
base, src = sys.argv[1], sys.argv[1] + "/ws/src"
conn = Connection.open(LocalTransport(Path(base) / "robot-home"))
state = State(Path(base) / "state.sqlite")
s = sync.Syncer(conn, state, local_root=src, remote_workspace="~/ws", rules=sync.build_rules())
assert s.push().errors == []
os.chmod(src + "/my_pkg/package.xml", 0)   # its owner may, without CAP_FOWNER
os.chmod(src + "/my_pkg/src", 0)
with open(src + "/my_pkg/CMakeLists.txt", "a") as fh:
    fh.write("# edited\\n")
r = s.push_paths({"my_pkg/package.xml", "my_pkg/CMakeLists.txt"}, {"my_pkg/src"})
print(json.dumps({"errors": r.errors, "deleted": r.deleted, "files": r.files}))
"""


@pytest.mark.skipif(
    os.geteuid() == 0 and SETPRIV is None, reason="needs setpriv (util-linux) as root"
)
def test_the_watch_agents_incremental_push_leaves_unreadable_paths_too(tmp_path):
    make_workspace(tmp_path / "ws")
    cmd = [sys.executable, "-c", INCREMENTAL, str(tmp_path)]
    if os.geteuid() == 0:
        cmd = [SETPRIV, "--bounding-set", "-dac_override,-dac_read_search", "--", *cmd]
    proc = subprocess.run(cmd, check=False, capture_output=True, timeout=60)
    try:
        assert proc.returncode == 0, proc.stderr.decode()
        r = json.loads(proc.stdout.decode().splitlines()[-1])
        assert {e["path"] for e in r["errors"]} == {"my_pkg/package.xml", "my_pkg/src"}
        assert (r["deleted"], r["files"]) == (0, 1)
        robot = tmp_path / "robot-home/ws/src/my_pkg"
        assert (robot / "package.xml").exists() and (robot / "src/node.cpp").exists()
        assert (robot / "src").stat().st_mode & 0o777 == 0o755
        assert (robot / "CMakeLists.txt").read_text().endswith("# edited\n")
    finally:
        (tmp_path / "ws/src/my_pkg/package.xml").chmod(0o644)
        (tmp_path / "ws/src/my_pkg/src").chmod(0o755)


@pytest.mark.skipif(
    os.geteuid() == 0 and SETPRIV is None, reason="needs setpriv (util-linux) as root"
)
def test_pull_leaves_unreadable_local_paths_alone(tmp_path):
    e = local_env(tmp_path)
    local, robot = tmp_path / "ws/src/my_pkg", tmp_path / "robot-home/robot_ws/src/my_pkg"
    assert report(run("push", "--json", env=e))["ok"]
    (robot / "package.xml").write_text("edited on the robot\n")
    (robot / "src/node.cpp").write_text("edited on the robot\n")
    (local / "package.xml").chmod(0)
    (local / "src").chmod(0)
    try:
        proc = run("pull", "--yes", "--json", env=e, unprivileged=True)
        assert proc.returncode == 5 and b"Traceback" not in proc.stderr, proc.stderr.decode()
        r = report(proc)
        assert {x["path"] for x in r["errors"]} == {"my_pkg/package.xml", "my_pkg/src"}
        assert r["files"] == 0 and r["conflicts"] == []
    finally:
        (local / "package.xml").chmod(0o644)
        (local / "src").chmod(0o755)
    assert (local / "package.xml").read_text() != "edited on the robot\n"
    assert not (tmp_path / "ws/.fetchsync/conflicts").exists()
    # readable again: the robot's edits come, replacing what was last synced (no conflict)
    r = report(run("pull", "--yes", "--json", env=e))
    assert r["ok"] and r["files"] == 2 and r["conflicts"] == []
    assert (local / "src/node.cpp").read_text() == "edited on the robot\n"


@pytest.mark.slow
@pytest.mark.ssh
def test_a_big_file_that_keeps_changing_keeps_the_robots_version(env, remote_dir):
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    robot = remote_dir / "src"
    log = local / "my_pkg/recording.bag"
    log.write_bytes(os.urandom(sync.BIG + 1024 * 1024))
    assert report(run("push", "--json", env=env))["ok"]
    old = hashlib.sha256(log.read_bytes()).hexdigest()
    (local / "my_pkg/CMakeLists.txt").write_text("project(my_pkg)  # edited\n")
    stop = threading.Event()

    def writer() -> None:  # a recorder appending as it goes (every attempt to send it
        with open(log, "ab") as fh:  # takes far longer than a few of its writes)
            while not stop.is_set():
                fh.write(os.urandom(256))
                fh.flush()
                time.sleep(0.001)

    t = threading.Thread(target=writer, daemon=True)
    t.start()
    try:
        proc = run("push", "--json", env=env)
    finally:
        stop.set()
        t.join()
    assert proc.returncode == 5, proc.stderr.decode()
    assert b"Traceback" not in proc.stderr
    r = report(proc)
    assert [e["path"] for e in r["errors"]] == ["my_pkg/recording.bag"], r["errors"]
    assert "kept changing" in r["errors"][0]["error"]
    assert hashlib.sha256((robot / "my_pkg/recording.bag").read_bytes()).hexdigest() == old
    assert (robot / "my_pkg/CMakeLists.txt").read_text() == "project(my_pkg)  # edited\n"
    assert leftovers(remote_dir) == []
    # once the recorder stopped, it goes
    r = report(run("push", "--json", env=env))
    assert r["ok"]
    assert tree_of(local) == tree_of(robot)


# --------------------------------------------------------------------------- in process, at the read seam
@pytest.fixture
def robot(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """A pushed workspace, its Syncer over the local robot, and the robot's workspace."""
    monkeypatch.setattr(sync, "BIG", 512 * 1024)  # big files are sent in pieces ...
    monkeypatch.setattr(sync, "PIECE", 128 * 1024)  # ... of this size
    make_workspace(tmp_path / "ws")
    src = tmp_path / "ws/src"
    (src / "my_pkg/data.txt").write_bytes(
        b"".join(b"line %d\n" % i for i in range(12000))
    )  # ~100 KB
    (src / "my_pkg/big.bin").write_bytes(os.urandom(1024 * 1024))
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    state = State(tmp_path / "state.sqlite")
    s = sync.Syncer(
        conn, state, local_root=str(src), remote_workspace="~/ws", rules=sync.build_rules()
    )
    assert s.push().errors == []
    yield s, src, tmp_path / "robot-home/ws"
    conn.close()
    state.close()


def hook_on(
    monkeypatch: pytest.MonkeyPatch,
    name: str,
    event: str,
    action,
    times: int = 1,
    skip: int = 0,
    every: int = 1,
) -> list[int]:
    """Run ``action(path)`` at ``times`` ``event``s ("open" or "read" of a chunk) of the file
    ``name``, after letting ``skip`` of them pass, then at every ``every``-th one."""
    calls = [0]
    seen = [0]

    def hook(full: str, what: str) -> None:
        if os.path.basename(full) != name or what != event:
            return
        seen[0] += 1
        if seen[0] > skip and (seen[0] - skip) % every == 0 and calls[0] < times:
            calls[0] += 1
            action(Path(full))

    monkeypatch.setattr(sync, "read_hook", hook)
    return calls


def size(name: str) -> int:
    """A size that keeps ``name`` on its path: small files read whole, big ones in pieces."""
    return 100 * 1024 if name == "data.txt" else 700 * 1024


def append(path: Path) -> None:
    with open(path, "ab") as fh:
        fh.write(b"appended while it was read\n")


# data.txt is read in one chunk; big.bin has two pieces on the robot when it changes
@pytest.mark.parametrize(("name", "skip"), [("data.txt", 0), ("big.bin", 2)])
def test_a_file_changed_while_read_is_read_again(robot, monkeypatch, name, skip):
    s, src, ws = robot
    f = src / "my_pkg" / name
    f.write_bytes(f.read_bytes()[:-10] + b"0123456789")  # what the scan sees
    calls = hook_on(monkeypatch, name, "read", append, skip=skip)  # changes under the first read
    r = s.push()
    assert calls[0] == 1
    assert r.errors == [] and r.files == 1
    assert (ws / "src/my_pkg" / name).read_bytes() == f.read_bytes()
    assert f.read_bytes().endswith(b"appended while it was read\n")
    assert leftovers(ws) == []  # the first attempt's upload was overwritten, not left
    monkeypatch.setattr(sync, "read_hook", None)
    assert s.push().changed == 0  # and the state knows it is there


def test_a_big_file_that_shrinks_while_read_is_sent_whole(robot, monkeypatch):
    s, src, ws = robot
    f = src / "my_pkg/big.bin"
    f.write_bytes(os.urandom(900 * 1024))
    # two pieces are on the robot when it shrinks below them
    hook_on(monkeypatch, "big.bin", "read", lambda p: p.write_bytes(os.urandom(100 * 1024)), skip=2)
    r = s.push()
    assert r.errors == []
    assert (ws / "src/my_pkg/big.bin").read_bytes() == f.read_bytes()
    assert len(f.read_bytes()) == 100 * 1024
    # the first attempt's upload, too long to reuse, goes when the session ends
    s.conn.close()
    assert leftovers_after_the_session(ws) == []


# big.bin changes at every third piece: two pieces of each attempt reach the robot
@pytest.mark.parametrize(("name", "every"), [("data.txt", 1), ("big.bin", 3)])
def test_a_file_that_keeps_changing_keeps_the_robots_version(robot, monkeypatch, name, every):
    s, src, ws = robot
    old = (ws / "src/my_pkg" / name).read_bytes()
    f = src / "my_pkg" / name
    f.write_bytes(os.urandom(size(name)))
    (src / "my_pkg/CMakeLists.txt").write_text("project(my_pkg)  # edited\n")
    calls = hook_on(monkeypatch, name, "read", append, times=1000, every=every)
    r = s.push()
    assert 1 < calls[0] <= 10  # read again, a bounded number of times
    assert [e["path"] for e in r.errors] == [f"my_pkg/{name}"]
    assert "kept changing" in r.errors[0]["error"]
    assert (ws / "src/my_pkg" / name).read_bytes() == old
    assert (ws / "src/my_pkg/CMakeLists.txt").read_text() == "project(my_pkg)  # edited\n"
    assert not list(ws.rglob("*fetchsync-tmp*"))
    assert len(leftovers(ws)) == (every > 1)  # the abandoned upload part, for now
    monkeypatch.setattr(sync, "read_hook", None)
    r = s.push()
    assert r.errors == [] and (ws / "src/my_pkg" / name).read_bytes() == f.read_bytes()
    # the same session (the watch agent's last hours) reused the abandoned upload part
    assert leftovers(ws) == []


@pytest.mark.parametrize("name", ["data.txt", "big.bin"])
def test_a_file_replaced_while_read_sends_the_new_one(robot, monkeypatch, name):
    s, src, ws = robot
    f = src / "my_pkg" / name
    f.write_bytes(os.urandom(size(name)))
    new = os.urandom(size(name) - 1000)

    def replace(p: Path) -> None:  # an editor's atomic save: write aside, rename over
        (p.parent / "tmp-save").write_bytes(new)
        os.rename(p.parent / "tmp-save", p)

    hook_on(monkeypatch, name, "read", replace)
    r = s.push()
    assert r.errors == []
    assert (ws / "src/my_pkg" / name).read_bytes() == new
    assert leftovers(ws) == []


@pytest.mark.parametrize("name", ["data.txt", "big.bin"])
def test_a_file_that_becomes_a_fifo_is_reported_not_waited_on(robot, monkeypatch, name):
    s, src, ws = robot
    old = (ws / "src/my_pkg" / name).read_bytes()
    f = src / "my_pkg" / name
    f.write_bytes(os.urandom(size(name)))

    def fifo(p: Path) -> None:
        p.unlink()
        os.mkfifo(p)

    hook_on(monkeypatch, name, "open", fifo, skip=1)

    def expire(signum: int, frame: object) -> None:
        raise TimeoutError("the push waited for a writer on the FIFO")

    before = signal.signal(signal.SIGALRM, expire)
    signal.alarm(60)
    try:
        r = s.push()
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, before)
    assert [e["path"] for e in r.errors] == [f"my_pkg/{name}"]
    assert "no longer a regular file" in r.errors[0]["error"]
    assert (ws / "src/my_pkg" / name).read_bytes() == old  # the robot keeps its version
    assert not list(ws.rglob("*fetchsync-tmp*"))


# the scan hashes a changed file (its first open); the send opens it again and reads it
@pytest.mark.parametrize(
    ("name", "event", "skip"),
    [
        ("data.txt", "open", 0),
        ("data.txt", "open", 1),
        ("data.txt", "read", 0),
        ("big.bin", "open", 1),
        ("big.bin", "read", 1),
    ],
)
def test_a_file_that_vanishes_is_treated_as_deleted(robot, monkeypatch, name, event, skip):
    s, src, ws = robot
    f = src / "my_pkg" / name
    f.write_bytes(os.urandom(size(name)))
    (src / "my_pkg/CMakeLists.txt").write_text("project(my_pkg)  # edited\n")
    calls = hook_on(monkeypatch, name, event, lambda p: p.unlink(), skip=skip)
    r = s.push()
    assert calls[0] == 1
    assert r.errors == []
    assert [x["path"] for x in r.skipped] == [f"my_pkg/{name}"]
    assert "vanished" in r.skipped[0]["reason"]
    assert r.deleted == 1
    assert not (ws / "src/my_pkg" / name).exists()  # mirrored: gone (into the trash)
    assert list((ws / ".fetchsync/trash").rglob(name))
    assert (ws / "src/my_pkg/CMakeLists.txt").read_text() == "project(my_pkg)  # edited\n"
    assert not list(ws.rglob("*fetchsync-tmp*"))
    monkeypatch.setattr(sync, "read_hook", None)
    assert s.push().changed == 0
    s.conn.close()  # a part of the vanished file goes with the session
    assert leftovers_after_the_session(ws) == []


def test_a_new_file_that_vanishes_leaves_nothing(robot, monkeypatch):
    s, src, ws = robot
    (src / "my_pkg/fresh.txt").write_text("fresh\n")
    hook_on(monkeypatch, "fresh.txt", "open", lambda p: p.unlink())
    r = s.push()
    assert r.errors == [] and r.deleted == 0 and r.files == 0
    assert not (ws / "src/my_pkg/fresh.txt").exists()
    assert tree_of(src) == tree_of(ws / "src")


@pytest.mark.skipif(
    os.geteuid() == 0 and SETPRIV is None, reason="needs setpriv (util-linux) as root"
)
def test_an_unreadable_src_itself_is_one_line(tmp_path):
    e = local_env(tmp_path)
    (tmp_path / "ws/src").chmod(0)
    try:
        proc = run("push", env=e, unprivileged=True)
    finally:
        (tmp_path / "ws/src").chmod(0o755)
    lines = proc.stderr.decode().strip().splitlines()
    assert proc.returncode == 5 and len(lines) == 1, proc.stderr.decode()
    assert "cannot list" in lines[0] and "Permission denied" in lines[0]
    assert not (tmp_path / "robot-home/robot_ws/src/my_pkg").exists()
