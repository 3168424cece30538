"""push and pull end to end against the built-in ``local`` robot (no SSH)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from helpers import check_ready, fetchsync, local_env, make_workspace, report, tree_of


@pytest.fixture
def env(tmp_path: Path) -> dict:
    return local_env(tmp_path)


def local_src(env: dict) -> Path:
    return Path(env["FETCHSYNC_WORKSPACE"]) / "src"


def robot_ws(env: dict) -> Path:
    return Path(env["FETCHSYNC_LOCAL_ROBOT_HOME"]) / "robot_ws"


def push(env: dict, *args: str, check: bool = True):
    return fetchsync("push", "--json", *args, env=env, check=check)


def test_push_mirrors_everything_and_a_second_push_is_a_noop(env):
    r = report(push(env))
    assert r["ok"] and r["files"] == 5 and r["links"] == 2 and r["dirs"] == 4
    assert tree_of(local_src(env)) == tree_of(robot_ws(env) / "src")
    assert os.readlink(robot_ws(env) / "src" / "CMakeLists.txt").startswith("/opt/ros")
    assert (robot_ws(env) / "src/my_pkg/scripts/run.py").stat().st_mode & 0o111
    r2 = report(push(env))
    assert r2["files"] == r2["dirs"] == r2["deleted"] == 0
    assert r2["bytes_sent"] < 2048


def test_same_size_edit_within_the_same_second_is_sent(env):
    push(env)
    f = local_src(env) / "my_pkg/src/node.cpp"
    st = f.stat()
    f.write_text("int main() { return 1; }\n")  # same size
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))  # and the very same mtime
    push(env)
    assert (robot_ws(env) / "src/my_pkg/src/node.cpp").read_text() == "int main() { return 1; }\n"


def test_insert_at_top_of_big_file_goes_by_delta(env):
    push(env)
    time.sleep(0.01)
    f = local_src(env) / "my_pkg/data.txt"
    f.write_text("// a new first line\n" + f.read_text())
    noop = report(push(env))
    assert noop["deltas"] == 1
    assert noop["bytes_sent"] < 4096
    assert (robot_ws(env) / "src/my_pkg/data.txt").read_bytes() == f.read_bytes()


def test_rename_reuses_content_on_the_robot(env):
    push(env)
    src = local_src(env)
    (src / "my_pkg/data.txt").rename(src / "my_pkg/moved.txt")
    r = report(push(env))
    assert r["reused"] == 1 and r["deleted"] == 1
    assert r["bytes_sent"] < 4096
    assert tree_of(src) == tree_of(robot_ws(env) / "src")


def test_file_becomes_directory_and_back(env):
    push(env)
    src = local_src(env)
    (src / "my_pkg/package.xml").unlink()
    (src / "my_pkg/package.xml").mkdir()
    (src / "my_pkg/package.xml/inner").write_text("x")
    push(env)
    assert tree_of(src) == tree_of(robot_ws(env) / "src")
    (src / "my_pkg/package.xml/inner").unlink()
    (src / "my_pkg/package.xml").rmdir()
    (src / "my_pkg/package.xml").write_text("back")
    push(env)
    assert tree_of(src) == tree_of(robot_ws(env) / "src")


def test_robot_side_edits_are_kept_not_lost(env):
    push(env)
    robot_src = robot_ws(env) / "src"
    (robot_src / "my_pkg/src/node.cpp").write_text("edited on the robot\n")
    (robot_src / "my_pkg/robot_only.txt").write_text("made on the robot\n")
    r = report(push(env))
    assert {c["path"] for c in r["conflicts"]} == {"my_pkg/src/node.cpp", "my_pkg/robot_only.txt"}
    assert tree_of(local_src(env)) == tree_of(robot_src)
    kept = sorted((robot_ws(env) / ".fetchsync/conflicts").rglob("*.*"))
    contents = {p.name: p.read_text() for p in kept if p.is_file()}
    assert contents["node.cpp"] == "edited on the robot\n"
    assert contents["robot_only.txt"] == "made on the robot\n"


def test_strict_refuses_to_replace_robot_side_edits(env):
    push(env)
    robot_file = robot_ws(env) / "src/my_pkg/src/node.cpp"
    robot_file.write_text("edited on the robot\n")
    (local_src(env) / "my_pkg/src/node.cpp").write_text("edited on the laptop\n")
    proc = push(env, "--strict", check=False)
    assert proc.returncode == 6
    assert robot_file.read_text() == "edited on the robot\n"
    assert b"changed on the robot" in proc.stderr


def test_deleted_files_go_to_the_trash(env):
    push(env)
    (local_src(env) / "my_pkg/src/node.cpp").unlink()
    push(env)
    assert not (robot_ws(env) / "src/my_pkg/src/node.cpp").exists()
    trashed = list((robot_ws(env) / ".fetchsync/trash").rglob("node.cpp"))
    assert len(trashed) == 1 and trashed[0].read_text() == "int main() { return 0; }\n"


def test_empty_or_missing_src_is_refused_without_force(env, tmp_path):
    push(env)
    for p in sorted(local_src(env).rglob("*"), reverse=True):
        p.unlink() if p.is_file() or p.is_symlink() else p.rmdir()
    proc = push(env, check=False)
    assert proc.returncode != 0 and b"empty" in proc.stderr
    assert (robot_ws(env) / "src/my_pkg/package.xml").exists()
    push(env, "--force")
    assert list((robot_ws(env) / "src").iterdir()) == []


def test_excludes_apply_and_excluded_robot_files_are_left_alone(env):
    src = local_src(env)
    (src / ".fetchsyncignore").write_text("*.log\n")
    (src / "my_pkg/run.log").write_text("log")
    (src / "my_pkg/.node.cpp.swp").write_text("swap")
    (src / "my_pkg/__pycache__").mkdir()
    (src / "my_pkg/__pycache__/x.pyc").write_text("pyc")
    (src / "my_pkg/secret.key").write_text("k")
    push(env, "--exclude", "*.key")
    robot_src = robot_ws(env) / "src"
    assert (robot_src / ".fetchsyncignore").exists()
    for name in ("run.log", ".node.cpp.swp", "__pycache__", "secret.key"):
        assert not (robot_src / "my_pkg" / name).exists(), name
    (robot_src / "my_pkg/robot.log").write_text("robot log")
    push(env, "--exclude", "*.key")
    assert (robot_src / "my_pkg/robot.log").read_text() == "robot log"


def test_dry_run_changes_nothing(env):
    r = report(push(env, "--dry-run"))
    assert r["dry_run"] and r["files"] == 5
    assert not (robot_ws(env) / "src/my_pkg").exists()


def test_interrupted_batch_leaves_no_torn_files_and_next_push_converges(env):
    push(env)
    robot_src = robot_ws(env) / "src"
    # what a push killed between writing temporaries and renaming leaves behind
    (robot_src / "my_pkg/.node.cpp.fetchsync-tmp-0123456789ab").write_text("half")
    (robot_ws(env) / ".fetchsync/batch-in-progress").write_text("")
    (local_src(env) / "my_pkg/src/node.cpp").write_text("new\n")
    push(env)
    assert not list(robot_src.rglob("*fetchsync-tmp*"))
    assert tree_of(local_src(env)) == tree_of(robot_src)


@pytest.mark.slow
def test_pull_mirrors_the_robot_and_keeps_local_edits(env):
    push(env)
    robot_src = robot_ws(env) / "src"
    (robot_src / "my_pkg/new_on_robot.txt").write_text("hello from the robot\n")
    (robot_src / "my_pkg/CMakeLists.txt").write_text("changed on the robot\n")
    (local_src(env) / "my_pkg/src/node.cpp").write_text("local edit never pushed\n")
    proc = fetchsync("pull", "--json", env=env, check=False, input=b"")
    assert proc.returncode != 0 and b"--yes" in proc.stderr  # no terminal: refuse, change nothing
    assert not (local_src(env) / "my_pkg/new_on_robot.txt").exists()
    r = report(fetchsync("pull", "--json", "--no-safety", env=env))
    assert r["ok"]
    assert tree_of(local_src(env)) == tree_of(robot_src)
    kept = list((Path(env["FETCHSYNC_WORKSPACE"]) / ".fetchsync/conflicts").rglob("node.cpp"))
    assert kept and kept[0].read_text() == "local edit never pushed\n"
    # after a pull both sides agree: the next push has nothing to do
    assert report(push(env))["files"] == 0


def test_local_robot_refuses_its_own_workspace(env):
    env = dict(
        env, FETCHSYNC_REMOTE_WORKSPACE=env["FETCHSYNC_WORKSPACE"], FETCHSYNC_LOCAL_ROBOT_HOME="/"
    )
    proc = push(env, check=False)
    assert proc.returncode == 2 and b"local workspace itself" in proc.stderr


def test_first_push_onto_an_existing_robot_tree_uses_the_robots_signatures(env):
    # the robot already holds an older copy (say, from rsync) and we have no state
    robot_src = robot_ws(env) / "src"
    import shutil

    shutil.copytree(local_src(env), robot_src, symlinks=True)
    f = local_src(env) / "my_pkg/data.txt"
    old = f.read_text()
    f.write_text("// new first line\n" + old)
    r = report(push(env))
    assert r["deltas"] == 1 and r["bytes_sent"] < 16384  # not the whole 2 MB
    assert tree_of(local_src(env)) == tree_of(robot_src)
    # the robot's version was not seen by us before: it is kept
    kept = list((robot_ws(env) / ".fetchsync/conflicts").rglob("data.txt"))
    assert len(kept) == 1 and kept[0].read_text() == old


@pytest.mark.slow
def test_a_long_pipeline_does_not_deadlock_the_local_robot(env):
    # thousands of operations: the robot's answers fill a pipe buffer while
    # the laptop is still writing requests
    import subprocess
    import sys

    src = local_src(env)
    for d in range(50):
        (src / f"many{d}").mkdir()
        for f in range(100):
            (src / f"many{d}" / f"{f}.txt").write_bytes(os.urandom(64).hex().encode())
    proc = subprocess.run(
        [sys.executable, "-m", "fetchsync", "push", "--json"],
        env=env,
        capture_output=True,
        timeout=90,
    )
    assert proc.returncode == 0, proc.stderr
    assert report(proc)["files"] == 5005
    assert tree_of(src) == tree_of(robot_ws(env) / "src")


def test_the_local_scan_is_made_while_the_endpoint_starts(tmp_path, monkeypatch):
    """Connection.open runs ``meanwhile`` once the endpoint's command is sent and before
    its hello is read; a first push given that scan lands the same tree."""
    from fetchsync.link.connection import Connection
    from fetchsync.link.transport import LocalTransport
    from fetchsync.protocol import wire
    from fetchsync.sync import engine as sync
    from fetchsync.sync.state import State

    make_workspace(tmp_path / "ws")
    src = tmp_path / "ws" / "src"
    events: list[str] = []
    real_hello = wire.Reader.read_hello

    def read_hello(self):
        events.append("hello")
        return real_hello(self)

    monkeypatch.setattr(wire.Reader, "read_hello", read_hello)
    rules = sync.build_rules()
    scanned = []
    state = State(tmp_path / "state.sqlite")

    def meanwhile(answered) -> None:
        events.append("scan")
        scanned.append(sync.scan_tree(str(src), rules))

    conn = Connection.open(LocalTransport(tmp_path / "robot-home"), meanwhile=meanwhile)
    try:
        assert events == ["scan", "hello"]
        r = sync.Syncer(
            conn, state, local_root=str(src), remote_workspace="~/ws", rules=rules
        ).push(scanned=scanned[0])
        assert r.errors == [] and r.files == 5
        assert tree_of(src) == tree_of(tmp_path / "robot-home" / "ws" / "src")
    finally:
        conn.close()
        state.close()


def test_the_endpoint_widens_the_pipe_it_reads(tmp_path):
    """The endpoint asks for a 1 MiB pipe on its stdin (64 KiB by default): the ~100 MB of
    a first push then wake its writer (sshd, or this process for the local robot) a
    sixteenth as often. Read back from our end of that very pipe."""
    import fcntl

    from fetchsync.link.connection import Connection
    from fetchsync.link.transport import LocalTransport

    limit = int(Path("/proc/sys/fs/pipe-max-size").read_text())
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    try:
        conn.request({"op": "ping"})  # answered after main() set it up
        size = fcntl.fcntl(conn.channel._proc.stdin.fileno(), 1032)  # F_GETPIPE_SZ
        assert size == min(1 << 20, limit) and size > 65536
    finally:
        conn.close()


def test_the_endpoint_runs_no_site_hooks_yet_finds_site_packages(tmp_path):
    """The loader starts Python with -S: a sitecustomize (or a .pth hook) on the robot
    does not run before the endpoint, which could print into the protocol's stream or
    cost every start tens of ms; the site directories are still on its path, so an
    installed xxhash is used."""
    from fetchsync.link.connection import Connection
    from fetchsync.link.transport import LocalTransport
    from fetchsync.protocol import hashing, wire

    hooks = tmp_path / "hooks"
    hooks.mkdir()
    marker = tmp_path / "sitecustomize-ran"
    (hooks / "sitecustomize.py").write_text(f"open({str(marker)!r}, 'w').close()\nprint('noise')\n")
    python = tmp_path / "robot-python3"
    python.write_text(f'#!/bin/sh\nPYTHONPATH={hooks} exec {sys.executable} "$@"\n')
    python.chmod(0o755)
    # the same interpreter without -S does run the hook: the test can see it
    subprocess.run([str(python), "-c", "pass"], check=True)
    assert marker.exists()
    marker.unlink()
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"), python=str(python))
    try:
        assert conn.request({"op": "ping"}).type == wire.T_RESPONSE
        assert not marker.exists()
        assert conn.hello["algorithms"] == hashing.available()  # xxhash found, if installed here
    finally:
        conn.close()


def test_the_local_robots_channel_tells_when_output_is_waiting(tmp_path):
    """Channel.ready() of the ``local`` robot: not before the command writes, then at
    once, and at its end."""
    from fetchsync.link.transport import LocalTransport

    check_ready(LocalTransport(tmp_path / "robot-home").exec("sleep 1; echo hi; sleep 0.5"))


def test_a_push_killed_before_its_state_is_written_sends_nothing_again(tmp_path, monkeypatch):
    """The state is written once, at the end of a push's rounds. A push stopped just
    before leaves the state as it was: the next push lists the robot, finds it
    identical, sends nothing, and then knows every path."""
    from fetchsync.link.connection import Connection
    from fetchsync.link.transport import LocalTransport
    from fetchsync.sync import engine as sync
    from fetchsync.sync.state import State

    src = tmp_path / "ws" / "src"
    for d in range(12):
        (src / f"d{d}").mkdir(parents=True)
        for f in range(60):
            (src / f"d{d}" / f"{f}.txt").write_text(f"{d} {f}\n" * 300)  # ~5 KiB: many batches
    monkeypatch.setattr(sync, "FIRST_BATCHES_SMALLER", {k: 6 for k in range(64)})  # 128 KiB batches
    state = State(tmp_path / "state.sqlite")
    commits: list[int] = []
    real_commit = State.commit

    def commit(self, **k):
        commits.append(1)
        raise KeyboardInterrupt

    monkeypatch.setattr(State, "commit", commit)
    rules = sync.build_rules()
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    try:
        syncer = sync.Syncer(conn, state, local_root=str(src), remote_workspace="~/ws", rules=rules)
        with pytest.raises(KeyboardInterrupt):
            syncer.push()
        assert commits == [1] and state.entries() == {}
        assert tree_of(src) == tree_of(tmp_path / "robot-home" / "ws" / "src")
        monkeypatch.setattr(State, "commit", real_commit)
        again = sync.Syncer(
            conn, state, local_root=str(src), remote_workspace="~/ws", rules=rules
        ).push()
        assert again.errors == [] and again.files == 0 and again.bytes_sent < 64 * 1024
        assert len(state.entries()) == 12 + 12 * 60
    finally:
        conn.close()
        state.close()


def test_a_large_push_keeps_signatures_so_an_edit_goes_as_a_delta(tmp_path, monkeypatch):
    """A push of more than a batch keeps a delta signature of each larger text file it
    sent, the content of each smaller one (and nothing of a binary one), so the next
    edit goes as a delta with no question to the robot."""
    import zlib

    from fetchsync.link.connection import Connection
    from fetchsync.link.transport import LocalTransport
    from fetchsync.protocol import delta
    from fetchsync.protocol import messages as M
    from fetchsync.sync import engine as sync
    from fetchsync.sync.state import State

    src = make_workspace(tmp_path / "ws") / "src"
    texts = {}
    for i in range(24):
        lines = 900 if i % 2 else 1800  # ~22 KiB: content kept; ~45 KiB: a signature
        texts[f"t{i}.txt"] = b"".join(b"line %d of text file %d\n" % (n, i) for n in range(lines))
        (src / f"t{i}.txt").write_bytes(texts[f"t{i}.txt"])
    (src / "mesh.bin").write_bytes(b"\0" + os.urandom(40 * 1024))  # binary: never signed
    monkeypatch.setattr(sync, "BATCH_BYTES", 128 * 1024)
    rules = sync.build_rules()
    state = State(tmp_path / "state.sqlite")
    robot_src = tmp_path / "robot-home" / "ws" / "src"
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    try:
        r = sync.Syncer(
            conn, state, local_root=str(src), remote_workspace="~/ws", rules=rules
        ).push()
        assert r.errors == []
        for name, data in texts.items():
            kept = state.signature(name)
            if len(data) <= M.ZDICT_BASE_MAX:  # the content itself, for dictionary writes
                assert kept[:4] == sync.BASE_MAGIC and zlib.decompress(kept[4:]) == data
            else:
                assert kept == delta.signature(data, algorithm=conn.algorithm).to_bytes()
        assert state.signature("mesh.bin") is None

        requests: list[str] = []
        real_request = Connection.request

        def request(self, header, *a, **k):
            requests.append(header["op"])
            return real_request(self, header, *a, **k)

        monkeypatch.setattr(Connection, "request", request)
        for name in ("t0.txt", "t1.txt"):
            (src / name).write_bytes(b"a line inserted at the top\n" + (src / name).read_bytes())
        again = sync.Syncer(
            conn, state, local_root=str(src), remote_workspace="~/ws", rules=rules
        ).push()
        assert again.errors == [] and again.files == 2 and again.deltas == 2
        assert tree_of(src) == tree_of(robot_src)
        assert again.bytes_sent < 8 * 1024  # two deltas, not 44 KiB of files
        assert "sigs" not in requests
    finally:
        conn.close()
        state.close()


def test_the_robots_command_is_sent_before_the_sync_engine_is_imported(env):
    """Each import before the connection delays the robot's start by as much; the sync
    engine is imported while the robot's endpoint starts (in the connection's
    ``meanwhile``). A new interpreter, as the test process imported it long ago."""
    code = textwrap.dedent("""
        import sys
        from fetchsync.link import connection
        real = connection.Connection.open.__func__

        def spy(cls, transport, **kw):
            print("sync imported before the connection:", "fetchsync.sync.engine" in sys.modules,
                  file=sys.stderr, flush=True)
            return real(cls, transport, **kw)

        connection.Connection.open = classmethod(spy)
        sys.argv = ["fetchsync", "push", "--json"]
        from fetchsync.cli import main
        main()  # exits
    """)
    proc = subprocess.run(
        [sys.executable, "-c", code],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    said = [line for line in proc.stderr.splitlines() if line.startswith("sync imported")]
    assert said == ["sync imported before the connection: False"], proc.stderr
    assert tree_of(local_src(env)) == tree_of(robot_ws(env) / "src")
