"""What every robot verb shares: the fetch_tools target options and their resolution."""

from __future__ import annotations

from typing import Any, Callable

import click


def complete_robot(ctx: click.Context, param: click.Parameter, incomplete: str) -> list[Any]:
    """``--robot`` completion (ssh config, known_hosts, fetchN): :func:`fetchsync.shell.complete_robot`."""
    from fetchsync.shell import complete_robot as complete
    return complete(ctx, param, incomplete)


def target_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """The fetch_tools options every robot verb takes."""
    opts = [
        click.option("--robot", shell_complete=complete_robot, help="Robot host name (or 'local'). "
                     "Default: $FETCHSYNC_ROBOT, $FETCH_ROBOT, the host of $ROS_MASTER_URI."),
        click.option("--user", help="User on the robot. Default: $FETCHSYNC_USER, $FETCH_USER, "
                     "the ssh config's User, $USER."),
        click.option("--workspace", type=click.Path(file_okay=False),
                     help="Local workspace. Default: $FETCHSYNC_WORKSPACE, $FETCH_WORKSPACE, ~/$ROS_DISTRO."),
        click.option("--remote-workspace", help="Workspace on the robot. Default: "
                     "$FETCHSYNC_REMOTE_WORKSPACE, $FETCH_REMOTE_WORKSPACE, the local path under ~."),
        click.option("--accept-host-key", metavar="SHA256:...",
                     help="Accept the robot's host key with this fingerprint (shown when it is unknown)."),
    ]
    for opt in reversed(opts):
        func = opt(func)
    return func


def resolve(robot: str | None, user: str | None, workspace: str | None,
            remote_workspace: str | None) -> Any:
    """The :class:`fetchsync.config.Target` for these options (environment as fallback)."""
    from fetchsync.config import resolve_target
    return resolve_target(robot=robot, user=user, workspace=workspace,
                          remote_workspace=remote_workspace, defer_ssh_user=True)
