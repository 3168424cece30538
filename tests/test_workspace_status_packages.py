"""workspace-status lists each repository's ROS packages with what builds them: catkin
(ROS 1), and ROS 2's package format 3 with ament_* (or plain cmake/python) build types."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

from helpers import fetchsync

from fetchsync.chores.workspace_status import find_packages
from fetchsync.config import ROBOT_VARS

GIT_ENV = {
    "GIT_AUTHOR_NAME": "t",
    "GIT_AUTHOR_EMAIL": "t@example.com",
    "GIT_COMMITTER_NAME": "t",
    "GIT_COMMITTER_EMAIL": "t@example.com",
}


def manifest(path: Path, xml: str) -> None:
    path.mkdir(parents=True, exist_ok=True)
    (path / "package.xml").write_text(xml)


def catkin(name: str, fmt: int = 2) -> str:
    return (
        f'<package format="{fmt}"><name>{name}</name>'
        "<buildtool_depend>catkin</buildtool_depend></package>"
    )


def ros2(name: str, build_type: str | None) -> str:
    export = f"<export><build_type>{build_type}</build_type></export>" if build_type else ""
    tool = f"<buildtool_depend>{build_type}</buildtool_depend>" if build_type else ""
    return f'<package format="3"><name>{name}</name>{tool}{export}</package>'


def test_packages_by_repository_with_their_build_types(tmp_path: Path):
    src = tmp_path / "ws/src"
    manifest(src / "ros1/cat_a", catkin("cat_a"))
    manifest(src / "ros1/cat_noetic", catkin("cat_noetic", fmt=3))  # Noetic's format 3: catkin
    manifest(src / "ros2/cpp", ros2("talker_cpp", "ament_cmake"))
    manifest(src / "ros2/py", ros2("talker_py", "ament_python"))
    manifest(src / "ros2/plain", ros2("plain_cmake", "cmake"))
    manifest(src / "ros2/bare", ros2("bare", None))  # format 3, nothing else
    manifest(src / "ros2/ignored", ros2("ignored", "ament_cmake"))
    (src / "ros2/ignored/COLCON_IGNORE").touch()
    manifest(src / "ros2/cpp/test/inner", catkin("inner"))  # inside a package: not one
    for repo in ("ros1", "ros2"):
        subprocess.run(["git", "init", "-q", "-b", "main", str(src / repo)], check=True)
        subprocess.run(["git", "-C", str(src / repo), "add", "-A"], check=True)
        subprocess.run(
            ["git", "-C", str(src / repo), "commit", "-q", "-m", "x"],
            check=True,
            env={**os.environ, **GIT_ENV},
        )
    found = {p.name: (p.format, p.build_type, p.ros) for p in find_packages(src)}
    assert found == {
        "cat_a": (2, "catkin", 1),
        "cat_noetic": (3, "catkin", 1),
        "talker_cpp": (3, "ament_cmake", 2),
        "talker_py": (3, "ament_python", 2),
        "plain_cmake": (3, "cmake", 2),
        "bare": (3, "ament_cmake", 2),
    }
    env = {k: v for k, v in os.environ.items() if k not in ROBOT_VARS}
    env.update(FETCHSYNC_WORKSPACE=str(tmp_path / "ws"), XDG_STATE_HOME=str(tmp_path / "state"))
    proc = fetchsync("workspace-status", "--no-robot", env=env)
    lines = proc.stdout.decode().splitlines()
    assert [c.strip() for c in lines[1].split("|")] == ["repository", "branch", "sha", "packages"]
    rows = {c[0]: c[3] for c in ([x.strip() for x in ln.split("|")] for ln in lines[3:])}
    assert rows == {"ros1": "2 catkin", "ros2": "2 ament_cmake, 1 ament_python, 1 cmake"}
    proc = fetchsync("workspace-status", "--no-robot", "--json", env=env)
    by_path = {r["path"]: r for r in json.loads(proc.stdout)}
    assert {p["name"]: p["ros"] for p in by_path["ros2"]["packages"]} == {
        "talker_cpp": 2,
        "talker_py": 2,
        "plain_cmake": 2,
        "bare": 2,
    }
    assert by_path["ros1"]["packages"][0] == {
        "name": "cat_a",
        "path": "ros1/cat_a",
        "format": 2,
        "build_type": "catkin",
        "ros": 1,
    }
