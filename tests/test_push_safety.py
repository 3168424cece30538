"""The laptop side of the safety promises (issue 22): nothing on either end is lost.

Against the built-in ``local`` robot: the engine directly (``Syncer``, as the watch
agent drives it) and the CLI end to end.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import stat
import subprocess
import sys
import time
import types
from pathlib import Path

import pytest
from helpers import fetchsync, local_env, make_workspace, report, tree_of

from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State


@pytest.fixture
def engine(tmp_path: Path):
    """A Syncer over the local robot, after a first push of make_workspace's tree."""
    src = make_workspace(tmp_path / "ws") / "src"
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    state = State(tmp_path / "state.sqlite")
    s = sync.Syncer(
        conn, state, local_root=str(src), remote_workspace="~/ws", rules=sync.build_rules()
    )
    assert s.push().errors == []
    yield s, src, tmp_path / "robot-home" / "ws"
    conn.close()
    state.close()


@pytest.fixture
def env(tmp_path: Path) -> dict:
    return local_env(tmp_path)


def local_src(env: dict) -> Path:
    return Path(env["FETCHSYNC_WORKSPACE"]) / "src"


def robot_ws(env: dict) -> Path:
    return Path(env["FETCHSYNC_LOCAL_ROBOT_HOME"]) / "robot_ws"


def kept(where: Path, name: str) -> list[bytes]:
    """The contents of every file called ``name`` kept below ``where``."""
    return [p.read_bytes() for p in where.rglob(name) if p.is_file()] if where.exists() else []


def test_a_chmod_over_a_robot_side_edit_keeps_the_robots_edit(engine):
    """Issue 22 item 1: the robot edits a file, the laptop only chmods it (the watch
    agent's incremental push). The robot ends with the laptop's file and mode, and its
    own edit is kept in conflicts/: the answer to the chmod, which names content the
    laptop never saw, is never taken as the base of the next write."""
    s, src, ws = engine
    robot_file = ws / "src/my_pkg/CMakeLists.txt"
    robot_file.write_text("fixed on the robot\n")
    local = src / "my_pkg/CMakeLists.txt"
    local.chmod(0o755)
    r = s.push_paths({"my_pkg/CMakeLists.txt"})
    assert r.errors == []
    assert robot_file.read_bytes() == local.read_bytes()
    assert stat.S_IMODE(robot_file.stat().st_mode) == 0o755
    assert b"fixed on the robot\n" in kept(ws / ".fetchsync", "CMakeLists.txt")
    # and nothing is left to do, on either path
    assert s.push_paths({"my_pkg/CMakeLists.txt"}).changed == 0
    assert s.push().changed == 0


def test_pull_keeps_every_local_file_it_replaces_or_deletes(env):
    """Issue 22 item 4: what pull replaces or deletes goes to the local trash, an
    unpushed local edit to conflicts/, as its prompt and the README say."""
    assert report(fetchsync("push", "--json", env=env))["ok"]
    robot_src, src = robot_ws(env) / "src", local_src(env)
    ws = Path(env["FETCHSYNC_WORKSPACE"])
    (robot_src / "my_pkg/CMakeLists.txt").write_text("changed on the robot\n")
    (robot_src / "my_pkg/rel_link").unlink()
    (robot_src / "my_pkg/rel_link").symlink_to("CMakeLists.txt")
    (robot_src / "my_pkg/data.txt").unlink()
    (robot_src / "my_pkg/package.xml").write_text("<robot/>\n")
    before = {n: (src / "my_pkg" / n).read_bytes() for n in ("CMakeLists.txt", "data.txt")}
    (src / "my_pkg/package.xml").write_text("<local edit never pushed/>\n")
    r = report(fetchsync("pull", "--json", "--yes", env=env))
    assert r["ok"]
    assert tree_of(src) == tree_of(robot_src)
    for name, data in before.items():
        assert data in kept(ws / ".fetchsync/trash", name), name
    assert any((d / "my_pkg/rel_link").is_symlink() for d in (ws / ".fetchsync/trash").iterdir())
    assert b"<local edit never pushed/>\n" in kept(ws / ".fetchsync/conflicts", "package.xml")
    assert not kept(ws / ".fetchsync/trash", "package.xml")  # an edit is a conflict, not trash


