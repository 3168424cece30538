"""``fetchsync run``: run a command on the robot, in the robot's ROS environment."""

from __future__ import annotations

import signal
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import click

from fetchsync.cli.common import resolve, say_where, target_options
from fetchsync.cli.fleet import fleet_options, robots_for
from fetchsync.errors import ConfigError, LinkLostError, TransportError

LINK_EXIT = 255
"""Exit status when fetchsync itself fails to run the command, as ssh's."""

_AFTER_DASHES = "fetchsync.run.after_dashes"


class _Interrupted(BaseException):
    """A signal that ends the local side: the remote command is stopped, we exit 128 + N."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


class _RunCommand(click.Command):
    """Remembers what followed ``--``: those arguments are an argv, not a command line."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if "--" in args:
            ctx.meta[_AFTER_DASHES] = list(args[args.index("--") + 1 :])
        return super().parse_args(ctx, args)


def remote_command_line(words: Sequence[str], *, argv_form: bool) -> str:
    """The shell command line for ``words``: an exact argv after ``--``, else words joined as ssh does."""
    from fetchsync.chores.remote import command_line

    return command_line(words) if argv_form else " ".join(words)


def _target(
    robot: str | None, user: str | None, workspace: str | None, remote_workspace: str | None
) -> tuple[Any, str | None]:
    """The target, and its remote workspace when one is known: run needs no local one.

    The remote workspace is the option or a variable, else the local workspace's
    (its path under ~), else none: then only the robot's distribution is sourced.
    """
    from fetchsync import config
    from fetchsync.cli.fleet import remote_option

    remote_workspace = remote_option(robot, remote_workspace)  # robots.toml's counts as the option
    try:
        local: Path | None = config.resolve_workspace(workspace)
    except ConfigError:
        if workspace is not None:
            raise
        local = None
    remote: str | None = None
    if local is not None or config.first_given(remote_workspace, config.REMOTE_WORKSPACE_VARS):
        remote = config.remote_workspace_with_source(remote_workspace, workspace=local)[0]
    # "/" stands in for what run does not need, only to resolve robot and user as usual
    target = resolve(robot, user, str(local or "/"), remote or "/fetchsync-no-workspace")
    return target, remote


@contextmanager
def _ending_signals() -> Iterator[None]:
    """SIGTERM and SIGHUP unwind like Ctrl-C, so the terminal is restored and the robot told."""

    def interrupted(signum: int, _frame: Any) -> None:
        raise _Interrupted(signum)

    saved = {sig: signal.signal(sig, interrupted) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)


