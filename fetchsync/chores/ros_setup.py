"""Which ROS setup file a command on the robot runs under: bash lines, evaluated there.

``run`` and the builds of ``push``/``watch`` source, on the machine the lines
run on, the first that applies of:

1. the workspace's own result space (``devel/setup.bash``, then
   ``install/setup.bash``: see ``spaces``); it chains to the distribution
   the workspace was built on;
2. ``/opt/ros/$ROS_DISTRO/setup.bash`` with that machine's ``ROS_DISTRO``
   (the laptop's is never sent: nothing here is expanded on the laptop);
3. the only distribution under ``/opt/ros``; with several, the one the
   workspace was built on (named in its ``install/setup.bash`` or
   ``devel/_setup_util.py``, which a colcon build leaves even when ``spaces``
   skips them), else the script stops with one line listing them: guessing
   would build a workspace against the wrong distribution;
4. nothing, when there is no ROS at all (plain CMake packages need none).

With ``announce`` the lines say on stderr which file they sourced (``-v``).
Everything is pure string construction; nothing here talks to a robot.
"""

from __future__ import annotations

import shlex
from collections.abc import Sequence

ROS_ROOT = "/opt/ros"

SEVERAL_EXIT = 2
"""The exit status of the lines when they cannot choose between distributions."""


def _quote_path(path: str) -> str:
    # a leading ~ means the home of the machine the lines run on
    if path == "~":
        return '"$HOME"'
    if path.startswith("~/"):
        return '"$HOME"/' + shlex.quote(path[2:])
    return shlex.quote(path)


def environment(
    workspace: str | None,
    *,
    spaces: Sequence[str],
    ros_root: str = ROS_ROOT,
    announce: bool = False,
) -> str:
    """bash lines that source the ROS environment for a command in ``workspace``.

    See the module's docstring for the order. The helper variables
    (``__fetchsync_*``) are unset afterwards.
    """
    root = shlex.quote(ros_root)
    lines = ["__fetchsync_setup="]
    if workspace is not None:
        ws = workspace.rstrip("/") or "/"
        for space in spaces:
            setup = _quote_path(f"{ws}/{space}/setup.bash")
            lines.append(
                f'if [ -z "$__fetchsync_setup" ] && [ -f {setup} ]; then '
                f"__fetchsync_setup={setup}; fi"
            )
    lines += [
        'if [ -z "$__fetchsync_setup" ] && [ -n "${ROS_DISTRO:-}" ] && '
        f'[ -f {root}/"$ROS_DISTRO"/setup.bash ]; then',
        f'  __fetchsync_setup={root}/"$ROS_DISTRO"/setup.bash',
        "fi",
        'if [ -z "$__fetchsync_setup" ]; then',
        "  __fetchsync_all=",
        f"  for __fetchsync_dir in {root}/*/; do",
        '    if [ -f "${__fetchsync_dir}setup.bash" ]; then',
        '      __fetchsync_all="$__fetchsync_all $(basename "$__fetchsync_dir")"',
        "    fi",
        "  done",
        "  set -- $__fetchsync_all",
        '  if [ "$#" -eq 1 ]; then',
        f'    __fetchsync_setup={root}/"$1"/setup.bash',
        '  elif [ "$#" -gt 1 ]; then',
    ]
    if workspace is not None:
        ws = workspace.rstrip("/") or "/"
        built = " ".join(
            _quote_path(f"{ws}/{p}") for p in ("install/setup.bash", "devel/_setup_util.py")
        )
        lines += [
            '    for __fetchsync_dir in "$@"; do',
            f"      if grep -qsE {root}/\"$__fetchsync_dir\"'([^A-Za-z0-9_.-]|$)' {built}; then",
            f'        __fetchsync_setup={root}/"$__fetchsync_dir"/setup.bash',
            "      fi",
            "    done",
        ]
    lines += [
        '    if [ -z "$__fetchsync_setup" ]; then',
        f'      echo "fetchsync: several ROS distributions under {ros_root} on $(hostname):'
        "$__fetchsync_all; the workspace was not built with one of them yet: set ROS_DISTRO "
        "in the robot's login environment (the top of its ~/.bashrc) or source one in "
        'the command" >&2',
        f"      exit {SEVERAL_EXIT}",
        "    fi",
        "  fi",
        "  set --",
        "fi",
        'if [ -n "$__fetchsync_setup" ]; then',
    ]
    if announce:
        lines.append('  echo "fetchsync: sourcing $__fetchsync_setup" >&2')
    lines += [
        '  . "$__fetchsync_setup"',
    ]
    if announce:
        lines += [
            "else",
            f'  echo "fetchsync: no ROS setup file to source (none under {ros_root})" >&2',
        ]
    lines += [
        "fi",
        "unset __fetchsync_setup __fetchsync_all __fetchsync_dir",
    ]
    return "\n".join(lines)