def test_pull_drops_setuid_and_setgid(env):
    """Issue 22 item 15: a robot's setuid or setgid file arrives without those bits,
    also when pull runs as root."""
    assert report(fetchsync("push", "--json", env=env))["ok"]
    robot_src, src = robot_ws(env) / "src", local_src(env)
    (robot_src / "my_pkg/run.sh").write_text("#!/bin/sh\nid\n")
    (robot_src / "my_pkg/run.sh").chmod(0o6755)
    (robot_src / "my_pkg/CMakeLists.txt").chmod(0o4644)
    assert report(fetchsync("pull", "--json", "--yes", env=env))["ok"]
    assert stat.S_IMODE((src / "my_pkg/run.sh").stat().st_mode) == 0o755
    assert stat.S_IMODE((src / "my_pkg/CMakeLists.txt").stat().st_mode) == 0o644


@pytest.mark.slow
def test_a_pattern_added_to_a_fetchsyncignore_leaves_the_robots_files_alone(env):
    """Issue 22 item 5: excluded means left alone, also when the pattern is added to an
    ignore file that was already synced: the matching robot files are neither deleted
    nor moved to the trash, and later pushes have nothing to do."""
    src, ws = local_src(env), robot_ws(env)
    assert report(fetchsync("push", "--json", env=env))["ok"]
    (src / ".fetchsyncignore").write_text("data.txt\n")
    assert report(fetchsync("push", "--json", env=env))["ok"]
    with open(src / ".fetchsyncignore", "a") as fh:
        fh.write("scripts\n")
    r = report(fetchsync("push", "--json", env=env))
    assert r["ok"] and r["deleted"] == 0 and r["conflicts"] == []
    assert (ws / "src/my_pkg/data.txt").read_bytes() == (src / "my_pkg/data.txt").read_bytes()
    assert (ws / "src/my_pkg/scripts/run.py").exists()
    assert (ws / "src/.fetchsyncignore").read_text() == (src / ".fetchsyncignore").read_text()
    assert not kept(ws / ".fetchsync", "data.txt") and not kept(ws / ".fetchsync", "run.py")
    # an excluded file deleted here is still left alone there
    (src / "my_pkg/data.txt").unlink()
    again = report(fetchsync("push", "--json", env=env))
    assert again["ok"] and again["deleted"] == 0
    assert (ws / "src/my_pkg/data.txt").exists()
    assert report(fetchsync("push", "--json", env=env))["files"] == 0


def test_patterns_added_to_a_synced_ignore_file_leave_the_robots_files_alone(engine):
    """Issue 22 item 5, as the engine (and the watch agent) sees it: a full push and an
    incremental one, with a pattern for a file and one for a directory added to an
    ignore file the robot already holds."""
    s, src, ws = engine
    (src / ".fetchsyncignore").write_text("data.txt\n")  # a new ignore file
    assert s.push().errors == []
    (src / ".fetchsyncignore").write_text("data.txt\nscripts\n")  # a pattern added to it
    r = s.push()
    assert r.errors == [] and r.deleted == 0 and r.conflicts == []
    (src / "my_pkg/.fetchsyncignore").write_text("package.xml\n")
    r = s.push_paths({"my_pkg/.fetchsyncignore"})
    assert r.errors == [] and r.deleted == 0 and r.conflicts == []
    for path in ("my_pkg/data.txt", "my_pkg/scripts/run.py", "my_pkg/package.xml"):
        assert (ws / "src" / path).read_bytes() == (src / path).read_bytes(), path
    assert not (ws / ".fetchsync/trash").exists() or not any((ws / ".fetchsync/trash").iterdir())
    assert s.push().changed == 0


def test_an_exclude_then_a_plain_push_finds_no_conflict_and_resends_nothing(env):
    """Issue 22 item 7: a push with --exclude DIR, then a plain one: DIR's files, the
    same on both ends, are neither conflicts nor sent again."""
    src, ws = local_src(env), robot_ws(env)
    for i in range(30):
        (src / f"my_pkg/src/f{i}.cpp").write_text(f"int f{i}() {{ return {i}; }}\n" * 50)
    assert report(fetchsync("push", "--json", env=env))["ok"]
    (src / "my_pkg/package.xml").write_text("<changed/>\n")
    r = report(fetchsync("push", "--json", "--exclude", "my_pkg/src", env=env))
    assert r["ok"] and r["files"] == 1 and r["deleted"] == 0
    plain = report(fetchsync("push", "--json", env=env))
    assert plain["ok"] and plain["conflicts"] == [] and plain["files"] == 0, plain
    assert plain["bytes_sent"] < 16 * 1024
    assert not (ws / ".fetchsync/conflicts").exists() or not any(
        (ws / ".fetchsync/conflicts").rglob("*.cpp")
    )
    assert tree_of(src) == tree_of(ws / "src")


