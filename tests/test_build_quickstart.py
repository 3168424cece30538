"""The README's ROS 2 quickstart, run as written against the sshd robot with the real colcon.

The block after ``<!-- ros2-quickstart -->`` runs in bash with the laptop's HOME
of the test, ``fetch7.local`` replaced by the test's robot, and the robot's
workspace in the test's directory (the robot is this machine: its ``~`` is
the real home of the login user). Its last line, ``watch --build``, runs in
the background while the test saves a change, as a user would in an editor.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from helpers import clean_env

pytestmark = [
    pytest.mark.ssh,
    pytest.mark.skipif(shutil.which("colcon") is None, reason="colcon not installed"),
]

README = Path(__file__).resolve().parent.parent / "README.md"
REPO = README.parent


def quickstart() -> list[str]:
    """The lines of the README's ROS 2 quickstart block."""
    text = README.read_text()
    m = re.search(r"<!-- ros2-quickstart -->\n```sh\n(.*?)\n```", text, re.S)
    assert m, "the README has no ROS 2 quickstart block"
    return m.group(1).replace("fetch7.local", "robot").split("\n")


def _bash(script: str, env: dict[str, str], **kwargs) -> subprocess.CompletedProcess[str]:
    prelude = f'fetchsync() {{ "{sys.executable}" -m fetchsync "$@"; }}\n'
    return subprocess.run(
        ["bash", "-ec", prelude + script],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
        **kwargs,
    )


@pytest.mark.slow
def test_the_readme_ros2_quickstart_runs_as_written(ssh_home, remote_dir, tmp_path):
    lines = quickstart()
    assert lines[-1].startswith("fetchsync watch --build")
    setup, watch_line = "\n".join(lines[:-1]), lines[-1]
    exports = "\n".join(ln for ln in lines if ln.startswith("export "))
    env = clean_env(
        HOME=str(ssh_home.home),
        FETCHSYNC_REMOTE_WORKSPACE=str(remote_dir),
        XDG_STATE_HOME=str(tmp_path / "state"),
        PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
    )
    proc = _bash(setup, env)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (
        "fetchsync: build tool: colcon (talker is a ROS 2 package (build type cmake)" in proc.stderr
    ), proc.stderr
    assert proc.stdout.endswith("hello from the robot\n"), proc.stdout
    assert (remote_dir / "install/talker/bin/talker").is_file()

    runtime = Path(tempfile.mkdtemp(prefix="fsqs", dir="/tmp"))
    runtime.chmod(0o700)
    log = tmp_path / "watch.log"
    watch = subprocess.Popen(
        [
            "bash",
            "-c",
            f'fetchsync() {{ exec "{sys.executable}" -m fetchsync "$@"; }}\n'
            f"{exports}\n{watch_line}",
        ],
        env=dict(env, XDG_RUNTIME_DIR=str(runtime)),
        stdout=open(log, "wb"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    text = lambda: log.read_text(errors="replace")  # noqa: E731
    try:
        end = time.monotonic() + 30
        while " live: " not in text() and time.monotonic() < end:
            time.sleep(0.05)
        assert " live: " in text(), text()
        source = ssh_home.home / "ros2_ws/src/talker/src/talker.cpp"
        source.write_text(source.read_text().replace("hello from the robot", "hello again"))
        end = time.monotonic() + 60
        while (
            "build: ok: talker" not in text()
            and "build failed" not in text()
            and time.monotonic() < end
        ):
            time.sleep(0.05)
        assert "build: colcon build --packages-above talker (on robot)" in text(), text()
        assert "build: ok: talker" in text(), text()
        proc = _bash(f"{exports}\nfetchsync run talker", env)
        assert proc.stdout == "hello again\n", proc.stdout + proc.stderr
    finally:
        os.killpg(watch.pid, signal.SIGTERM)
        try:
            watch.wait(15)
        except subprocess.TimeoutExpired:
            os.killpg(watch.pid, signal.SIGKILL)
            watch.wait()
        shutil.rmtree(runtime, ignore_errors=True)
        print(text())
