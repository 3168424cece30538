"""Ctrl-C ends a push the resident makes, as it ends one made the normal way.

With a resident, ``fetchsync push`` only asks (the push is the resident's); the first
Ctrl-C used to end the asking process while the resident went on and finished the push:
a push the user stopped on seeing it was the wrong one (a checkout of the wrong branch)
still reached the robot. The resident now stops the push when its caller hangs up, as a
killed push stops: nothing torn, the state behind the robot, the next push converges.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import fetchsync, report, tree_of
from test_faults import bulky_files
from test_mux_spare import masters, wait_for
from test_resident import resident_env, residents, traced

pytestmark = pytest.mark.ssh


@pytest.fixture
def env(proxied_home, remote_dir, tmp_path):
    """The robot behind the fault proxy, so the test can throttle the push."""
    yield from resident_env(proxied_home.home, remote_dir, tmp_path)


def test_ctrl_c_ends_the_residents_push(env, fault_proxy, remote_dir):
    runtime = Path(env["XDG_RUNTIME_DIR"])
    src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    first = report(fetchsync("push", "--json", env=env))
    if first["connection"] == "ssh":
        assert wait_for(lambda: bool(masters(runtime)))
    assert wait_for(lambda: bool(residents(runtime)))
    assert wait_for(lambda: any("resident: connected" in ln for ln in traced(env)))
    bulky_files(src, count=60)  # 3.8 MiB of noise: ~13 s at 300 kB/s
    fault_proxy.throttle(bytes_per_second=300_000)
    proc = subprocess.Popen(
        [sys.executable, "-m", "fetchsync", "push"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert wait_for(lambda: any("resident: push asked" in ln for ln in traced(env)))
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and b"interrupted" in err, err
    fault_proxy.pass_through()

    def ended() -> bool:
        return any(
            "resident: pushed" in ln or "resident: the caller hung up" in ln for ln in traced(env)
        )

    assert wait_for(ended, 60)
    assert not any("resident: pushed" in ln for ln in traced(env)), "it went on after Ctrl-C"
    time.sleep(1)
    assert len(list((remote_dir / "src/bulk").glob("*.bin"))) < 60
    # and nothing is lost or torn: the next push converges
    fetchsync("push", env=env)
    assert tree_of(src) == tree_of(remote_dir / "src")
