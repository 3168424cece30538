"""push --build on several robots: the real catkin_make on the sshd robot, each robot's
build output prefixed with its name, one robot's failed build its own row."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from helpers import fetchsync
from test_build_ssh import SYSTEM_PYTHON, catkin_workspace
from test_fleet import _rows, fleet_env  # noqa: F401 - the fixture

pytestmark = [
    pytest.mark.ssh,
    pytest.mark.skipif(shutil.which("catkin_make") is None, reason="catkin not installed"),
]


@pytest.mark.slow
def test_a_fleet_build_fails_on_one_robot_and_builds_on_the_other(fleet_env, tmp_path):  # noqa: F811
    ws = Path(fleet_env["FETCHSYNC_WORKSPACE"])
    shutil.rmtree(ws)
    catkin_workspace(ws)
    broken = tmp_path / "robot-fetch2"
    broken.mkdir()
    (broken / "build").write_text("a file where catkin_make wants its build directory\n")
    proc = fetchsync(
        "push", SYSTEM_PYTHON, "--robot", "fetch1,fetch2", "--json", env=fleet_env, check=False
    )
    assert proc.returncode != 0, proc.stderr.decode()
    assert (tmp_path / "robot-fetch1/devel/setup.bash").is_file()
    rows = _rows(proc.stderr)
    assert rows["fetch1"][0] == "ok" and rows["fetch1"][5] == "ok"  # result, ..., build
    assert rows["fetch2"][0] == "failed" and rows["fetch2"][5] == "failed"
    [one, two] = json.loads(proc.stdout)  # with --json the builds' output went to stderr
    assert (one["build"], two["build"], one["files"], two["files"]) == ("ok", "failed", 2, 2)
    err = proc.stderr.decode()
    assert "[fetch1] Build space: " + str(tmp_path / "robot-fetch1/build") in err
    assert "[fetch2] fetchsync: catkin_make -DPYTHON_EXECUTABLE=/usr/bin/python3 (on fetch2)" in err
