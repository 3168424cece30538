"""Small helpers shared by the end-to-end tests."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

# a minimal catkin package.xml, for the build tests
CATKIN_PACKAGE_XML = """<?xml version="1.0"?>
<package format="2">
  <name>{name}</name>
  <version>0.0.1</version>
  <description>A package for fetchsync's tests.</description>
  <maintainer email="dev@example.com">dev</maintainer>
  <license>BSD</license>
  <buildtool_depend>catkin</buildtool_depend>
</package>
"""


def make_workspace(root: Path) -> Path:
    """A small ROS-like workspace with the shapes a push must handle."""
    src = root / "src"
    pkg = src / "my_pkg"
    (pkg / "scripts").mkdir(parents=True)
    (pkg / "src").mkdir()
    (pkg / "package.xml").write_text("<package format='2'><name>my_pkg</name></package>\n")
    (pkg / "CMakeLists.txt").write_text("cmake_minimum_required(VERSION 3.0.2)\nproject(my_pkg)\n")
    (pkg / "src" / "node.cpp").write_text("int main() { return 0; }\n")
    script = pkg / "scripts" / "run.py"
    script.write_text("#!/usr/bin/env python3\nprint('hi')\n")
    script.chmod(0o755)
    (pkg / "launch").mkdir()  # empty directory
    big = (
        "\n".join(
            f"line {i}: the quick brown fox jumps over the lazy dog {i * 7919 % 10007}"
            for i in range(40000)
        )
        + "\n"
    )
    (pkg / "data.txt").write_text(big)
    # catkin's absolute toplevel link, which rsync -phErtz silently skips
    (src / "CMakeLists.txt").symlink_to("/opt/ros/noetic/share/catkin/cmake/toplevel.cmake")
    (pkg / "rel_link").symlink_to("package.xml")
    return root


def tree_of(root: Path) -> dict[str, tuple]:
    """Everything under root as {relpath: (kind, mode, content or target)}."""
    out = {}
    for dirpath, dirs, files in os.walk(root):
        for name in dirs + files:
            full = Path(dirpath) / name
            rel = str(full.relative_to(root))
            if full.is_symlink():
                out[rel] = ("l", os.readlink(full))
            elif full.is_dir():
                out[rel] = ("d", full.stat().st_mode & 0o7777)
            else:
                out[rel] = ("f", full.stat().st_mode & 0o7777, full.read_bytes())
    return out


def fetchsync(
    *args: str, env: dict | None = None, check: bool = True, input: bytes | None = None
) -> subprocess.CompletedProcess:
    """Run the real CLI in a subprocess."""
    proc = subprocess.run(
        [sys.executable, "-m", "fetchsync", *args],
        capture_output=True,
        env=env,
        input=input,
        timeout=120,
    )
    if check and proc.returncode != 0:
        raise AssertionError(
            f"fetchsync {' '.join(args)} failed ({proc.returncode}):\n"
            f"{proc.stdout.decode()}\n{proc.stderr.decode()}"
        )
    return proc


def without_where(text: str) -> list[str]:
    """The non-empty lines of a verb's stderr but the line saying where its answer goes
    (``push ~/ws/src → user@robot:~/ws/src``), which precedes a one-line error."""
    return [
        line
        for line in text.strip().splitlines()
        if line.strip()
        and not (
            line.startswith(("push ", "pull ", "workspace-status "))
            and ("\u2192" in line or "\u2194" in line)
        )
    ]


def report(proc: subprocess.CompletedProcess) -> dict:
    return json.loads(proc.stdout.decode().strip().splitlines()[-1])


# Set for every test by tests/conftest.py (fresh connections, no lingering master): kept.
_SESSION_VARS = ("FETCHSYNC_PERSIST",)
# Where the developer's own configuration and data would be read from instead of HOME's.
_DEVELOPER_VARS = ("SSH_AUTH_SOCK", "XDG_CONFIG_HOME", "XDG_DATA_HOME")


def clean_env(**values: str) -> dict[str, str]:
    """This process's environment without the developer's own settings, plus ``values``: no
    ``FETCH_*``, ``FETCHSYNC_*`` or ``ROS_*`` variable (a robot, a workspace, a remote Python,
    a ROS master or distribution; residents off unless asked for), no ``SSH_AUTH_SOCK`` (an agent would offer the
    developer's keys), no ``XDG_CONFIG_HOME`` or ``XDG_DATA_HOME`` (their robots.toml, their
    local robot), so a CLI run sees only what its test gives it."""
    env = {
        k: v
        for k, v in os.environ.items()
        if k in _SESSION_VARS
        or not (
            k.startswith(("FETCH_", "FETCHSYNC_", "_FETCHSYNC_", "ROS_")) or k in _DEVELOPER_VARS
        )
    }
    env["FETCHSYNC_RESIDENT"] = "0"  # no resident outliving a test (tests/test_resident.py)
    env.update(values)
    return env


def local_env(tmp_path: Path, *, make_ws: bool = True, **extra: str) -> dict[str, str]:
    """The CLI's environment for a push to the built-in ``local`` robot (its home
    ``tmp_path/robot-home``, the workspace ``~/robot_ws``) of the workspace
    ``tmp_path/ws`` (a fresh ``make_workspace`` unless ``make_ws`` is false or it exists);
    ``extra`` overrides any of it."""
    env = clean_env(
        **{
            "FETCHSYNC_LOCAL_ROBOT_HOME": str(tmp_path / "robot-home"),
            "XDG_STATE_HOME": str(tmp_path / "state"),
            "FETCHSYNC_ROBOT": "local",
            "FETCHSYNC_WORKSPACE": str(tmp_path / "ws"),
            "FETCHSYNC_REMOTE_WORKSPACE": "~/robot_ws",
            **extra,
        }
    )
    if make_ws and not Path(env["FETCHSYNC_WORKSPACE"]).exists():
        make_workspace(Path(env["FETCHSYNC_WORKSPACE"]))
    return env


def ssh_env(
    home: Path, remote_dir: Path | str, tmp_path: Path, *, make_ws: bool = True, **extra: str
) -> dict[str, str]:
    """The CLI's environment for a push to the test sshd's ``robot`` alias from ``home``
    (an ssh_home or proxied_home) into ``remote_dir``, of the workspace ``tmp_path/ws`` (a
    fresh ``make_workspace`` unless ``make_ws`` is false or it exists); ``extra`` overrides
    any of it."""
    env = clean_env(
        **{
            "HOME": str(home),
            "FETCHSYNC_ROBOT": "robot",
            "FETCHSYNC_WORKSPACE": str(tmp_path / "ws"),
            "FETCHSYNC_REMOTE_WORKSPACE": str(remote_dir),
            "XDG_STATE_HOME": str(tmp_path / "state"),
            **extra,
        }
    )
    if make_ws and not Path(env["FETCHSYNC_WORKSPACE"]).exists():
        make_workspace(Path(env["FETCHSYNC_WORKSPACE"]))
    return env


def run_bench(
    script: str, *args: str, tmp_path: Path, needs: tuple[str, ...] = ()
) -> tuple[str, dict]:
    """Run ``bench/SCRIPT`` with ``args`` plus ``--json`` and ``--workdir`` under ``tmp_path``;
    its stdout (the report) and the raw JSON. Skips (fails under CI) without sshd or ``needs``."""
    import shutil

    import pytest
    from sshd import find_sshd

    missing = [t for t in needs if shutil.which(t) is None] + (
        ["sshd"] if find_sshd() is None else []
    )
    if missing:
        if os.environ.get("CI"):
            pytest.fail(f"{', '.join(missing)} should have been installed by .ci/run")
        pytest.skip(f"needs {', '.join(missing)}")
    repo = Path(__file__).resolve().parent.parent
    out_json = tmp_path / "bench.json"
    proc = subprocess.run(
        [
            sys.executable,
            str(repo / "bench" / script),
            *args,
            "--json",
            str(out_json),
            "--workdir",
            str(tmp_path / "work"),
        ],
        cwd=repo,
        check=False,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == 0, f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-5000:]}"
    return proc.stdout, json.loads(out_json.read_text())


def check_ready(chan) -> None:
    """Channel.ready() of ``chan``, running ``sleep 1; echo hi; sleep 0.5``: not before
    the command writes, then at once, and at its end. Closes ``chan``."""
    import time

    try:
        assert not chan.ready()
        deadline = time.monotonic() + 10
        while not chan.ready() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert chan.ready() and chan.recv(10) == b"hi\n"
        assert chan.recv(10) == b"" and chan.ready()
    finally:
        chan.close()


@contextlib.contextmanager
def local_sync_loop(tmp_path: Path, monkeypatch: Any) -> Iterator[tuple[Any, Path]]:
    """The watch agent's sync loop against the local robot (its own watcher off: the
    test feeds it batches), after its first full sync of ``tmp_path/ws``: yields the
    agent and the robot's ``src``; stopped and disconnected after."""
    import threading

    from fetchsync.agent import service
    from fetchsync.config import Target
    from fetchsync.sync import engine as sync

    monkeypatch.setenv("FETCHSYNC_LOCAL_ROBOT_HOME", str(tmp_path / "robot-home"))
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    target = Target(
        robot="local",
        host="local",
        user=None,
        workspace=tmp_path / "ws",
        remote_workspace="~/robot_ws",
        is_local=True,
    )
    a = service.Agent(target, rules=sync.build_rules(), own_watcher=False)
    loop = threading.Thread(target=a._sync_loop, daemon=True)
    loop.start()
    try:
        assert a.wait_for(a.request(full=True), 60) == (True, "")
        yield a, tmp_path / "robot-home" / "robot_ws" / "src"
    finally:
        a.stop()
        loop.join(10)
        a._disconnect()  # the state closes with its thread's objects