@pytest.mark.parametrize("left", ["empty directories", "a CATKIN_IGNORE"])
def test_a_src_of_empty_directories_counts_as_empty(env, left):
    """Issue 22 item 8: a src/ holding only empty directories, or a CATKIN_IGNORE, would
    empty the robot's: refused without --force."""
    assert report(fetchsync("push", "--json", env=env))["ok"]
    src = local_src(env)
    for p in sorted(src.rglob("*"), reverse=True):
        p.unlink() if p.is_file() or p.is_symlink() else p.rmdir()
    (src / "my_pkg/launch").mkdir(parents=True)
    if left == "a CATKIN_IGNORE":
        (src / "CATKIN_IGNORE").touch()
    proc = fetchsync("push", "--json", env=env, check=False)
    assert proc.returncode == 5 and b"empty the robot's src/" in proc.stderr
    assert b"Traceback" not in proc.stderr
    assert (robot_ws(env) / "src/my_pkg/package.xml").exists()
    assert report(fetchsync("push", "--json", "--force", env=env))["ok"]
    assert not (robot_ws(env) / "src/my_pkg/package.xml").exists()


def many_files(src: Path, n: int = 40) -> None:
    for i in range(n):
        (src / "my_pkg/many").mkdir(exist_ok=True)
        (src / f"my_pkg/many/f{i}.txt").write_text(f"file {i}\n")


@pytest.mark.slow
def test_deleting_most_of_the_robots_files_needs_force(env):
    """The mass-deletion guard: a push that would delete more than half of the robot's
    files (and more than a few) changes nothing without --force; fewer go as usual."""
    src, ws = local_src(env), robot_ws(env)
    many_files(src)
    assert report(fetchsync("push", "--json", env=env))["ok"]
    for i in range(10):  # a few: no question
        (src / f"my_pkg/many/f{i}.txt").unlink()
    assert report(fetchsync("push", "--json", env=env))["deleted"] == 10
    (src / "my_pkg/package.xml").write_text("<changed/>\n")
    for p in (src / "my_pkg/many").iterdir():
        p.unlink()
    (src / "my_pkg/data.txt").unlink()
    proc = fetchsync("push", "--json", env=env, check=False)
    assert proc.returncode == 5 and b"would delete 31 of the robot's" in proc.stderr, proc.stderr
    assert b"--force" in proc.stderr and b"Traceback" not in proc.stderr
    assert len(list((ws / "src/my_pkg/many").iterdir())) == 30
    assert (ws / "src/my_pkg/package.xml").read_text() != "<changed/>\n"  # nothing at all was sent
    r = report(fetchsync("push", "--json", "--force", env=env))
    assert r["ok"] and r["deleted"] >= 2
    assert tree_of(src) == tree_of(ws / "src")


def test_the_engine_refuses_a_mass_deletion_unless_confirmed(engine):
    """The same guard where the watch agent meets it: an incremental push of a deleted
    directory."""
    s, src, ws = engine
    many_files(src)
    assert s.push().errors == []
    for p in (src / "my_pkg/many").iterdir():
        p.unlink()
    with pytest.raises(sync.MassDeletionError):
        s.push_paths(set(), {"my_pkg/many"})
    assert len(list((ws / "src/my_pkg/many").iterdir())) == 40
    r = s.push_paths(set(), {"my_pkg/many"}, confirm_deletions=True)
    assert r.errors == [] and r.deleted == 40


