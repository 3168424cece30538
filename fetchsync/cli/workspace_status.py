"""``fetchsync workspace-status``: the click layer over :mod:`fetchsync.chores.workspace_status`."""

from __future__ import annotations

import json

import click

from fetchsync.chores.workspace_status import DEFAULT_TIMEOUT, optional_target, workspace_status
from fetchsync.cli.common import say_where, target_options
from fetchsync.config import resolve_workspace


@click.command("workspace-status")
@target_options
@click.option(
    "--exclude",
    "excludes",
    multiple=True,
    metavar="PATTERN",
    help="Exclude paths from the robot comparison (gitignore syntax), as for push; repeatable.",
)
@click.option("--no-robot", is_flag=True, help="Leave the robot column out; connect to nothing.")
@click.option(
    "--timeout",
    type=click.FloatRange(min=0, min_open=True),
    default=DEFAULT_TIMEOUT,
    show_default=True,
    metavar="SECONDS",
    help="How long to wait for the robot before calling it unreachable.",
)
@click.option("--json", "as_json", is_flag=True, help="Print a JSON list instead of the table.")
def command(
    robot: str | None,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    excludes: tuple[str, ...],
    no_robot: bool,
    timeout: float,
    as_json: bool,
) -> None:
    """Show every git repository under src/ and whether the robot's copy matches.

    One row per repository, nested ones and submodules included: its branch,
    its commit (with -dirty when tracked files are modified), and top-level
    directories outside git as untracked. When a robot is configured, a
    column says whether the robot holds the same files (in sync, N paths
    differ, unreachable, not pushed yet). Exits 0 whatever it finds.
    """
    target = (
        None
        if no_robot
        else optional_target(
            robot=robot, user=user, workspace=workspace, remote_workspace=remote_workspace
        )
    )
    ws = target.workspace if target is not None else resolve_workspace(workspace)
    if target is not None:
        say_where(
            "workspace-status",
            target,
            local=ws / "src",
            remote=target.remote_workspace + "/src",
            direction="both",
        )
    status = workspace_status(
        ws / "src",
        target=target,
        excludes=excludes,
        accept_fingerprint=accept_host_key,
        timeout=timeout,
    )
    from fetchsync.console import printable

    for note in status.notes:
        click.echo(f"fetchsync: {printable(note)}", err=True)
    if as_json:
        click.echo(json.dumps(status.to_json(), sort_keys=True))
    else:
        for line in status.lines():
            click.echo(printable(line))
