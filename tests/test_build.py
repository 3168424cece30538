"""fetchsync.chores.build without a robot: tool detection, command construction, the steps' scripts,
and the --build option's fetch_tools semantics."""

from __future__ import annotations

import os
import stat
import subprocess
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from fetchsync.chores import build
from fetchsync.chores.build import BuildRequest, build_command, detect_tool, plan
from fetchsync.cli import build_flags as build_options
from fetchsync.cli.build_flags import explicit_build_values

CATKIN_XML = (
    "<package format='2'><name>a</name><buildtool_depend>catkin</buildtool_depend></package>"
)
AMENT_XML = (
    "<package format='3'><name>b</name><buildtool_depend>ament_cmake</buildtool_depend>"
    "<export><build_type>ament_cmake</build_type></export></package>"
)
AMENT_PYTHON_XML = (
    "<package format='3'><name>c</name>"
    "<export><build_type>ament_python</build_type></export></package>"
)


# --------------------------------------------------------------------------- detection
@pytest.mark.parametrize(
    "markers, expected",
    [
        ({".catkin_tools"}, "catkin"),
        ({".catkin_tools", "src/CMakeLists.txt", "devel/.catkin"}, "catkin"),
        ({"build/COLCON_IGNORE"}, "colcon"),
        ({"install/COLCON_IGNORE", "log/COLCON_IGNORE"}, "colcon"),
        ({"src/CMakeLists.txt"}, "catkin_make"),
        ({"build/catkin_make.cache"}, "catkin_make"),
        ({"devel/.catkin"}, "catkin_make"),
        (set(), "catkin_make"),
    ],
)
def test_the_workspace_says_how_it_is_built(markers, expected):
    assert detect_tool(markers) == expected
    if markers:  # what the workspace was set up for wins over what its packages suggest
        other = CATKIN_XML if expected == "colcon" else AMENT_XML
        assert detect_tool(markers, [other]) == expected


@pytest.mark.parametrize(
    "manifests, expected",
    [
        ([CATKIN_XML], "catkin_make"),
        ([CATKIN_XML, AMENT_XML], "colcon"),
        ([AMENT_PYTHON_XML], "colcon"),
        ([], "catkin_make"),
    ],
)
def test_a_fresh_workspace_is_known_by_its_packages(manifests, expected):
    assert detect_tool(set(), manifests) == expected


def _package(path: Path, xml: str) -> None:
    path.mkdir(parents=True)
    (path / "package.xml").write_text(xml)


def test_manifests_skip_ignored_hidden_and_nested_packages(tmp_path):
    src = tmp_path / "src"
    _package(src / "a", CATKIN_XML)
    _package(src / "a" / "nested", AMENT_XML)  # inside a package: not a package
    _package(src / "ignored", AMENT_XML)
    (src / "ignored" / "COLCON_IGNORE").touch()
    _package(src / ".hidden", AMENT_XML)
    _package(src / "group" / "b", CATKIN_XML)
    assert sorted(build.manifests(src)) == [CATKIN_XML, CATKIN_XML]
    assert detect_tool(build.local_markers(tmp_path), build.manifests(src)) == "catkin_make"


def test_markers_here_and_there_agree(tmp_path):
    (tmp_path / ".catkin_tools").mkdir()
    (tmp_path / "src").mkdir()
    # catkin's toplevel link may point at a path that does not exist here
    (tmp_path / "src/CMakeLists.txt").symlink_to(
        "/opt/ros/noetic/share/catkin/cmake/toplevel.cmake"
    )
    (tmp_path / "build").mkdir()
    (tmp_path / "build/COLCON_IGNORE").touch()
    expected = {".catkin_tools", "src/CMakeLists.txt", "build/COLCON_IGNORE"}
    assert build.local_markers(tmp_path) == expected
    probe = build.marker_probe(str(tmp_path))
    out = subprocess.run(["sh", "-c", probe], capture_output=True, text=True, check=True)
    assert set(out.stdout.split()) == expected
    out = subprocess.run(
        ["sh", "-c", build.marker_probe(str(tmp_path / "none"))],
        capture_output=True,
        text=True,
        check=True,
    )
    assert out.stdout == ""


# --------------------------------------------------------------------------- commands
@pytest.mark.parametrize(
    "tool, args, build_type, expected",
    [
        ("catkin_make", "", "default", "catkin_make"),
        ("catkin_make", "-j4", "default", "catkin_make -j4"),
        ("catkin_make", "-j4 ", "Release", "catkin_make -j4 -DCMAKE_BUILD_TYPE=Release"),
        (
            "catkin_make",
            "install",
            "MinSizeRel",
            "catkin_make install -DCMAKE_BUILD_TYPE=MinSizeRel",
        ),
        ("catkin", "", "Debug", "catkin build --cmake-args -DCMAKE_BUILD_TYPE=Debug"),
        ("catkin", "my_pkg", "default", "catkin build my_pkg"),
        ("colcon", "", "default", "colcon build"),
        (
            "colcon",
            "--symlink-install",
            "RelWithDebInfo",
            "colcon build --symlink-install --cmake-args -DCMAKE_BUILD_TYPE=RelWithDebInfo",
        ),
        # colcon keeps the last --cmake-args only: the build type joins the one given
        (
            "colcon",
            "--cmake-args -DFOO=1 --packages-select x",
            "Release",
            "colcon build --cmake-args -DCMAKE_BUILD_TYPE=Release -DFOO=1 --packages-select x",
        ),
    ],
)
def test_build_command(tool, args, build_type, expected):
    assert build_command(tool, args, build_type) == expected


