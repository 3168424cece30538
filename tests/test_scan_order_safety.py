"""The safety promises with the push's new order (fc32ea4): with the endpoint up (a
connection master's warm spare) the push asks for the robot's list before it scans the
local tree. The mass-deletion guard and the robot's own edits must hold the same way as
when the scan comes first (safety track's attack on the start track's change)."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import local_env, tree_of
from test_push_scan_order import _gc_back, invoke, record  # noqa: F401 - a fixture

N = 40


@pytest.fixture(params=[True, False], ids=["list-first", "scan-first"])
def order(request, monkeypatch) -> tuple[list[str], str]:
    """The push's events as they come, and which of the two comes first."""
    return record(monkeypatch, endpoint_up=request.param), "list" if request.param else "scan"


def push(env: dict[str, str], *args: str):
    return invoke(["push", "--json", *args], env)


def test_the_guard_refuses_an_emptied_tree_whatever_the_order(order, tmp_path: Path):
    env = local_env(tmp_path)
    src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    robot = Path(env["FETCHSYNC_LOCAL_ROBOT_HOME"]) / "robot_ws" / "src"
    (src / "many").mkdir()
    for i in range(N):
        (src / f"many/f{i}.txt").write_text(f"{i}\n")
    assert push(env).exit_code == 0
    events, first = order
    assert events[0] == first  # the order under test is the one the push took
    for p in (src / "many").iterdir():
        p.unlink()
    (src / "many").rmdir()
    (src / "my_pkg/package.xml").write_text("<changed/>\n")
    refused = push(env)
    assert refused.exit_code == 5, refused.output
    assert "would delete" in refused.output
    assert len(list((robot / "many").iterdir())) == N
    assert (robot / "my_pkg/package.xml").read_text() != "<changed/>\n"
    assert push(env, "--force").exit_code == 0
    assert tree_of(src) == tree_of(robot)


def test_a_robot_side_edit_is_kept_whatever_the_order(order, tmp_path: Path):
    env = local_env(tmp_path)
    src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    home = Path(env["FETCHSYNC_LOCAL_ROBOT_HOME"])
    robot = home / "robot_ws" / "src"
    assert push(env).exit_code == 0
    (robot / "my_pkg/package.xml").write_text("<edited on the robot/>\n")
    (src / "my_pkg/package.xml").write_text("<edited on the laptop/>\n")
    assert push(env).exit_code == 0
    assert (robot / "my_pkg/package.xml").read_text() == "<edited on the laptop/>\n"
    kept = [
        p.read_text()
        for p in (home / "robot_ws/.fetchsync/conflicts").rglob("package.xml")
        if p.is_file()
    ]
    assert kept == ["<edited on the robot/>\n"]
