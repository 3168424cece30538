"""Issue 25 item 6: the robot-side endpoint runs on Python 3.6 (Ubuntu 18.04, Fetch's own
Melodic image) with the standard library only: push (whole files and a delta) and pull
through the ``local`` robot with its endpoint run by a real Python 3.6."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from helpers import fetchsync, local_env, make_workspace, report, tree_of

PY36 = "/root/.pyenv/versions/3.6.15/bin/python3.6"

pytestmark = pytest.mark.skipif(
    not os.path.exists(PY36) and not os.environ.get("CI"), reason="no Python 3.6 at " + PY36
)


def test_push_and_pull_with_a_python_36_endpoint(tmp_path: Path) -> None:
    make_workspace(tmp_path / "ws")
    src = tmp_path / "ws/src"
    (src / "pkg").mkdir(parents=True, exist_ok=True)
    big = os.urandom(200_000)
    (src / "pkg/big.bin").write_bytes(big)
    (src / "pkg/link").symlink_to("big.bin")
    env = local_env(
        tmp_path,
        FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "rh"),
        FETCHSYNC_REMOTE_WORKSPACE="~/rws",
        FETCHSYNC_REMOTE_PYTHON=PY36,
    )
    robot = tmp_path / "rh/rws/src"
    fetchsync("push", env=env)
    assert tree_of(src) == tree_of(robot)
    # the endpoint that answered is the 3.6 one (the robot's cache holds its build)
    built = [p.name for p in (tmp_path / "rh/.cache/fetchsync").iterdir()]
    assert any(name.endswith("-cpython-36") for name in built), built
    (src / "pkg/big.bin").write_bytes(b"inserted at the top\n" + big)
    cmake = src / "my_pkg/CMakeLists.txt"  # a small text file: a dictionary write
    cmake.write_text(cmake.read_text().replace("project(my_pkg)", "project(my_pkg) # edited"))
    out = report(fetchsync("push", "--json", env=env))
    assert out["deltas"] == 2, out
    assert tree_of(src) == tree_of(robot)
    (robot / "pkg/robot_edit.txt").write_text("made on the robot\n")
    fetchsync("pull", "--yes", env=env)
    assert (src / "pkg/robot_edit.txt").read_text() == "made on the robot\n"
    assert tree_of(src) == tree_of(robot)
