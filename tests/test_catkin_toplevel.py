"""The robot's catkin_make makes ``src/CMakeLists.txt`` a link to catkin's toplevel.cmake
when the laptop's ``src/`` has none: push and pull leave that link alone (see
fetchsync.sync.plan.catkin_toplevel). A pure test of the plan and one end to end with the
real catkin_make on the sshd robot."""

from __future__ import annotations

import shutil

import pytest
from helpers import CATKIN_PACKAGE_XML as PACKAGE_XML
from helpers import fetchsync, report, ssh_env

from fetchsync.protocol import messages as M
from fetchsync.sync.engine import reconcile
from fetchsync.sync.plan import WHOLE

NOETIC = "/opt/ros/noetic/share/catkin/cmake/toplevel.cmake"
DEBIAN = "/usr/share/catkin/cmake/toplevel.cmake"


def f(path: str, h: str) -> M.Listed:
    return M.Listed(path, "f", 0o644, 10, hash=h)


def d(path: str) -> M.Listed:
    return M.Listed(path, "d", 0o755)


def link(path: str, target: str) -> M.Listed:
    return M.Listed(path, "l", 0o777, len(target), target=target)


def tree(*items: M.Listed) -> dict[str, M.Listed]:
    return {i.path: i for i in items}


def absent(_path: str) -> str:
    return M.ABSENT


def ops(planned) -> list[tuple[str, str]]:
    return [(p.op.kind, p.op.path) for p in planned]


def never(_path: str) -> bool:
    return False


@pytest.mark.parametrize("target", [NOETIC, DEBIAN])
def test_the_robots_catkin_toplevel_link_is_neither_deleted_nor_pulled(target):
    laptop = tree(d("pkg"), f("pkg/CMakeLists.txt", "h1"))
    robot = dict(laptop, **tree(link("CMakeLists.txt", target)))
    assert reconcile(laptop, robot, absent, guarded=never) == []
    assert reconcile(robot, laptop, absent, guarded=never, pulling=True) == []


def test_a_laptops_own_toplevel_cmakelists_is_pushed_over_the_robots_link():
    laptop = tree(d("pkg"), f("CMakeLists.txt", "mine"))
    robot = tree(d("pkg"), link("CMakeLists.txt", NOETIC))
    (p,) = reconcile(laptop, robot, absent, guarded=never)
    assert (p.op.kind, p.op.path, p.how) == (M.WRITE, "CMakeLists.txt", WHOLE)
    laptop_link = tree(
        d("pkg"), link("CMakeLists.txt", "/opt/ros/melodic/share/catkin/cmake/toplevel.cmake")
    )
    assert ops(reconcile(laptop_link, robot, absent, guarded=never)) == [
        (M.SYMLINK, "CMakeLists.txt")
    ]


def test_a_link_this_laptop_pushed_and_deleted_since_is_deleted_on_the_robot():
    robot = tree(d("pkg"), link("CMakeLists.txt", NOETIC))
    last_synced = {"CMakeLists.txt": M.expect_link(NOETIC)}.get
    assert ops(
        reconcile(tree(d("pkg")), robot, lambda p: last_synced(p, M.ABSENT), guarded=never)
    ) == [(M.DELETE, "CMakeLists.txt")]


def test_only_the_toplevel_link_to_catkins_toplevel_cmake_is_left_alone():
    laptop = tree(d("pkg"))
    robot = tree(
        d("pkg"),
        link("pkg/CMakeLists.txt", NOETIC),  # not the toplevel one
        link("CMakeLists.txt", "/opt/elsewhere/toplevel.cmake"),
    )  # not catkin's
    assert ops(reconcile(laptop, robot, absent, guarded=never)) == [
        (M.DELETE, "CMakeLists.txt"),
        (M.DELETE, "pkg/CMakeLists.txt"),
    ]
    assert ops(
        reconcile(laptop, tree(d("pkg"), f("CMakeLists.txt", "h")), absent, guarded=never)
    ) == [(M.DELETE, "CMakeLists.txt")]  # a file, not catkin_make's link


CMAKELISTS = """cmake_minimum_required(VERSION 3.0.2)
project(tiny)
find_package(catkin REQUIRED)
catkin_package()
"""


@pytest.mark.slow
@pytest.mark.ssh
@pytest.mark.skipif(shutil.which("catkin_make") is None, reason="catkin not installed")
def test_push_build_twice_with_the_robots_catkin_make_meets_no_conflict(
    ssh_home, remote_dir, tmp_path
):
    env = ssh_env(ssh_home.home, remote_dir, tmp_path, make_ws=False)
    pkg = tmp_path / "ws" / "src" / "tiny"
    pkg.mkdir(parents=True)
    (pkg / "package.xml").write_text(PACKAGE_XML.format(name="tiny"))
    (pkg / "CMakeLists.txt").write_text(CMAKELISTS)
    # the system's Python has catkin's modules (see test_build_ssh)
    build = "--build=-DPYTHON_EXECUTABLE=/usr/bin/python3"
    fetchsync("push", build, env=env)
    toplevel = remote_dir / "src" / "CMakeLists.txt"
    assert toplevel.is_symlink() and str(toplevel.readlink()).endswith(
        "catkin/cmake/toplevel.cmake"
    )
    for _ in range(2):
        out = report(fetchsync("push", build, "--json", env=env))
        assert out["conflicts"] == [], out
        assert toplevel.is_symlink()
    conflicts = remote_dir / ".fetchsync" / "conflicts"
    assert not conflicts.exists() or not any(conflicts.iterdir())
    # a pull leaves the laptop without it
    fetchsync("pull", "--yes", env=env)
    assert not (tmp_path / "ws" / "src" / "CMakeLists.txt").exists()
    assert (tmp_path / "ws" / "src" / "tiny" / "CMakeLists.txt").read_text() == CMAKELISTS
