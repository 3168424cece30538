"""``fetchsync config``: each resolved setting, and where it came from.

The answer to "where did that push go, and why there": the same resolution as
every robot verb (:mod:`fetchsync.config`), shown setting by setting with its
source (an option, which variable, the ssh config, the current directory, a
default) and the order in which the sources are tried.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from typing import Any

import click

from fetchsync.cli.common import resolve, target_options, where_line
from fetchsync.errors import ConfigError

ORDERS = {
    "robot": "--robot, FETCHSYNC_ROBOT, FETCH_ROBOT, the host of ROS_MASTER_URI",
    "user": "--user, FETCHSYNC_USER, FETCH_USER, the ssh config's User, $USER",
    "workspace": "--workspace, FETCHSYNC_WORKSPACE, FETCH_WORKSPACE, the workspace around the "
    "current directory, ~/$ROS_DISTRO",
    "remote workspace": "--remote-workspace, FETCHSYNC_REMOTE_WORKSPACE, FETCH_REMOTE_WORKSPACE, "
    "the local workspace with ~ for home",
}
"""The order in which each target setting's sources are tried (README, Configuration)."""


@dataclass(frozen=True)
class Setting:
    """One resolved setting: its value (None when it cannot be resolved) and its source,
    or why it cannot be resolved."""

    name: str
    value: str | None
    source: str


def _variable(name: str, default: str, meaning: str, unit: str = "") -> Setting:
    value = os.environ.get(name, "").strip()
    if value:
        return Setting(meaning, value + unit, name)
    return Setting(meaning, default, f"default; {name} changes it")


def settings(
    *, robot: str | None, user: str | None, workspace: str | None, remote_workspace: str | None
) -> list[Setting]:
    """Every setting a robot verb would use with these options, in display order."""
    from fetchsync import config

    out: list[Setting] = []
    robot_name: str | None = None
    try:
        robot_name, source = config.robot_with_source(robot)
        out.append(Setting("robot", robot_name, source))
    except ConfigError as exc:
        out.append(Setting("robot", None, f"not set: {exc}"))
    if robot_name == "local":
        from fetchsync.link.transport import local_robot_home

        out.append(
            Setting("user", None, f"none: the local robot is the directory {local_robot_home()}")
        )
    elif robot_name is not None:
        try:
            out.append(Setting("user", *config.user_with_source(user, host=robot_name)))
        except ConfigError as exc:
            out.append(Setting("user", None, f"not set: {exc}"))
    else:
        out.append(Setting("user", None, "not set: there is no robot"))
    local = None
    try:
        local, source = config.workspace_with_source(workspace)
        out.append(Setting("workspace", config.home_relative(local), source))
    except ConfigError as exc:
        out.append(Setting("workspace", None, f"not set: {exc}"))
    remote = None
    try:
        remote, source = config.remote_workspace_with_source(remote_workspace, workspace=local)
        out.append(Setting("remote workspace", remote, source))
    except ConfigError as exc:
        out.append(Setting("remote workspace", None, f"not set: {exc}"))
    if local is not None:
        from fetchsync.chores.build import detect_tool, local_markers, manifests

        tool = detect_tool(local_markers(local), manifests(local / "src"))
        out.append(
            Setting(
                "build tool",
                f"auto ({tool} for this workspace)",
                "default; --build-tool chooses, and a build on the robot "
                "detects it from the robot's workspace",
            )
        )
    from fetchsync.link.mux import DEFAULT_PERSIST

    out.append(_variable("FETCHSYNC_PERSIST", f"{DEFAULT_PERSIST:g} s", "persist", " s"))
    out.append(_variable("FETCHSYNC_REMOTE_PYTHON", "python3", "remote python"))
    out.append(
        Setting(
            "ssh config",
            os.path.join(os.path.expanduser("~"), ".ssh", "config"),
            "default, OpenSSH's",
        )
    )
    try:
        target = resolve(robot, user, workspace, remote_workspace)
    except ConfigError:
        return out  # said above
    from fetchsync.link.session import robot_id
    from fetchsync.sync.state import state_path

    out.append(
        Setting(
            "state",
            str(state_path(robot_id(target), target.remote_workspace)),
            "XDG_STATE_HOME"
            if os.environ.get("XDG_STATE_HOME", "").strip()
            else "default, under ~/.local/state; XDG_STATE_HOME moves it",
        )
    )
    out.append(
        Setting(
            "a push goes",
            where_line(
                "", target, local=target.workspace / "src", remote=target.remote_workspace + "/src"
            ).strip(),
            "the settings above",
        )
    )
    return out


@click.command("config")
@target_options(host_key=False)
@click.option("--json", "as_json", is_flag=True, help="Print a JSON list instead of the table.")
def command(
    robot: str | None,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    as_json: bool,
) -> None:
    """Show each resolved setting and where it came from.

    \b
    Each target setting is the first of these that is set:
      robot             --robot, FETCHSYNC_ROBOT, FETCH_ROBOT, the host of ROS_MASTER_URI
      user              --user, FETCHSYNC_USER, FETCH_USER, the ssh config's User, $USER
      workspace         --workspace, FETCHSYNC_WORKSPACE, FETCH_WORKSPACE,
                        the workspace around the current directory, ~/$ROS_DISTRO
      remote workspace  --remote-workspace, FETCHSYNC_REMOTE_WORKSPACE,
                        FETCH_REMOTE_WORKSPACE, the local workspace with ~ for home

    Takes the options of the robot verbs, to show what they would do with
    them. Connects to nothing; exits 0 also when a setting is missing.
    """
    from fetchsync.console import printable  # a directory's name may hold escape sequences

    found = settings(robot=robot, user=user, workspace=workspace, remote_workspace=remote_workspace)
    if as_json:
        rows: list[dict[str, Any]] = [dict(asdict(s), order=ORDERS.get(s.name)) for s in found]
        click.echo(json.dumps(rows, sort_keys=True))
        return
    width = max(len(s.name) for s in found)
    for s in found:
        value = s.value if s.value is not None else "-"
        source = (
            s.source if s.source.startswith(("not set", "none", "default")) else f"from {s.source}"
        )
        click.echo(printable(f"{s.name:<{width}}  {value}  ({source})"))
    click.echo("")
    click.echo("Each is the first of these that is set:")
    for name, order in ORDERS.items():
        click.echo(f"  {name:<{width}}  {order}")
