"""``fetchsync workspace-status``: the click layer over :mod:`fetchsync.chores.workspace_status`."""

from __future__ import annotations

import json
import sys

import click

from fetchsync.chores.workspace_status import (
    DEFAULT_TIMEOUT,
    optional_target,
    workspace_status,
)
from fetchsync.cli.common import say_where, target_options
from fetchsync.cli.fleet import fleet_options, robots_for
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
@fleet_options
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
    jobs: int,
    fail_fast: bool,
    retry_failed: bool,
) -> None:
    """Show every git repository under src/ and whether the robot's copy matches.

    One row per repository, nested ones and submodules included: its branch,
    its commit (with -dirty when tracked files are modified), and top-level
    directories outside git as untracked. When a robot is configured, a
    column says whether the robot holds the same files (in sync, N paths
    differ, unreachable, not pushed yet). Exits 0 whatever it finds.

    On several robots (--robot a,b or @group), each robot's table prefixed
    with its name, then one line per robot; non-zero if one was unreachable.
    """
    robots = None if no_robot else robots_for("workspace-status", robot, retry_failed=retry_failed)
    if robots is not None:
        sys.exit(
            _fleet_status(
                robots,
                user=user,
                workspace=workspace,
                remote_workspace=remote_workspace,
                accept_host_key=accept_host_key,
                excludes=excludes,
                timeout=timeout,
                as_json=as_json,
                jobs=jobs,
                fail_fast=fail_fast,
            )
        )
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


def _fleet_status(
    robots: list[str],
    *,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    excludes: tuple[str, ...],
    timeout: float,
    as_json: bool,
    jobs: int,
    fail_fast: bool,
) -> int:
    """The comparison with each robot, in parallel: a robot that cannot be compared
    (unreachable) is a failed row of the table; ``--json`` gives one report per robot."""
    from fetchsync.cli.common import resolve
    from fetchsync.cli.fleet import Prefixed, RobotResult, finish, quiet, run_all
    from fetchsync.console import printable
    from fetchsync.errors import TransportError

    silent = quiet()

    def work(name: str, out: Prefixed) -> RobotResult:
        target = resolve(name, user, workspace, remote_workspace)
        status = workspace_status(
            target.workspace / "src",
            target=target,
            excludes=excludes,
            accept_fingerprint=accept_host_key,
            timeout=timeout,
        )
        for note in status.notes:
            out.line(f"fetchsync: {printable(note)}")
        if not as_json:
            for line in status.lines():
                out.line(printable(line), err=False)
        unreachable = [n for n in status.notes if f"{target.robot} unreachable" in n]
        return RobotResult(
            name,
            result="failed" if unreachable else "ok",
            exit_code=TransportError.exit_code if unreachable else 0,
            error=unreachable[0] if unreachable else "",
            report={"rows": status.to_json(), "notes": status.notes},
        )

    if not silent:
        click.echo(f"workspace-status: comparing with {len(robots)} robots", err=True)
    results = run_all(robots, work, jobs=jobs, fail_fast=fail_fast)
    return finish("workspace-status", results, as_json=as_json)
