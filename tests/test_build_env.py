"""Which setup file commands on the robot run under (fetchsync.chores.ros_setup), here and over ssh:
the workspace's, else the robot's ROS_DISTRO (never the laptop's), else the only distribution
or the one the workspace was built on, else a one-line error listing them; -v says which."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
from helpers import clean_env, fetchsync

from fetchsync.chores.ros_setup import SEVERAL_EXIT, environment


def distro(root: Path, name: str) -> None:
    (root / name).mkdir(parents=True)
    (root / name / "setup.bash").write_text(f"export FROM=/opt/ros/{name}\n")


def sourced(
    workspace: Path | None,
    ros_root: Path,
    *,
    spaces=("devel", "install"),
    env: dict[str, str] | None = None,
    announce: bool = False,
) -> subprocess.CompletedProcess:
    lines = environment(
        None if workspace is None else str(workspace),
        spaces=spaces,
        ros_root=str(ros_root),
        announce=announce,
    )
    full = {k: v for k, v in os.environ.items() if k != "ROS_DISTRO"}
    full.update(env or {})
    return subprocess.run(
        ["bash", "-c", lines + '\nprintf "%s|%s" "${FROM:-none}" "$#"'],
        capture_output=True,
        text=True,
        env=full,
        timeout=30,
        check=False,
    )


def test_several_distributions_pick_the_one_the_workspace_was_built_on(tmp_path):
    ros = tmp_path / "ros"
    for name in ("humble", "jazzy", "rolling"):
        distro(ros, name)
    ws = tmp_path / "ws"
    # colcon's install/setup.bash names the prefix it chained to; colcon builds skip the
    # workspace's own setup (spaces=()) but still follow it
    (ws / "install").mkdir(parents=True)
    (ws / "install/setup.bash").write_text(
        f'COLCON_CURRENT_PREFIX="{ros}/jazzy"\n_colcon_prefix_chain_bash_source_script\n'
    )
    assert sourced(ws, ros, spaces=()).stdout == "/opt/ros/jazzy|0"
    # catkin's devel/_setup_util.py holds the CMAKE_PREFIX_PATH it was built with
    (ws / "install/setup.bash").unlink()
    (ws / "devel").mkdir()
    (ws / "devel/_setup_util.py").write_text(f"CMAKE_PREFIX_PATH = r'{ros}/humble'.split(';')\n")
    assert sourced(ws, ros, spaces=()).stdout == "/opt/ros/humble|0"


def test_several_distributions_and_nothing_to_tell_is_one_line_listing_them(tmp_path):
    ros = tmp_path / "ros"
    distro(ros, "humble")
    distro(ros, "jazzy")
    out = sourced(tmp_path / "never-built", ros)
    assert out.returncode == SEVERAL_EXIT and out.stdout == ""
    assert len(out.stderr.splitlines()) == 1
    assert f"several ROS distributions under {ros} on " in out.stderr
    assert ": humble jazzy;" in out.stderr and "ROS_DISTRO" in out.stderr
    # the robot's own ROS_DISTRO settles it
    out = sourced(tmp_path / "never-built", ros, env={"ROS_DISTRO": "humble"})
    assert (out.returncode, out.stdout) == (0, "/opt/ros/humble|0")


def test_a_distro_name_that_is_a_prefix_of_another_is_not_confused(tmp_path):
    ros = tmp_path / "ros"
    distro(ros, "hum")
    distro(ros, "humble")
    ws = tmp_path / "ws"
    (ws / "install").mkdir(parents=True)
    (ws / "install/setup.bash").write_text(f'COLCON_CURRENT_PREFIX="{ros}/humble"\n')
    assert sourced(ws, ros, spaces=()).stdout == "/opt/ros/humble|0"


def test_announce_names_the_file(tmp_path):
    ros = tmp_path / "ros"
    distro(ros, "humble")
    out = sourced(tmp_path / "ws", ros, announce=True)
    assert out.stderr == f"fetchsync: sourcing {ros}/humble/setup.bash\n"
    out = sourced(tmp_path / "ws", tmp_path / "no-ros", announce=True)
    assert out.stderr.startswith("fetchsync: no ROS setup file to source")
    assert sourced(tmp_path / "ws", ros).stderr == ""  # quiet without -v


# --------------------------------------------------------------------------- over ssh
@pytest.mark.ssh
def test_run_v_says_what_it_sourced_and_the_laptops_ros_distro_stays_here(
    ssh_home, remote_dir, tmp_path
):
    env = clean_env(
        HOME=str(ssh_home.home),
        FETCHSYNC_ROBOT="robot",
        ROS_DISTRO="laptops-distro",
        FETCHSYNC_REMOTE_WORKSPACE=str(remote_dir),
        XDG_STATE_HOME=str(tmp_path / "state"),
    )
    (remote_dir / "install").mkdir()
    (remote_dir / "install/setup.bash").write_text("export FROM_WS=install\n")
    proc = fetchsync("-v", "run", "--", "sh", "-c", 'echo "${ROS_DISTRO:-unset} $FROM_WS"', env=env)
    assert proc.stdout.decode() == "unset install\n"
    assert f"fetchsync: sourcing {remote_dir}/install/setup.bash" in proc.stderr.decode()
    proc = fetchsync("run", "--", "true", env=env)
    assert b"sourcing" not in proc.stderr
