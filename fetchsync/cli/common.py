"""What every robot verb shares: the fetch_tools target options, their resolution, and the
line that says where an answer goes."""

from __future__ import annotations

import sys
from typing import Any, Callable

import click

from fetchsync.console import ARROW, BOTH, robot_place, where_line

__all__ = ["ARROW", "BOTH", "robot_place", "where_line"]


def complete_robot(ctx: click.Context, param: click.Parameter, incomplete: str) -> list[Any]:
    """``--robot`` completion (ssh config, known_hosts, fetchN): :func:`fetchsync.chores.shell.complete_robot`."""
    from fetchsync.chores.shell import complete_robot as complete

    return complete(ctx, param, incomplete)


def _robots(_ctx: click.Context, _param: click.Parameter, values: tuple[str, ...]) -> str | None:
    """The ``--robot`` values as one comma-separated list (None when none): several robots
    are a fleet for push and run (:mod:`fetchsync.cli.fleet`), refused in one line elsewhere."""
    names = [v.strip() for v in values if v.strip()]
    return ",".join(names) if names else None


def target_options(func: Callable[..., Any] | None = None, *, host_key: bool = True) -> Any:
    """The fetch_tools options every robot verb takes; ``host_key=False`` leaves out
    ``--accept-host-key`` (for verbs that open no connection of their own)."""
    opts = [
        click.option(
            "--robot",
            multiple=True,
            callback=_robots,
            metavar="NAME",
            shell_complete=complete_robot,
            help="Robot host name (or 'local'); push, run, watch, create-account, workspace-status and snapshot take "
            "several (repeated, "
            "a,b, or @group of robots.toml). "
            "Default: $FETCHSYNC_ROBOT, $FETCH_ROBOT, the host of $ROS_MASTER_URI.",
        ),
        click.option(
            "--user",
            help="User on the robot. Default: $FETCHSYNC_USER, $FETCH_USER, "
            "the ssh config's User, $USER.",
        ),
        click.option(
            "--workspace",
            type=click.Path(file_okay=False),
            help="Local workspace. Default: $FETCHSYNC_WORKSPACE, $FETCH_WORKSPACE, "
            "the workspace around the current directory, ~/$ROS_DISTRO.",
        ),
        click.option(
            "--remote-workspace",
            help="Workspace on the robot. Default: "
            "$FETCHSYNC_REMOTE_WORKSPACE, $FETCH_REMOTE_WORKSPACE, the local path under ~.",
        ),
    ]
    if host_key:
        opts.append(
            click.option(
                "--accept-host-key",
                metavar="SHA256:...",
                help="Accept the robot's host key with this fingerprint (shown when it is unknown).",
            )
        )

    def decorate(f: Callable[..., Any]) -> Callable[..., Any]:
        for opt in reversed(opts):
            f = opt(f)
        return f

    return decorate(func) if func is not None else decorate


def resolve(
    robot: str | None, user: str | None, workspace: str | None, remote_workspace: str | None
) -> Any:
    """The :class:`fetchsync.config.Target` for these options (environment as fallback)."""
    from fetchsync.config import resolve_target

    return resolve_target(
        robot=robot,
        user=user,
        workspace=workspace,
        remote_workspace=remote_workspace,
        defer_ssh_user=True,
    )


def say_where(
    verb: str,
    target: Any,
    *,
    local: Any = None,
    remote: str | None = None,
    direction: str = "to",
    terminal_only: bool = False,
) -> None:
    """Say on stderr, before ``verb`` starts, where its answer goes (:func:`where_line`),
    as fetch_tools' ``Pushing X/src to user@robot:Y/src`` did.

    A user left to the ssh config is named as the connection will use it (see
    :func:`fetchsync.config.login_name`). ``terminal_only``: only when stderr is a
    terminal (``run``, whose stderr is the command's). ``-q`` silences it.
    """
    if terminal_only and not sys.stderr.isatty():
        return
    ctx = click.get_current_context(silent=True)
    if ctx is not None and ctx.find_root().meta.get("fetchsync.quiet"):
        return  # -q (fetchsync.cli.QUIET)
    click.echo(where_line(verb, target, local=local, remote=remote, direction=direction), err=True)
