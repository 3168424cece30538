"""A fleet push to robots in different states gives each robot its own plan.

The attack (redteam, session 22) on the fleet's shared work (SharedPacks: reads,
streams, digests, kept records and samples shared between the robots' pushes): three
robots, one with a robot-side edit, one ahead of the others (a push to it alone of a
change the laptop then took back). Each robot must end as the laptop is, the
robot-side edit kept in that robot's conflicts only, and no robot's plan, expectation
or conflict given to another.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers import fetchsync, tree_of
from test_fleet import fleet_env  # noqa: F401 - the fixture

pytestmark = pytest.mark.ssh


def test_robots_in_different_states_each_get_their_own_plan(fleet_env, tmp_path):  # noqa: F811
    src = Path(fleet_env["FETCHSYNC_WORKSPACE"]) / "src"
    robots = {name: tmp_path / f"robot-{name}/src" for name in ("fetch1", "fetch2", "fetch3")}
    shared = src / "my_pkg/shared.txt"
    shared.write_text("shared line\n" * 200)
    (src / "my_pkg/g.txt").write_text("g as synced\n")
    fetchsync("push", "--robot", "fetch1,fetch2,fetch3", env=fleet_env)
    # fetch3 ahead: a change pushed to it alone, then taken back here
    (src / "my_pkg/g.txt").write_text("g only fetch3 got\n")
    fetchsync("push", "--robot", "fetch3", env=fleet_env)
    (src / "my_pkg/g.txt").write_text("g as synced\n")
    # fetch2: a robot-side edit of the file the laptop edits next
    (robots["fetch2"] / "my_pkg/shared.txt").write_text("edited on fetch2\n")
    shared.write_text("shared line\n" * 199 + "edited here\n")
    proc = fetchsync("push", "--robot", "fetch1,fetch2,fetch3", "--json", env=fleet_env)
    reports = {r["robot"]: r for r in json.loads(proc.stdout)}
    for name, robot in robots.items():
        assert tree_of(robot) == tree_of(src), name
    assert [c["path"] for c in reports["fetch2"]["conflicts"]] == ["my_pkg/shared.txt"]
    kept = tmp_path / "robot-fetch2" / reports["fetch2"]["conflicts"][0]["kept"]
    assert kept.read_text() == "edited on fetch2\n"
    assert reports["fetch1"]["conflicts"] == [] and reports["fetch3"]["conflicts"] == []
    for name in ("fetch1", "fetch3"):
        assert not (tmp_path / f"robot-{name}/.fetchsync/conflicts").exists() or not list(
            (tmp_path / f"robot-{name}/.fetchsync/conflicts").rglob("*.txt")
        ), name
