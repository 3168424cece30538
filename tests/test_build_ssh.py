"""push/pull --build and --install-deps end to end: the real catkin_make of the OS packages,
on the sshd robot (push) and here (pull)."""

from __future__ import annotations

import shutil
import stat
from pathlib import Path

import pytest
from helpers import CATKIN_PACKAGE_XML as PACKAGE_XML
from helpers import fetchsync, report, ssh_env
from terminal import Terminal

pytestmark = [
    pytest.mark.ssh,
    pytest.mark.skipif(shutil.which("catkin_make") is None, reason="catkin not installed"),
]

# The system's Python has catkin's modules; a python3 of pyenv or a venv first on
# PATH (CI, and the robot's login shell here) has not, and CMake would find that one.
SYSTEM_PYTHON = "--build=-DPYTHON_EXECUTABLE=/usr/bin/python3"


CMAKELISTS = """cmake_minimum_required(VERSION 3.0.2)
project({name})
find_package(catkin REQUIRED)
catkin_package()
{extra}
"""


def catkin_workspace(root: Path, *, name: str = "tiny", extra: str = "") -> Path:
    pkg = root / "src" / name
    pkg.mkdir(parents=True)
    (pkg / "package.xml").write_text(PACKAGE_XML.format(name=name))
    (pkg / "CMakeLists.txt").write_text(CMAKELISTS.format(name=name, extra=extra))
    return root


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    return ssh_env(ssh_home.home, remote_dir, tmp_path, make_ws=False)


def _cache_value(build_dir: Path, name: str) -> str:
    for line in (build_dir / "CMakeCache.txt").read_text().splitlines():
        if line.startswith(name + ":"):
            return line.split("=", 1)[1]
    raise AssertionError(f"{name} not in the CMake cache")


@pytest.mark.slow
def test_push_build_runs_catkin_make_on_the_robot(env, remote_dir, tmp_path):
    catkin_workspace(tmp_path / "ws")
    proc = fetchsync("push", SYSTEM_PYTHON, env=env)
    assert b"catkin_make -DPYTHON_EXECUTABLE=/usr/bin/python3 (on robot)" in proc.stderr
    assert (remote_dir / "devel/setup.bash").is_file()
    assert (remote_dir / "build/CMakeCache.txt").is_file()
    # catkin_make made its toplevel link on the robot; locally there is none
    assert (remote_dir / "src/CMakeLists.txt").is_symlink()
    assert not (tmp_path / "ws/devel").exists()
    # the build's output streamed to ours
    assert b"Build space: " + str(remote_dir / "build").encode() in proc.stdout
    # the next push builds again, in the environment of the devel space it made
    fetchsync("push", SYSTEM_PYTHON, "--build-type", "Release", env=env)
    assert _cache_value(remote_dir / "build", "CMAKE_BUILD_TYPE") == "Release"


@pytest.mark.slow
def test_each_build_option_is_one_build_in_order(env, remote_dir, tmp_path):
    catkin_workspace(tmp_path / "ws")
    proc = fetchsync(
        "push", SYSTEM_PYTHON, "--build", "install", "--build-type", "Debug", "--json", env=env
    )
    assert report(proc)["ok"]  # with --json, stdout holds the report only
    err = proc.stderr.decode()
    first = err.index("catkin_make -DPYTHON_EXECUTABLE=/usr/bin/python3 -DCMAKE_BUILD_TYPE=Debug")
    assert first < err.index("catkin_make install -DCMAKE_BUILD_TYPE=Debug")
    assert (remote_dir / "install/setup.bash").is_file()
    assert _cache_value(remote_dir / "build", "CMAKE_BUILD_TYPE") == "Debug"


def test_a_failing_build_fails_push_with_the_builds_exit_code(env, remote_dir, tmp_path):
    catkin_workspace(tmp_path / "ws", extra='message(FATAL_ERROR "broken on purpose")')
    proc = fetchsync("push", SYSTEM_PYTHON, env=env, check=False)
    assert b"broken on purpose" in proc.stderr
    assert proc.returncode == 1  # catkin_make's, whatever failed under it
    assert (
        b"catkin_make -DPYTHON_EXECUTABLE=/usr/bin/python3 failed on robot with exit status 1"
        in proc.stderr
    )
    assert b"Traceback" not in proc.stderr


def test_a_dry_run_builds_nothing(env, remote_dir, tmp_path):
    catkin_workspace(tmp_path / "ws")
    fetchsync("push", "--dry-run", SYSTEM_PYTHON, "--install-deps", env=env)
    assert not (remote_dir / "build").exists()


