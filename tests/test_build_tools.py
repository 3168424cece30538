"""The three build tools for real on the sshd robot: catkin_make, ``catkin build``, colcon.

For each, one workspace of two packages (``beta`` includes ``alpha``'s header,
see ``ros_workspaces.py``) goes through what a user does: ``push --build``
builds both in order, ``run`` runs the built program, a compile error's output
and exit status reach the user, ``--build-tool auto`` finds the tool again
from what the first build left on the robot, and ``watch --build`` rebuilds
what a change touched (colcon: and what depends on it).
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from helpers import fetchsync, ssh_env
from ros_workspaces import (
    GREETING,
    SYSTEM_PYTHON_DEFINE,
    catkin_workspace,
    colcon_workspace,
    set_greeting,
)

pytestmark = pytest.mark.ssh


@dataclass(frozen=True)
class Tool:
    name: str  # --build-tool's
    program: str  # what must be on PATH
    make: object  # the workspace builder
    args: str  # the build's arguments
    hello: str  # how `run` reaches the built program ({ws}: the remote workspace)
    detected: str  # the command auto detection runs after the first build


TOOLS = [
    Tool(
        "catkin_make",
        "catkin_make",
        catkin_workspace,
        SYSTEM_PYTHON_DEFINE,
        "{ws}/devel/lib/beta/beta_hello",
        "catkin_make " + SYSTEM_PYTHON_DEFINE,
    ),
    Tool(
        "catkin",
        "catkin",
        catkin_workspace,
        "--cmake-args " + SYSTEM_PYTHON_DEFINE,
        "{ws}/devel/lib/beta/beta_hello",
        "catkin build --cmake-args " + SYSTEM_PYTHON_DEFINE,
    ),
    Tool("colcon", "colcon", colcon_workspace, "", "beta_hello", "colcon build"),
]


def _wait_for(cond, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def _hello(tool: Tool, remote_dir: Path, env: dict[str, str]) -> str:
    proc = fetchsync("run", "--", tool.hello.format(ws=remote_dir), env=env)
    return proc.stdout.decode().strip()


@pytest.mark.slow
@pytest.mark.parametrize("tool", TOOLS, ids=[t.name for t in TOOLS])
def test_build_run_fail_and_watch_with_the_real_tool(tool, ssh_home, remote_dir, tmp_path):
    if shutil.which(tool.program) is None:
        pytest.skip(f"{tool.program} not installed (pip install -e '.[test]')")
    if shutil.which("catkin_make") is None and tool.make is catkin_workspace:
        pytest.skip("catkin not installed (apt-get install catkin)")
    env = ssh_env(ssh_home.home, remote_dir, tmp_path, make_ws=False)
    src = tool.make(tmp_path / "ws") / "src"
    build = f"--build={tool.args}"

    # the first build: the tool is chosen; both packages build, alpha first
    proc = fetchsync("push", "--build-tool", tool.name, build, env=env)
    err = proc.stderr.decode()
    assert f"{tool.detected} (on robot)" in err, err
    assert _hello(tool, remote_dir, env) == GREETING

    # a compile error: its output and the tool's exit status reach the user
    hello_cpp = src / "beta/src/hello.cpp"
    good = hello_cpp.read_text()
    hello_cpp.write_text(good.replace("return 0;", "return undefined_on_purpose;"))
    proc = fetchsync("push", build, env=env, check=False)
    out = proc.stdout.decode() + proc.stderr.decode()
    assert "undefined_on_purpose" in out, out
    assert proc.returncode not in (0, 255), out
    assert f"{tool.detected} failed on robot with exit status {proc.returncode}" in out, out
    # auto detection found the tool from what the first build left on the robot
    assert f"build tool: {tool.name}" in out, out
    assert "Traceback" not in out
    hello_cpp.write_text(good)

    # watch --build: a change rebuilds the package it touched
    log = tmp_path / "watch.log"
    runtime = _short_dir()
    watch_env = dict(env, XDG_RUNTIME_DIR=str(runtime))
    watch = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fetchsync",
            "watch",
            f"--build-args={tool.args}" if tool.args else "--build",
        ],
        env=watch_env,
        stdout=open(log, "wb"),
        stderr=subprocess.STDOUT,
    )
    text = lambda: log.read_text(errors="replace")  # noqa: E731
    try:
        _wait_for(lambda: " live: " in text(), 30, "watch to be live")
        # the broken hello.cpp of the failed push is on the robot: watch's first sync fixes
        # it, and a first sync is built whole
        _wait_for(
            lambda: "build: ok: " in text() or "build failed" in text(), 60, "the first build"
        )
        assert "build: ok: everything" in text(), text()
        assert _hello(tool, remote_dir, env) == GREETING
        mark = len(text())
        set_greeting(src, "hello again")
        _wait_for(
            lambda: "build: ok: alpha" in text()[mark:] or "build failed" in text()[mark:],
            60,
            "the build of alpha",
        )
        after = text()[mark:]
        assert "build: ok: alpha" in after, after
        if tool.name == "colcon":
            # colcon builds what depends on a changed package too: beta sees alpha's header
            assert "--packages-above alpha" in after, after
            assert "Finished <<< beta" in after, after
            assert _hello(tool, remote_dir, env) == "hello again"
        elif tool.name == "catkin_make":
            # catkin_make --pkg makes the named packages only
            assert f"catkin_make {tool.args} --pkg alpha (on robot)" in after, after
        else:
            # catkin build builds the named packages and what they depend on, not their users
            assert f"catkin build alpha {tool.args} (on robot)" in after, after
    finally:
        watch.send_signal(signal.SIGTERM)
        try:
            watch.wait(15)
        except subprocess.TimeoutExpired:
            watch.kill()
            watch.wait()
        shutil.rmtree(runtime, ignore_errors=True)
        print(text())


def _short_dir() -> Path:
    """A private runtime directory with a short path (AF_UNIX sockets live there)."""
    import tempfile

    d = Path(tempfile.mkdtemp(prefix="fsbt", dir="/tmp"))
    d.chmod(0o700)
    return d