@click.command(
    cls=_RunCommand,
    context_settings={"allow_interspersed_args": False, "ignore_unknown_options": True},
)
@target_options
@click.option(
    "--tty/--no-tty",
    "-t/-T",
    "tty",
    default=None,
    help="Run the command on a terminal (PTY) on the robot. Default: when stdin is a terminal.",
)
@fleet_options
@click.option(
    "--json",
    "as_json",
    is_flag=True,
    help="Print a JSON list of per-robot reports on stdout; the command's output goes to "
    "stderr, prefixed [robot].",
)
@click.argument("words", nargs=-1, required=True, type=click.UNPROCESSED, metavar="COMMAND...")
@click.pass_context
def command(
    ctx: click.Context,
    robot: str | None,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    tty: bool | None,
    jobs: int,
    fail_fast: bool,
    retry_failed: bool,
    as_json: bool,
    words: tuple[str, ...],
) -> None:
    """Run COMMAND on the robot, with the robot's ROS environment.

    \b
    fetchsync run "rostopic list | grep scan"     one argument: a shell command line
    fetchsync run -- printf '%s\\n' "a b" '$HOME'  after --: exactly this argv

    The environment is the remote workspace's devel/setup.bash or
    install/setup.bash, else /opt/ros/$ROS_DISTRO/setup.bash of the robot.
    Ctrl-C stops the command on the robot. Exits with the command's status,
    255 when fetchsync could not run it. On several robots (--robot a,b or
    @group) it runs on each in parallel, its output prefixed [robot]. With
    --json (one robot or several) stdout is the list of per-robot reports
    (robot, result, exit_code, fleet_seconds, error) and the command's own
    output goes to stderr, prefixed [robot].
    """
    from fetchsync.chores.remote import ros_environment, script, wrap
    from fetchsync.console import NO_STATUS, attach
    from fetchsync.link.connection import remote_python
    from fetchsync.link.session import open_transport

    argv_form = ctx.meta.get(_AFTER_DASHES) == list(words)
    line = remote_command_line(words, argv_form=argv_form)
    robots = robots_for("run", robot, retry_failed=retry_failed)
    if robots is None and as_json:
        # one robot's report in the fleet's form: its output beside it, prefixed
        robots = [_target(robot, user, workspace, remote_workspace)[0].robot]
    if robots is not None:
        ctx.exit(
            _fleet_run(
                robots,
                user=user,
                workspace=workspace,
                remote_workspace=remote_workspace,
                accept_host_key=accept_host_key,
                line=line,
                jobs=jobs,
                fail_fast=fail_fast,
                as_json=as_json,
            )
        )
    target, remote_ws = _target(robot, user, workspace, remote_workspace)
    # stderr is the command's: said only to a person watching it
    say_where("run on", target, remote=remote_ws, terminal_only=True)
    # the local robot runs commands over pipes only
    pty = (sys.stdin.isatty() if tty is None else tty) and not target.is_local
    body = script(line, environment=ros_environment(remote_ws))
    transport = None
    channel = None
    try:
        with _ending_signals():
            try:
                transport = open_transport(
                    target, accept_fingerprint=accept_host_key, persistent=False
                )
                channel = transport.exec(wrap(body, tty=pty, python=remote_python()), pty=pty)
                status = attach(channel, pty=pty)
            except BrokenPipeError:
                status = 128 + signal.SIGPIPE  # our reader went away; closing stops the command
            except TransportError as exc:
                if isinstance(exc, LinkLostError):
                    exc.hint = exc.hint or "the command may have been stopped on the robot"
                exc.exit_code = LINK_EXIT
                raise
            except KeyboardInterrupt:
                raise _Interrupted(signal.SIGINT) from None
    except _Interrupted as stop:
        if channel is not None:
            channel.close()
        click.echo(
            f"fetchsync: interrupted; the command on {target.robot} is being stopped", err=True
        )
        ctx.exit(128 + stop.signum)
    finally:
        if channel is not None:
            channel.close()
        if transport is not None:
            transport.close()
    if status == NO_STATUS:
        click.echo(
            f"fetchsync: the command on {target.robot} ended without an exit status", err=True
        )
        ctx.exit(LINK_EXIT)
    ctx.exit(status)


def _fleet_run(
    robots: Sequence[str],
    *,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    line: str,
    jobs: int,
    fail_fast: bool,
    as_json: bool = False,
) -> int:
    """``run`` of one command line on each robot, with an empty stdin (several robots cannot
    share ours) and no terminal; its output prefixed per robot (on stderr with
    ``as_json``, stdout then being the list of reports); the exit status."""
    from fetchsync.chores.remote import ros_environment, script, wrap
    from fetchsync.cli.fleet import (
        Prefixed,
        RobotResult,
        finish,
        remote_option,
        run_all,
    )
    from fetchsync.console import NO_STATUS, attach
    from fetchsync.errors import TransportError
    from fetchsync.link.connection import remote_python
    from fetchsync.link.session import open_transport

    def work(name: str, out: Prefixed) -> RobotResult:
        target, remote_ws = _target(name, user, workspace, remote_option(name, remote_workspace))
        body = script(line, environment=ros_environment(remote_ws))
        try:
            transport = open_transport(target, accept_fingerprint=accept_host_key, persistent=False)
            try:
                channel = transport.exec(wrap(body, tty=False, python=remote_python()), pty=False)
                try:
                    status = attach(channel, pty=False, stdin=None, stdout=out.out, stderr=out.err)
                finally:
                    channel.close()
            finally:
                transport.close()
        except TransportError as exc:
            exc.exit_code = LINK_EXIT
            raise
        if status == NO_STATUS:
            return RobotResult(
                name,
                result="failed",
                exit_code=LINK_EXIT,
                error="the command ended without an exit status",
            )
        if status != 0:
            return RobotResult(
                name, result="failed", exit_code=status, error=f"exit status {status}"
            )
        return RobotResult(name, result="ok")

    results = run_all(robots, work, jobs=jobs, fail_fast=fail_fast, stdout=2 if as_json else 1)
    return finish("run", results, as_json=as_json)
