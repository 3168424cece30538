"""A push whose only batch is sent on the caller's thread (4e08fa4: a save's, an edit's,
one large file's) still ends within the progress deadline when the robot's endpoint
stops reading mid-send (the SSH window full: the caller's own send blocks), with one
line and exit 3, and the next push converges. Over the real sshd, direct and through
the master."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import pytest
from helpers import fetchsync, tree_of
from test_faults import (  # noqa: F401 - env and marked_env: fixtures
    assert_one_line_failure,
    env,
    finish,
    local_src,
    marked,
    marked_env,
    signal_all,
    start,
    wait_for,
)

pytestmark = [pytest.mark.ssh, pytest.mark.slow]


@pytest.mark.parametrize("via", ["direct", "master"])
def test_a_stall_mid_send_of_the_only_batch_ends_within_the_deadline(
    via,
    marked_env,  # noqa: F811
    fault_proxy,
    remote_dir,
):
    env, mark = marked_env  # noqa: F811
    runtime = Path(tempfile.mkdtemp(prefix="fsrun", dir="/tmp"))
    if via == "master":
        env = dict(env, FETCHSYNC_PERSIST="60", XDG_RUNTIME_DIR=str(runtime))
    try:
        fetchsync("push", env=dict(env, FETCHSYNC_DEADLINE="30"))
        if via == "master":
            wait_for(lambda: list((runtime / "fetchsync").glob("mux-*.sock")), 20, "a master")
        # one file in one batch (under 8 MiB), incompressible: more than the SSH
        # window and the endpoint's pipe hold
        (local_src(env) / "my_pkg/blob.bin").write_bytes(os.urandom(7 << 20))
        fault_proxy.throttle(bytes_per_second=400_000)
        proc = start(["push"], env)
        wait_for(lambda: marked(mark), 30, "the robot's endpoint")
        time.sleep(1.0)
        stopped = marked(mark)
        signal_all(stopped, signal.SIGSTOP)
        t0 = time.monotonic()
        line = assert_one_line_failure(finish(proc))
        took = time.monotonic() - t0
        assert proc.returncode == 3 and "made no progress" in line, line
        assert took < 20, took  # a generous bound over the 3 s deadline (load)
        signal_all(stopped, signal.SIGCONT)
        fault_proxy.throttle()  # full speed again
        fetchsync("push", env=dict(env, FETCHSYNC_DEADLINE="30"))
        assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
    finally:
        subprocess.run(["pkill", "-f", f"fetchsync.link.mux.*{runtime}"], check=False)
        shutil.rmtree(runtime, ignore_errors=True)


# one read; a large file's pieces, stopped in its second (the first applied as an upload part)
@pytest.mark.parametrize(
    ("size", "rate", "after"), [(7 << 20, 400_000, 1.5), (40 << 20, 4_000_000, 3.0)]
)
def test_a_pull_stalled_mid_answer_ends_within_the_deadline_and_writes_nothing_torn(
    size,
    rate,
    after,
    marked_env,  # noqa: F811
    fault_proxy,
    remote_dir,
):
    """The robot's endpoint stops in the middle of answering a pull's read (the frame
    half sent): the pull ends with one line and exit 3, the laptop holds no part of the
    file (no temporary, no upload part), and the next pull brings it whole."""
    env, mark = marked_env  # noqa: F811
    fetchsync("push", env=dict(env, FETCHSYNC_DEADLINE="30"))
    (remote_dir / "src/my_pkg/from_robot.bin").write_bytes(os.urandom(size))
    fault_proxy.throttle(bytes_per_second=rate)
    proc = start(["pull", "--yes", "--no-safety"], env)
    wait_for(lambda: marked(mark), 30, "the robot's endpoint")
    time.sleep(after)
    stopped = marked(mark)
    signal_all(stopped, signal.SIGSTOP)
    line = assert_one_line_failure(finish(proc))
    assert proc.returncode == 3 and "made no progress" in line, line
    signal_all(stopped, signal.SIGCONT)
    fault_proxy.throttle()  # full speed again
    ws = local_src(env).parent
    assert not (ws / "src/my_pkg/from_robot.bin").exists()
    assert not [p for p in ws.rglob("*") if ".fetchsync-tmp-" in p.name or "upload-" in p.name]
    fetchsync("pull", "--yes", "--no-safety", env=dict(env, FETCHSYNC_DEADLINE="30"))
    assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
