"""Command lines for the robot: its ROS environment, bash, and a reaper around them.

Shared by ``run`` and the builds of ``push``/``pull``. Everything here is pure
string construction (``shlex`` quoting); nothing talks to a robot.

A command for the robot is built in three layers:

1. a bash script that sources the ROS environment (:func:`ros_environment`)
   and then runs the user's command line;
2. ``bash -c SCRIPT``, since every ROS ``setup.bash`` needs bash whatever the
   login shell is;
3. :func:`wrap`: that under ``fetchsync/robot/reaper.py`` (sent inline to the
   robot's ``python3``), so the command runs in its own process group and
   nothing of it outlives the channel. Where the robot has no such Python the
   command still runs, without that guarantee.

The last string is what the transport hands to the login shell of the robot
user (a POSIX shell, as for the rest of fetchsync).
"""

from __future__ import annotations

import functools
import logging
import shlex
from collections.abc import Sequence
from pathlib import Path

ROS_ROOT = "/opt/ros"
"""Where ROS distributions are installed, one directory per distribution."""

RUN_SPACES = ("devel", "install")
"""Result spaces whose ``setup.bash`` a command on the robot runs under, first found wins."""


def shell_path(path: str) -> str:
    """``path`` quoted for a POSIX shell, with a leading ``~`` meaning ``$HOME`` there."""
    if path == "~":
        return '"$HOME"'
    if path.startswith("~/"):
        rest = path[2:]
        return '"$HOME"' + ("/" + shlex.quote(rest) if rest else "/")
    return shlex.quote(path)


def command_line(argv: Sequence[str]) -> str:
    """A shell command line that runs exactly ``argv`` (no expansion, no splitting)."""
    if not argv:
        raise ValueError("an empty argv is no command")
    return shlex.join(argv)


def ros_environment(
    workspace: str | None,
    *,
    spaces: Sequence[str] = RUN_SPACES,
    ros_root: str = ROS_ROOT,
    announce: bool | None = None,
) -> str:
    """bash lines that source the ROS environment a command in ``workspace`` should see.

    See :mod:`fetchsync.chores.ros_setup` for which file; ``announce`` (default: when
    ``-v`` is given) has the lines say which one on stderr.
    """
    from fetchsync.chores.ros_setup import environment

    if announce is None:
        announce = logging.getLogger("fetchsync").isEnabledFor(logging.INFO)
    return environment(workspace, spaces=spaces, ros_root=ros_root, announce=announce)


def script(command: str, *, environment: str, directory: str | None = None) -> str:
    """A bash script: optionally ``cd`` to ``directory``, source ``environment``, run ``command``."""
    parts = []
    if directory is not None:
        parts.append(f"cd {shell_path(directory)} || exit 1")
    parts.append(environment)
    parts.append(command)
    return "\n".join(parts)


@functools.cache
def reaper_source() -> str:
    """The source of :mod:`fetchsync.robot.reaper`, as sent to the robot."""
    return (Path(__file__).resolve().parent.parent / "robot" / "reaper.py").read_text(
        encoding="utf-8"
    )


def wrap(bash_script: str, *, tty: bool, python: str = "python3") -> str:
    """The command line for the robot's login shell that runs ``bash_script`` reaped.

    ``tty`` must say whether the channel has a PTY: the reaper then hands the
    terminal to the command's process group so that ``^C`` reaches it.
    """
    bash = ["bash", "-c", bash_script]
    reaped = [python, "-c", reaper_source(), "tty" if tty else "pipe", *bash]
    return (
        f"if command -v {shlex.quote(python)} >/dev/null 2>&1; "
        f"then exec {shlex.join(reaped)}; else exec {shlex.join(bash)}; fi"
    )