def test_rosdep_as_fetch_tools_ran_it():
    assert build.deps_commands() == [
        "rosdep update",
        "rosdep install --from-paths src --ignore-src -y",
    ]


def test_requests_are_validated_and_false_when_empty():
    assert not BuildRequest()
    assert BuildRequest(builds=("",))
    assert BuildRequest(install_deps=True)
    with pytest.raises(ValueError):
        BuildRequest(build_type="Fast")
    with pytest.raises(ValueError):
        BuildRequest(tool="make")


def test_the_clis_choices_are_the_librarys():
    assert build_options.BUILD_TYPES == build.BUILD_TYPES
    assert build_options.TOOLS == build.TOOLS


def _tool(bin_dir: Path, name: str) -> None:
    bin_dir.mkdir(exist_ok=True)
    path = bin_dir / name
    path.write_text('#!/bin/sh\necho "$(basename "$0") $* in $PWD with ${FROM_SETUP:-nothing}"\n')
    path.chmod(path.stat().st_mode | stat.S_IXUSR)


def _run(steps: list[build.Step], bin_dir: Path) -> list[str]:
    env = dict(os.environ, PATH=f"{bin_dir}:{os.environ['PATH']}")
    env.pop("ROS_DISTRO", None)
    out = []
    for step in steps:
        proc = subprocess.run(
            ["bash", "-c", step.script], capture_output=True, text=True, env=env, check=True
        )
        out.append(proc.stdout.strip())
    return out


def test_steps_deps_first_then_each_build_in_the_workspace(tmp_path):
    ws = tmp_path / "ws"
    (ws / "devel").mkdir(parents=True)
    (ws / "devel/setup.bash").write_text("export FROM_SETUP=devel\n")
    for name in ("rosdep", "catkin_make", "colcon"):
        _tool(tmp_path / "bin", name)
    request = BuildRequest(builds=("", "install"), build_type="Release", install_deps=True)
    steps = plan(request, workspace=str(ws), tool="catkin_make")
    assert [s.what for s in steps] == [
        "rosdep update",
        "rosdep install --from-paths src --ignore-src -y",
        "catkin_make -DCMAKE_BUILD_TYPE=Release",
        "catkin_make install -DCMAKE_BUILD_TYPE=Release",
    ]
    assert _run(steps, tmp_path / "bin") == [
        f"rosdep update in {ws} with devel",
        f"rosdep install --from-paths src --ignore-src -y in {ws} with devel",
        f"catkin_make -DCMAKE_BUILD_TYPE=Release in {ws} with devel",
        f"catkin_make install -DCMAKE_BUILD_TYPE=Release in {ws} with devel",
    ]


def test_colcon_builds_do_not_source_the_workspaces_own_install(tmp_path):
    ws = tmp_path / "ws"
    (ws / "install").mkdir(parents=True)
    (ws / "install/setup.bash").write_text("export FROM_SETUP=install\n")
    _tool(tmp_path / "bin", "colcon")
    _tool(tmp_path / "bin", "rosdep")
    steps = plan(BuildRequest(builds=("",), install_deps=True), workspace=str(ws), tool="colcon")
    assert _run(steps, tmp_path / "bin")[-1] == f"colcon build in {ws} with nothing"
    assert _run(steps, tmp_path / "bin")[0] == f"rosdep update in {ws} with install"


class _Runner:
    where = "robot"

    def __init__(self, statuses: list[int]) -> None:
        self.statuses = statuses
        self.ran: list[str] = []

    def run(self, step: build.Step) -> int:
        self.ran.append(step.what)
        return self.statuses.pop(0)


def test_the_first_failure_stops_and_carries_its_status():
    steps = plan(BuildRequest(builds=("", "install")), workspace="~/ws", tool="catkin_make")
    runner = _Runner([0, 3])
    with pytest.raises(build.BuildError) as failed:
        build.execute(steps, runner)
    assert failed.value.exit_code == 3
    assert str(failed.value).startswith("catkin_make install failed on robot with exit status 3")
    steps = plan(
        BuildRequest(builds=("",), install_deps=True), workspace="~/ws", tool="catkin_make"
    )
    runner = _Runner([127])
    with pytest.raises(build.BuildError) as failed:
        build.execute(steps, runner)
    assert runner.ran == ["rosdep update"] and "python3-rosdep" in str(failed.value)


