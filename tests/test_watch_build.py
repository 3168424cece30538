"""fetchsync watch --build: the real catkin_make on the sshd robot, package by package,
a newer batch cancelling a slow build; and the package mapping and commands it uses."""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from helpers import CATKIN_PACKAGE_XML as PACKAGE_XML
from helpers import fetchsync, ssh_env

from fetchsync.agent.builder import package_command, packages_of

SYSTEM_PYTHON = "--build-args=-DPYTHON_EXECUTABLE=/usr/bin/python3"  # see test_build_ssh.py


# each build of a package appends to its log on the robot (this machine); "slow" takes seconds
CMAKELISTS = """cmake_minimum_required(VERSION 3.0.2)
project({name})
find_package(catkin REQUIRED)
catkin_package()
add_custom_target(stamp_{name} ALL COMMAND sh ${{CMAKE_CURRENT_SOURCE_DIR}}/stamp.sh)
"""


def package(src: Path, name: str, command: str, *, directory: str | None = None) -> Path:
    pkg = src / (directory or name)
    pkg.mkdir(parents=True)
    (pkg / "package.xml").write_text(PACKAGE_XML.format(name=name))
    (pkg / "CMakeLists.txt").write_text(CMAKELISTS.format(name=name))
    (pkg / "stamp.sh").write_text(command + "\n")
    return pkg


def wait_for(cond, timeout, what):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def lines(path: Path) -> list[str]:
    return path.read_text().split() if path.exists() else []


# --------------------------------------------------------------------------- pure parts
def test_paths_map_to_the_nearest_package(tmp_path):
    src = tmp_path / "src"
    package(src, "alpha", "true", directory="stack/alpha_dir")  # <name>, not the directory's
    package(src, "beta", "true")
    (src / "stack/alpha_dir/src").mkdir()
    (src / "stack/alpha_dir/src/a.cpp").write_text("")
    (src / "README").write_text("")
    assert packages_of(src, ["stack/alpha_dir/src/a.cpp"]) == {"alpha"}
    assert packages_of(src, ["stack/alpha_dir/src/gone.cpp", "beta/package.xml"]) == {
        "alpha",
        "beta",
    }
    assert packages_of(src, ["README", "stack/notes.txt", "nowhere/x"]) == set()
    assert packages_of(src, [], dirs=["stack"]) == {"alpha"}  # a subtree that arrived whole
    assert packages_of(src, [], dirs=["beta/include"]) == {"beta"}


def test_each_tool_builds_only_the_packages():
    assert package_command("catkin_make", {"b", "a"}, "-j4") == "catkin_make -j4 --pkg a b"
    assert (
        package_command("catkin_make", {"a"}, "", "Release")
        == "catkin_make --pkg a -DCMAKE_BUILD_TYPE=Release"
    )
    assert (
        package_command("catkin", {"a", "b"}, "--cmake-args -DX=1", "Debug")
        == "catkin build a b --cmake-args -DCMAKE_BUILD_TYPE=Debug -DX=1"
    )
    assert (
        package_command("colcon", {"a"}, "--symlink-install")
        == "colcon build --packages-above a --symlink-install"
    )
    assert package_command("colcon", None, "") == "colcon build"


# --------------------------------------------------------------------------- on the robot
@pytest.fixture
def short_runtime():
    """A private XDG_RUNTIME_DIR with a short path (AF_UNIX), removed afterwards."""
    d = Path(tempfile.mkdtemp(prefix="fswb", dir="/tmp"))
    d.chmod(0o700)
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.mark.slow
@pytest.mark.ssh
@pytest.mark.skipif(shutil.which("catkin_make") is None, reason="catkin not installed")
def test_watch_build_rebuilds_changed_packages_and_a_newer_batch_cancels(
    ssh_home, remote_dir, tmp_path, short_runtime
):
    runtime = short_runtime
    logs = tmp_path / "logs"
    logs.mkdir()
    ws = tmp_path / "ws"
    src = ws / "src"
    package(src, "alpha", f"echo built >> {logs}/alpha.log")
    package(src, "beta", f"echo built >> {logs}/beta.log")
    package(src, "slow", f"echo start >> {logs}/slow.log; sleep 5; echo end >> {logs}/slow.log")
    e = ssh_env(ssh_home.home, remote_dir, tmp_path, make_ws=False, XDG_RUNTIME_DIR=str(runtime))
    fetchsync("push", env=e)  # the robot holds the sources already: starting builds nothing
    log = tmp_path / "watch.log"
    proc = subprocess.Popen(
        [sys.executable, "-m", "fetchsync", "watch", SYSTEM_PYTHON],
        env=e,
        stdout=open(log, "wb"),
        stderr=subprocess.STDOUT,
    )

    def out() -> str:
        return log.read_text(errors="replace")

    try:
        wait_for(lambda: " live: " in out(), 20, "live")
        # one package's file changes: that package only is built, its output streamed
        (src / "alpha/notes.txt").write_text("a change\n")
        wait_for(
            lambda: "build: ok: alpha" in out() or "build failed" in out(), 40, "alpha's build"
        )
        assert "build: ok: alpha" in out(), out()
        assert lines(logs / "alpha.log") == ["built"]
        assert not (logs / "beta.log").exists() and not (logs / "slow.log").exists()
        assert "catkin_make -DPYTHON_EXECUTABLE=/usr/bin/python3 --pkg alpha (on robot)" in out()
        assert "build: Base path: " in out()  # catkin_make's own output, prefixed
        # a slow build; a second change during it cancels it and builds both
        (src / "slow/notes.txt").write_text("a change\n")
        wait_for(lambda: lines(logs / "slow.log") == ["start"], 20, "the slow build to start")
        (src / "beta/notes.txt").write_text("a change\n")
        wait_for(
            lambda: "build: ok: beta slow" in out() or "build failed" in out(),
            30,
            "the second build",
        )
        assert "build: cancelled (slow)" in out(), out()
        assert lines(logs / "beta.log") == ["built"]
        time.sleep(1.0)
        # the cancelled build's processes died on the robot: one start without an end
        assert lines(logs / "slow.log") == ["start", "start", "end"], out()
        assert lines(logs / "alpha.log") == ["built"]
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        print(out())