def state_files(env: dict) -> list[Path]:
    return sorted((Path(env["XDG_STATE_HOME"]) / "fetchsync").glob("*.sqlite"))


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_a_damaged_state_is_set_aside_and_rebuilt_with_a_note(env, damage):
    """Issue 22 item 22: a damaged state database is set aside with a one-line note; the
    push lists the robot, sends nothing it holds already, and later pushes are quiet."""
    src, ws = local_src(env), robot_ws(env)
    for i in range(200):
        (src / f"my_pkg/f{i}.txt").write_text(f"file {i}\n" * 20)
    assert report(fetchsync("push", "--json", env=env))["ok"]
    (path,) = state_files(env)
    # a one-shot push exits with its commits in the WAL (cli._ONE_SHOT): into the file
    with sqlite3.connect(path) as db:
        db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    data = path.read_bytes()
    path.write_bytes(
        data[:100] + os.urandom(len(data) - 100) if damage == "garbage" else data[: len(data) // 2]
    )
    (src / "my_pkg/package.xml").write_text("<edited after the damage/>\n")
    proc = fetchsync("push", "--json", env=env, check=False)
    err = proc.stderr.decode()
    assert proc.returncode == 0 and "Traceback" not in err, err
    notes = [line for line in err.splitlines() if line.startswith("fetchsync: note:")]
    assert len(notes) == 1 and "damaged" in notes[0] and "set aside" in notes[0]
    r = json.loads(proc.stdout)
    # without its state the laptop cannot tell its edit from one made on the robot:
    # the robot's version is kept aside, the rest is adopted as it is
    assert r["files"] == 1 and r["bytes_sent"] < 64 * 1024
    assert [c["path"] for c in r["conflicts"]] == ["my_pkg/package.xml"]
    assert tree_of(src) == tree_of(ws / "src")
    assert list(path.parent.glob(path.name + ".damaged-*"))
    again = fetchsync("push", "--json", env=env)
    assert b"note:" not in again.stderr and json.loads(again.stdout)["files"] == 0


SETPRIV = shutil.which("setpriv")


@pytest.mark.skipif(
    os.geteuid() == 0 and SETPRIV is None, reason="needs setpriv (util-linux) as root"
)
@pytest.mark.parametrize("how", ["full", "incremental"])
def test_a_directory_that_lost_its_x_bit_is_one_line_and_left_alone(env, how):
    """Issue 22 item 22: a synced directory without its x bit (its entries cannot be
    looked up) is one error line, no traceback, and its robot copy is left as it was:
    its files are not taken for deleted."""
    src, ws = local_src(env), robot_ws(env)
    assert report(fetchsync("push", "--json", env=env))["ok"]
    before = tree_of(ws / "src")
    if how == "incremental":  # an edit in it: the push goes path by path
        (src / "my_pkg/package.xml").write_text("<edited/>\n")
    cmd = [sys.executable, "-m", "fetchsync", "push"]
    if os.geteuid() == 0:  # root's power to look anywhere, taken away
        cmd = [SETPRIV, "--bounding-set", "-dac_override,-dac_read_search", "--", *cmd]
    (src / "my_pkg").chmod(0o644)
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, timeout=120, check=False)
    finally:
        (src / "my_pkg").chmod(0o755)
    err = proc.stderr.decode()
    assert proc.returncode == 5 and "Traceback" not in err, err
    assert (
        err.strip().splitlines()[-1].startswith("fetchsync: error: 1 path(s) failed; first: my_pkg")
    )
    assert tree_of(ws / "src") == before
    assert not (ws / ".fetchsync/trash").exists()


def test_a_dry_run_creates_nothing_on_the_robot(env):
    """Issue 22 item 24: a dry run against a robot without the workspace plans the whole
    tree and leaves the robot as it was (no workspace made); on one with the workspace,
    its index is left as it was too."""
    proc = fetchsync("push", "--json", "--dry-run", env=env)
    r = json.loads(proc.stdout)
    assert r["dry_run"] and r["files"] == 5 and r["conflicts"] == []
    assert not robot_ws(env).exists()
    # the real push then finds nothing in its way
    assert report(fetchsync("push", "--json", env=env))["conflicts"] == []
    (local_src(env) / "my_pkg/package.xml").write_text("<edited/>\n")
    before = tree_of(robot_ws(env))
    assert report(fetchsync("push", "--json", "--dry-run", env=env))["files"] == 1
    assert tree_of(robot_ws(env)) == before


def test_a_dry_run_reports_the_conflicts_the_real_push_meets(env):
    """Issue 22 item 24: the conflicts a dry run reports are the real push's; with
    --strict both exit 6, and the dry run changed nothing on the robot."""
    src, ws = local_src(env), robot_ws(env)
    assert report(fetchsync("push", "--json", env=env))["ok"]
    (ws / "src/my_pkg/package.xml").write_text("<edited on the robot/>\n")
    (ws / "src/my_pkg/scripts/fix.py").write_text("# new on the robot\n")
    shutil.rmtree(src / "my_pkg/scripts")  # deletes a directory holding a robot-side file
    (src / "my_pkg/package.xml").write_text("<edited here/>\n")
    (src / "my_pkg/CMakeLists.txt").write_text("project(my_pkg)  # edited here only\n")
    (ws / "src/my_pkg/src/node.cpp").write_text("// edited on the robot\n")
    (src / "my_pkg/src/node.cpp").chmod(0o755)  # only a chmod here
    before = tree_of(ws)  # its index in .fetchsync/ included
    dry = report(fetchsync("push", "--json", "--dry-run", env=env))
    assert tree_of(ws) == before
    want = ["my_pkg/package.xml", "my_pkg/scripts", "my_pkg/src/node.cpp"]
    assert sorted(c["path"] for c in dry["conflicts"]) == want
    strict_dry = fetchsync("push", "--json", "--dry-run", "--strict", env=env, check=False)
    assert strict_dry.returncode == 6 and tree_of(ws) == before
    strict = fetchsync("push", "--json", "--strict", env=env, check=False)
    assert strict.returncode == 6
    assert sorted(c["path"] for c in json.loads(strict.stdout)["conflicts"]) == want
    real = report(fetchsync("push", "--json", env=env))
    assert sorted(c["path"] for c in real["conflicts"]) == want