# --------------------------------------------------------------------------- --build parsing
@pytest.mark.parametrize(
    "args, expected",
    [
        (["--build"], ["--build="]),
        (["--build", "--json"], ["--build=", "--json"]),
        (["--build", "-j4"], ["--build=", "-j4"]),  # as argparse: -j4 looks like an option
        (["--build", "-j4 -DX=1"], ["--build", "-j4 -DX=1"]),  # ... this does not
        (["--build", "install", "--build"], ["--build", "install", "--build="]),
        (["--build=-j4"], ["--build=-j4"]),
        (["--build", "--", "--build"], ["--build=", "--", "--build"]),
    ],
)
def test_build_takes_an_optional_value_as_in_fetch_tools(args, expected):
    assert explicit_build_values(args) == expected


def test_build_options_parse():
    seen = {}

    @click.command(cls=build_options.BuildCommand)
    @build_options.build_options
    def cmd(**kwargs):
        seen.update(kwargs)

    result = CliRunner().invoke(
        cmd,
        [
            "--build",
            "--build=-j4",
            "--build",
            "install",
            "--build-type",
            "Release",
            "--install-deps",
        ],
    )
    assert result.exit_code == 0, result.output
    assert seen == {
        "builds": ("", "-j4", "install"),
        "build_type": "Release",
        "build_tool": "auto",
        "install_deps": True,
    }
    result = CliRunner().invoke(cmd, ["--build-type", "Fast"])
    assert result.exit_code == 2


def test_build_type_alone_warns(capsys):
    request = build_options.build_request((), "Release", "auto", False)
    assert not request
    assert "--build-type has no effect without --build" in capsys.readouterr().err


def test_a_push_without_build_options_does_not_import_the_build_module():
    import subprocess
    import sys

    code = (
        "import sys\nfrom fetchsync.cli.build_flags import build_request\n"
        "print(build_request((), 'default', 'auto', False), 'fetchsync.chores.build' in sys.modules, "
        "bool(build_request((), 'default', 'auto', True)))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    assert out.split() == ["None", "False", "True"]


# --------------------------------------------------------------------------- detection, ROS 2
FORMAT3_CATKIN_XML = (
    "<package format='3'><name>n</name><buildtool_depend>catkin</buildtool_depend></package>"
)
FORMAT3_PLAIN_XML = '<package format="3"><name>p</name></package>'
CMAKE_XML = (
    "<package format='3'><name>m</name><export><build_type>cmake</build_type></export></package>"
)


@pytest.mark.parametrize(
    "markers, manifests, distros, tool, reason",
    [
        (
            {".catkin_workspace"},
            [AMENT_XML],
            set(),
            "catkin_make",
            "the workspace has .catkin_workspace",
        ),
        (
            {"install/.colcon_install_layout"},
            [CATKIN_XML],
            set(),
            "colcon",
            "the workspace has install/.colcon_install_layout",
        ),
        (
            set(),
            [FORMAT3_CATKIN_XML],
            {"ros2:humble"},
            "catkin_make",
            "never built, and n is a catkin package",
        ),  # Noetic packages are format 3 too
        (
            set(),
            [FORMAT3_PLAIN_XML],
            set(),
            "colcon",
            "p is a ROS 2 package (package.xml format 3 without catkin)",
        ),
        (
            set(),
            [CATKIN_XML, CMAKE_XML],
            set(),
            "colcon",
            "m is a ROS 2 package (build type cmake)",
        ),
        (set(), [AMENT_XML], set(), "colcon", "b is a ROS 2 package (build type ament_cmake)"),
        (
            set(),
            [],
            {"ros2:humble", "ros2:jazzy"},
            "colcon",
            "no packages yet, and the robot has ROS 2 only (humble, jazzy)",
        ),
        (
            set(),
            [],
            {"ros2:humble", "ros1:noetic"},
            "catkin_make",
            "nothing tells: catkin_make, as fetch_tools",
        ),
    ],
)
def test_the_choice_of_tool_says_why(markers, manifests, distros, tool, reason):
    choice = build.choose_tool(markers, manifests, distros)
    assert (choice.tool, choice.reason) == (tool, reason)


def test_the_probe_names_the_robots_distributions_and_their_generation(tmp_path):
    ros = tmp_path / "ros"
    for name, ros2 in (("noetic", False), ("humble", True), ("broken", True)):
        (ros / name / "share/ament_index" if ros2 else ros / name).mkdir(parents=True)
        if name != "broken":  # no setup.bash: not a distribution
            (ros / name / "setup.bash").write_text("")
    (tmp_path / "ws/.catkin_tools").mkdir(parents=True)
    out = subprocess.run(
        ["sh", "-c", build.marker_probe(str(tmp_path / "ws"), ros_root=str(ros))],
        capture_output=True,
        text=True,
        check=True,
    )
    assert build.split_probe(out.stdout) == ({".catkin_tools"}, {"ros1:noetic", "ros2:humble"})
