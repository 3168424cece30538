"""The laptop's memory during a pull is bounded by a part (about BATCH_BYTES of content and
the next part's reads), not by what the robot holds: a pull fetched every file, kept all
of their content and joined it for one apply (80 MiB pulled peaked at 221 MiB; a robot
listing a 10 GB file had the laptop hold 10 GB). Over the real sshd; the peak is the
pulling process's own (ru_maxrss of the child that runs the CLI)."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import report, ssh_env, tree_of

from fetchsync.link.connection import Connection
from fetchsync.link.ssh import SSHTransport
from fetchsync.sync import engine
from fetchsync.sync.state import State

pytestmark = [pytest.mark.ssh, pytest.mark.slow]

MiB = 1 << 20
PEAK = """
import resource, subprocess, sys
proc = subprocess.run(sys.argv[1:], capture_output=True)
sys.stderr.buffer.write(proc.stderr)
sys.stdout.buffer.write(proc.stdout)
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024)
sys.exit(proc.returncode)
"""


def pull_peak(env: dict[str, str]) -> tuple[dict, int]:
    """The pull's report and its process's peak resident memory in bytes."""
    proc = subprocess.run(
        [sys.executable, "-c", PEAK, sys.executable, "-m", "fetchsync"]
        + ["pull", "--json", "--yes", "--no-safety"],
        capture_output=True,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr.decode()
    lines = proc.stdout.decode().strip().splitlines()
    return report(subprocess.CompletedProcess([], 0, lines[-2].encode())), int(lines[-1])


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_pull_of_150_mib_holds_a_part_not_the_whole(ssh_home, remote_dir, tmp_path):
    env = ssh_env(ssh_home.home, remote_dir, tmp_path)
    robot = remote_dir / "src/data"
    robot.mkdir(parents=True)
    for i in range(25):  # whole files, read in requests of about 8 MiB
        (robot / f"scan{i:02d}.bin").write_bytes(os.urandom(4 * MiB))
    (robot / "big.bin").write_bytes(os.urandom(48 * MiB))  # in pieces (over BIG)
    (robot / "note.txt").write_text("after the big one in the plan's order\n")
    r, peak = pull_peak(env)
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    assert r["ok"] and r["files"] == 27, r
    assert digest(local / "data/big.bin") == digest(robot / "big.bin")
    assert tree_of(local / "data") == tree_of(robot)
    # ~85 MiB with parts (the interpreter and its imports ~45); 400+ when held whole
    assert peak < 150 * MiB, f"the pull peaked at {peak / MiB:.0f} MiB"
    assert not list((Path(env["FETCHSYNC_WORKSPACE"]) / ".fetchsync/tmp").glob("upload-*"))


def test_a_large_file_that_changes_while_pulled_leaves_no_upload_part(
    ssh_home, remote_dir, tmp_path, monkeypatch
):
    """Its pieces are applied as they come: when the file is not the one listed at its
    end, the part they made is removed and the laptop's file left as it was."""
    robot = remote_dir / "src/data"
    robot.mkdir(parents=True)
    (robot / "big.bin").write_bytes(os.urandom(40 * MiB))
    (robot / "small.txt").write_text("small\n")
    real = engine.Endpoint.read
    calls = []

    def read(self, items):  # the robot's file grows between two pieces
        calls.append(items)
        if len(calls) == 2:
            with open(robot / "big.bin", "ab") as fh:
                fh.write(b"appended on the robot meanwhile")
        return real(self, items)

    monkeypatch.setattr(engine.Endpoint, "read", read)
    ws = tmp_path / "ws"
    (ws / "src").mkdir(parents=True)
    conn = Connection.open(SSHTransport.connect("robot", connect_timeout=10.0))
    state = State(tmp_path / "state.sqlite")
    try:
        rep = engine.pull(
            conn,
            state,
            local_workspace=str(ws),
            remote_workspace=str(remote_dir),
            rules=engine.build_rules(),
            confirm=lambda _report: True,
        )
    finally:
        conn.close()
        state.close()
    assert len(calls) >= 3  # read in pieces
    assert [e["path"] for e in rep.errors] == ["data/big.bin"]
    assert not (ws / "src/data/big.bin").exists()
    assert (ws / "src/data/small.txt").read_text() == "small\n"
    assert not list((ws / ".fetchsync/tmp").glob("upload-*"))
