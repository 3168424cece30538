"""A one-shot push's late signing, done by a process of its own (fetchsync.signer).

End to end through the CLI against the ``local`` robot: the push returns, a
background process signs the text files it sent, and the next push, which
waits for that process, sends an edit as a delta without asking the robot.
The rest are unit tests of the job's lock, the hash checks and the fallback.
"""

from __future__ import annotations

import fcntl
import glob
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import fetchsync, make_workspace, report, tree_of

from fetchsync import signer
from fetchsync.protocol import delta, hashing
from fetchsync.state import State, Synced

TEXTS = 24


@pytest.fixture
def env(tmp_path: Path) -> dict:
    e = dict(os.environ)
    e.update(FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "robot-home"), XDG_STATE_HOME=str(tmp_path / "state"),
             FETCHSYNC_ROBOT="local", FETCHSYNC_WORKSPACE=str(tmp_path / "ws"),
             FETCHSYNC_REMOTE_WORKSPACE="~/robot_ws")
    for k in ("FETCH_ROBOT", "ROS_MASTER_URI"):
        e.pop(k, None)
    src = make_workspace(tmp_path / "ws") / "src"
    for i in range(TEXTS):  # ~22 KiB each: worth a signature
        (src / f"t{i}.txt").write_bytes(b"".join(b"line %d of text file %d\n" % (n, i) for n in range(900)))
    # binary, and more than a batch: the round signs its text files late
    (src / "recording.bag").write_bytes(b"\0" + os.urandom(9 * 1024 * 1024))
    return e


def state_file(env: dict) -> Path:
    (path,) = glob.glob(os.path.join(env["XDG_STATE_HOME"], "fetchsync", "*.sqlite"))
    return Path(path)


def signatures(path: Path) -> dict[str, bytes | None]:
    db = sqlite3.connect(str(path))
    try:
        return {bytes(p).decode(): (bytes(s) if s is not None else None)
                for p, s in db.execute("SELECT path, sig FROM entries WHERE kind='f'")}
    finally:
        db.close()


def test_a_push_leaves_its_signing_to_a_process_the_next_push_waits_for(env, tmp_path):
    r = report(fetchsync("push", "--json", env=env))
    assert r["ok"] and r["files"] >= TEXTS + 1
    path = state_file(env)
    signer.wait(path)  # as the next push does
    assert not [n for n in os.listdir(path.parent) if n.startswith(signer.job_prefix(path))]
    sigs = signatures(path)
    src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    algorithm = hashing.available()[0]
    for i in range(TEXTS):
        data = (src / f"t{i}.txt").read_bytes()
        assert sigs[f"t{i}.txt"] == delta.signature(data, algorithm=algorithm).to_bytes()
    assert sigs["recording.bag"] is None

    # the next push finds them: an insert at the top of two files goes as two deltas
    for name in ("t0.txt", "t1.txt"):
        (src / name).write_bytes(b"a line inserted at the top\n" + (src / name).read_bytes())
    again = report(fetchsync("push", "--json", env=env))
    assert again["ok"] and again["files"] == 2 and again["deltas"] == 2
    assert again["bytes_sent"] < 8 * 1024  # not 44 KiB of files
    assert tree_of(src) == tree_of(tmp_path / "robot-home" / "robot_ws" / "src")


def test_the_next_push_waits_for_a_signing_under_way(env, tmp_path):
    fetchsync("push", "--json", env=env)
    path = state_file(env)
    signer.wait(path)
    # a signing that is still running: its job is locked by a live process
    job = path.parent / (signer.job_prefix(path) + "test.json")
    job.write_text("{}")
    done = tmp_path / "signed"
    code = ("import fcntl, sys, time\n"
            f"fd = open({str(job)!r}); fcntl.flock(fd, fcntl.LOCK_EX)\n"
            "print('locked', flush=True); time.sleep(1.0)\n"
            f"open({str(done)!r}, 'w').close()")
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    try:
        assert holder.stdout is not None and holder.stdout.readline() == b"locked\n"
        src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
        (src / "t3.txt").write_bytes(b"changed\n" + (src / "t3.txt").read_bytes())
        again = report(fetchsync("push", "--json", env=env))
        assert again["ok"]
        assert done.exists()  # the push waited until the lock's holder was done
        assert not job.exists()  # unlocked and left behind: the push removed it
    finally:
        holder.kill()
        holder.wait()


def test_wait_removes_a_job_whose_process_died_and_gives_up_on_a_stuck_one(tmp_path):
    path = tmp_path / "x.sqlite"
    dead = tmp_path / (signer.job_prefix(path) + "dead.json")
    dead.write_text("{}")
    other = tmp_path / ".y.sqlite.sign-keep.json"  # another state's job is not ours to judge
    other.write_text("{}")
    signer.wait(path)
    assert not dead.exists() and other.exists()

    stuck = tmp_path / (signer.job_prefix(path) + "stuck.json")
    stuck.write_text("{}")
    with open(stuck) as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        signer.wait(path, timeout=0.2)  # returns without the lock
        assert stuck.exists()


def test_signatures_are_kept_only_for_the_content_the_state_holds(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    algorithm = hashing.available()[0]
    same = b"a line\n" * 3000
    (src / "same.txt").write_bytes(same)
    (src / "edited.txt").write_bytes(b"edited since it was sent\n" * 800)
    sent = b"what was sent\n" * 1500
    items = [("same.txt", hashing.digest(algorithm, same).hex(), len(same)),
             ("edited.txt", hashing.digest(algorithm, sent).hex(), len(sent)),
             ("gone.txt", hashing.digest(algorithm, sent).hex(), len(sent))]
    rows = list(signer.sign_files(str(src), algorithm, items))
    assert [r[0] for r in rows] == ["same.txt"]  # read again, and the hash still holds

    state = State(tmp_path / "state.sqlite")
    try:
        def entry(digest: str) -> Synced:
            return Synced("f", 0o644, digest, "", len(same), 1, 1, 1)

        newer = hashing.digest(algorithm, b"pushed again since").hex()
        state.commit(upserts=[("same.txt", entry(items[0][1]), None), ("moved.txt", entry(newer), None)])
        # a row whose content changed since (a later push) gets no signature
        state.add_signatures(rows + [("moved.txt", items[0][1], b"stale")])
        assert state.signature("same.txt") == rows[0][2]
        assert state.signature("moved.txt") is None
        # one already there is left as it is
        state.add_signatures([("same.txt", items[0][1], b"other")])
        assert state.signature("same.txt") == rows[0][2]
    finally:
        state.close()


def test_a_push_signs_in_process_when_the_signer_cannot_start(env, tmp_path, monkeypatch):
    from fetchsync import sync
    from fetchsync.connection import Connection
    from fetchsync.transport import LocalTransport

    started: list[int] = []
    monkeypatch.setattr(signer, "start", lambda *a, **k: bool(started.append(1)))
    src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    state = State(tmp_path / "state.sqlite")
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    try:
        syncer = sync.Syncer(conn, state, local_root=str(src), remote_workspace="~/ws",
                             rules=sync.build_rules(), sign_apart=True)
        assert syncer.push().errors == []
        assert all(state.signature(f"t{i}.txt") is None for i in range(TEXTS))  # not yet
        syncer.sign_apart_now()
        assert started == [1]
        for i in range(TEXTS):
            data = (src / f"t{i}.txt").read_bytes()
            assert state.signature(f"t{i}.txt") == delta.signature(data, algorithm=conn.algorithm).to_bytes()
    finally:
        conn.close()
        state.close()
    assert not list(tmp_path.glob(".state.sqlite.sign-*"))  # no job was made
