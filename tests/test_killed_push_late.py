"""A killed push's bytes are not carried on to the robot once it is gone (the master).

The attack (redteam, session 22): a push through the connection master whose robot
endpoint stalls (SIGSTOP: a robot swapping, a frozen disk) fills the SSH window; the
master's thread forwarding the caller's bytes then blocks in the channel's send and
no longer watched the caller. Killed (SIGKILL, Ctrl-C, its deadline), the push left
its channel open and the rest of what it had written in the master's socket: once the
endpoint went on, the master carried that tail to it (a complete request in it would
then be applied after the push had gone, after a later push that found nothing to
do), and the endpoint lingered until the tail was through (test_faults.py's
stalled-endpoint[master] once waited 20 s for it). Now the master closes a caller's
channel as soon as the caller hangs up, also while its send waits for the window, and
forwards nothing it read from a caller that has gone.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import tempfile
import time
import uuid
from pathlib import Path

import pytest
from helpers import fetchsync, ssh_env, tree_of
from test_faults import bulky_files, local_src, marked, signal_all, start, wait_for

pytestmark = pytest.mark.ssh


def test_a_killed_push_through_a_stalled_master_sends_nothing_more(
    fault_proxy, proxied_home, remote_dir, tmp_path
):
    runtime = Path(tempfile.mkdtemp(prefix="fsrun", dir="/tmp"))
    env = ssh_env(
        proxied_home.home,
        remote_dir,
        tmp_path,
        FETCHSYNC_DEADLINE="60",
        FETCHSYNC_PERSIST="60",
        XDG_RUNTIME_DIR=str(runtime),
    )
    mark = uuid.uuid4().hex[:12]
    try:
        src = local_src(env)
        bulky_files(src, count=60)
        fetchsync("push", env=env)
        wait_for(lambda: list((runtime / "fetchsync").glob("mux-*.sock")), 20, "a master")
        bulky_files(src, count=60)  # 3.8 MB of edits: more than the window and pipes hold
        fault_proxy.throttle(bytes_per_second=1_000_000)
        # its own command (not the master's spare), so its endpoint is known by its mark
        proc = start(["push"], dict(env, FETCHSYNC_REMOTE_PYTHON=f"python3 -X fsmark={mark}"))
        wait_for(lambda: marked(mark), 30, "the robot's endpoint")
        time.sleep(0.5)
        stopped = marked(mark)
        signal_all(stopped, signal.SIGSTOP)
        # the window fills: the master blocks sending the push's bytes
        last, since = -1, time.monotonic()
        while time.monotonic() - since < 1.5:
            if fault_proxy.bytes_up != last:
                last, since = fault_proxy.bytes_up, time.monotonic()
            time.sleep(0.1)
        assert proc.poll() is None, "the push ended before it was killed"
        proc.kill()
        proc.wait()
        time.sleep(1.5)  # the master's hang-up watch runs every 0.5 s
        fault_proxy.pass_through()
        fault_proxy.throttle()
        before = fault_proxy.bytes_up
        signal_all(stopped, signal.SIGCONT)
        wait_for(lambda: not marked(mark), 20, "the killed push's endpoint to end")
        carried = fault_proxy.bytes_up - before
        assert carried < 16 * 1024, f"{carried} bytes of the killed push sent after it ended"
        fetchsync("push", env=env)
        assert tree_of(src) == tree_of(Path(remote_dir) / "src")
    finally:
        signal_all(marked(mark), signal.SIGCONT)
        signal_all(marked(mark), signal.SIGKILL)
        subprocess.run(["pkill", "-f", f"fetchsync.link.mux.*{runtime}"], check=False)
        shutil.rmtree(runtime, ignore_errors=True)