def test_deletions_in_quick_succession_count_as_one(engine):
    """The watch agent sees an rm -rf as several batches: small ones in quick succession
    add up, so the guard still stops most of the deletion."""
    s, src, ws = engine
    many_files(src)
    assert s.push().errors == []
    for i in range(15):
        (src / f"my_pkg/many/f{i}.txt").unlink()
    assert s.push_paths({f"my_pkg/many/f{i}.txt" for i in range(15)}).deleted == 15
    for i in range(15, 40):
        (src / f"my_pkg/many/f{i}.txt").unlink()
    with pytest.raises(
        sync.MassDeletionError, match="15 of them deleted by the pushes just before"
    ):
        s.push_paths({f"my_pkg/many/f{i}.txt" for i in range(15, 40)})
    assert len(list((ws / "src/my_pkg/many").iterdir())) == 25


def test_deletions_add_up_however_long_each_push_took(engine, monkeypatch):
    """A slow link or a busy machine spreads an rm -rf over batches whose pushes take
    longer than the guard's window: the chain is measured from the end of the last
    deleting push, so they still add up (the engine's clock is made to run 15 s during
    the first push, and 2 s between the two)."""
    s, src, ws = engine
    many_files(src)
    assert s.push().errors == []
    clock = [1000.0]
    fake = types.SimpleNamespace(
        **{n: getattr(time, n) for n in dir(time) if not n.startswith("_")}
    )
    fake.monotonic = lambda: clock[0]
    monkeypatch.setattr(sync, "time", fake)
    real_run = sync.Round.run

    def slow_run(self, *args, **kwargs):
        clock[0] += 15.0  # the push takes 15 s after its deletions were counted
        return real_run(self, *args, **kwargs)

    monkeypatch.setattr(sync.Round, "run", slow_run)
    for i in range(15):
        (src / f"my_pkg/many/f{i}.txt").unlink()
    assert s.push_paths({f"my_pkg/many/f{i}.txt" for i in range(15)}).deleted == 15
    clock[0] += 2.0
    for i in range(15, 40):
        (src / f"my_pkg/many/f{i}.txt").unlink()
    with pytest.raises(sync.MassDeletionError, match="15 of them deleted by the pushes just"):
        s.push_paths({f"my_pkg/many/f{i}.txt" for i in range(15, 40)})
    assert len(list((ws / "src/my_pkg/many").iterdir())) == 25


@pytest.mark.skipif(
    os.geteuid() == 0 and SETPRIV is None, reason="needs setpriv (util-linux) as root"
)
def test_pull_works_on_a_read_only_robot(env):
    """Issue 22 items 24 and 25: pull opens the robot read-only and writes nothing there
    (no lock, no index), so a robot whose workspace cannot be written is pulled from."""
    src, ws = local_src(env), robot_ws(env)
    assert report(fetchsync("push", "--json", env=env))["ok"]
    (ws / "src/my_pkg/package.xml").write_text("<fixed on the robot/>\n")
    before = tree_of(ws)
    cmd = [sys.executable, "-m", "fetchsync", "pull", "--yes", "--json"]
    if os.geteuid() == 0:  # root's power to write anywhere, taken away
        cmd = [SETPRIV, "--bounding-set", "-dac_override,-dac_read_search", "--", *cmd]
    # the endpoint's own directory read-only (src's modes are what pull mirrors)
    dirs = [p for p in [ws, *(ws / ".fetchsync").rglob("*")] if p.is_dir() and not p.is_symlink()]
    dirs.append(ws / ".fetchsync")
    modes = {d: stat.S_IMODE(d.stat().st_mode) for d in dirs}
    for d in dirs:
        d.chmod(0o555)
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, timeout=120, check=False)
    finally:
        for d, mode in modes.items():
            d.chmod(mode)
    assert proc.returncode == 0, (proc.stderr.decode(), proc.stdout.decode())
    assert (src / "my_pkg/package.xml").read_text() == "<fixed on the robot/>\n"
    assert tree_of(ws) == before
    # the next push finds both ends alike
    assert report(fetchsync("push", "--json", env=env))["files"] == 0
