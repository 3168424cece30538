"""Secrets given to a call are not in the environment of the local build ``pull --build``
runs: chores.build's LocalRunner gave bash (and so colcon, catkin, cmake, every compiler
and every package's build script) the call's whole environment, FETCHSYNC_SUDO_PASSWORD
and the account passwords included. The build tool here is a fake on PATH that writes
its environment, over the built-in ``local`` robot."""

from __future__ import annotations

import os
import stat

from helpers import fetchsync, local_env
from test_secrets_not_inherited import SECRETS


def test_the_local_build_of_a_pull_gets_no_password(tmp_path):
    env = local_env(tmp_path, **SECRETS)
    robot_ws = tmp_path / "robot-home/robot_ws"
    (robot_ws / "src/pkg").mkdir(parents=True)
    (robot_ws / "src/pkg/package.xml").write_text("<package><name>pkg</name></package>\n")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    dump = tmp_path / "colcon-environ"
    tool = bin_dir / "colcon"
    tool.write_text(f"#!/bin/sh\ncat /proc/$$/environ > {dump}\nexit 0\n")
    tool.chmod(tool.stat().st_mode | stat.S_IXUSR)
    env["PATH"] = f"{bin_dir}{os.pathsep}{env['PATH']}"
    proc = fetchsync("pull", "--yes", "--build-tool", "colcon", "--build", env=env, check=False)
    assert proc.returncode == 0, proc.stderr.decode()
    assert (tmp_path / "ws/src/pkg/package.xml").is_file()
    seen = dump.read_bytes()
    assert b"PATH=" in seen  # the build still gets the rest of the environment
    for name, value in SECRETS.items():
        assert value.encode() not in seen, f"{name} given to the build"