def test_pull_build_builds_here(env, remote_dir, tmp_path):
    catkin_workspace(remote_dir)
    local = tmp_path / "ws"
    local.mkdir()
    proc = fetchsync("pull", "--yes", SYSTEM_PYTHON, "--build-type", "RelWithDebInfo", env=env)
    assert b"(on this machine)" in proc.stderr
    assert (local / "devel/setup.bash").is_file()
    assert _cache_value(local / "build", "CMAKE_BUILD_TYPE") == "RelWithDebInfo"
    assert not (remote_dir / "build").exists()


def _fake_tool(bin_dir: Path, name: str, *, log: Path, fail_on: str | None = None) -> None:
    """A stand-in for ``name`` that records its argv and working directory."""
    bin_dir.mkdir(parents=True, exist_ok=True)
    tool = bin_dir / name
    fail = (
        f'[ "$1" = {fail_on} ] && {{ echo "{name}: cannot {fail_on}" >&2; exit 4; }}\n'
        if fail_on
        else ""
    )
    tool.write_text(f'#!/bin/sh\necho "{name} $* in $PWD" >> {log}\n{fail}exit 0\n')
    tool.chmod(tool.stat().st_mode | stat.S_IXUSR)


def _fake_rosdep_on_the_robot(remote_dir: Path, *, fail_on: str | None = None) -> Path:
    # rosdep needs the network: the workspace's setup file puts a fake one first on PATH
    log = remote_dir / "rosdep.log"
    _fake_tool(remote_dir / "fakebin", "rosdep", log=log, fail_on=fail_on)
    (remote_dir / "devel").mkdir(exist_ok=True)
    (remote_dir / "devel/setup.bash").write_text(f'export PATH="{remote_dir}/fakebin:$PATH"\n')
    return log


def test_install_deps_runs_rosdep_in_the_workspace_on_the_robot(env, remote_dir, tmp_path):
    catkin_workspace(tmp_path / "ws")
    log = _fake_rosdep_on_the_robot(remote_dir)
    fetchsync("push", "--install-deps", env=env)
    assert log.read_text().splitlines() == [
        f"rosdep update in {remote_dir}",
        f"rosdep install --from-paths src --ignore-src -y in {remote_dir}",
    ]


def test_a_failing_rosdep_fails_push_clearly_and_builds_nothing(env, remote_dir, tmp_path):
    catkin_workspace(tmp_path / "ws")
    log = _fake_rosdep_on_the_robot(remote_dir, fail_on="install")
    proc = fetchsync("push", "--install-deps", SYSTEM_PYTHON, env=env, check=False)
    assert proc.returncode == 4
    err = proc.stderr.decode()
    assert "rosdep: cannot install" in err
    assert (
        "rosdep install --from-paths src --ignore-src -y failed on robot with exit status 4" in err
    )
    assert len(log.read_text().splitlines()) == 2
    assert not (remote_dir / "build").exists()


def test_pull_with_a_chosen_tool_runs_it_here(env, remote_dir, tmp_path):
    catkin_workspace(remote_dir)
    log = tmp_path / "colcon.log"
    _fake_tool(tmp_path / "bin", "colcon", log=log)
    env = dict(env, PATH=f"{tmp_path / 'bin'}:{env['PATH']}")
    fetchsync(
        "pull",
        "--yes",
        "--build-tool",
        "colcon",
        "--build=--symlink-install",
        "--build-type",
        "Release",
        env=env,
    )
    assert log.read_text() == (
        f"colcon build --symlink-install --cmake-args "
        f"-DCMAKE_BUILD_TYPE=Release in {tmp_path / 'ws'}\n"
    )


def test_a_failing_build_here_fails_pull_with_its_exit_code(env, remote_dir, tmp_path):
    catkin_workspace(remote_dir)
    _fake_tool(tmp_path / "bin", "colcon", log=tmp_path / "colcon.log", fail_on="build")
    env = dict(env, PATH=f"{tmp_path / 'bin'}:{env['PATH']}")
    proc = fetchsync("pull", "--yes", "--build-tool", "colcon", "--build", env=env, check=False)
    assert proc.returncode == 4
    assert b"colcon build failed on this machine with exit status 4" in proc.stderr


def test_at_a_terminal_rosdep_gets_one_so_sudo_can_ask(env, remote_dir, tmp_path):
    catkin_workspace(tmp_path / "ws")
    log = _fake_rosdep_on_the_robot(remote_dir)
    (remote_dir / "fakebin/rosdep").write_text(f'#!/bin/sh\necho "rosdep $1 on $(tty)" >> {log}\n')
    term = Terminal(["push", "--install-deps"], env)
    try:
        assert term.wait() == 0, term.output
    finally:
        term.close()
    lines = log.read_text().splitlines()
    assert [line.split(" on ")[0] for line in lines] == ["rosdep update", "rosdep install"]
    assert all(" on /dev/pts/" in line for line in lines)
