"""``fetchsync snapshot`` (alias ``debug-snapshot``): the click layer over :mod:`fetchsync.chores.snapshot`.

Called by fetch_tools' name, ``debug-snapshot``, it does what fetch_tools'
did: the ``fetch`` profile, logged in as ``fetch``, into a ``.zip``; called
``snapshot``, the ``generic`` profile into a ``.tar.gz``. Options override both.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Any

import click

from fetchsync.chores.snapshot import (
    DEFAULT_BAG_DURATION,
    DEFAULT_JOBS,
    FETCH_BAG_TOPICS,
    MAX_JOBS,
    PROFILES,
    Collector,
    CommandResult,
    PasswordSource,
    Snapshot,
    load_config,
    parse_extra,
    select_collectors,
)
from fetchsync.cli.common import resolve, target_options
from fetchsync.cli.fleet import fleet_options, robots_for

PASSWORD_VAR = "FETCHSYNC_SUDO_PASSWORD"
FETCH_TOOLS_NAME = "debug-snapshot"
FETCH_LOGIN = "fetch"
"""fetch_tools' debug-snapshot logged in as Fetch's admin account."""


@click.command("snapshot")
@target_options
@click.option(
    "--profile",
    type=click.Choice(sorted(PROFILES)),
    default=None,
    help="What to collect: generic (the default), or fetch: fetch_tools' "
    "debug-snapshot (read_board, robot/roscore/joystick services, robot.log, "
    "syslog, netplan, roswtf, a 10 s bag...), logged in as fetch unless --user. "
    "Default: fetch when called as debug-snapshot.",
)
@click.option(
    "--zip/--tar",
    "as_zip",
    default=None,
    help="Write a .zip (as fetch_tools) or a .tar.gz. Default: .zip when called as "
    "debug-snapshot or --output ends in .zip, else .tar.gz.",
)
@click.option(
    "--output",
    "-o",
    type=click.Path(),
    default=".",
    help="Archive path, or a directory for snapshot-<robot>-<time>.tar.gz. "
    "Default: the current directory.",
)
@click.option(
    "--only",
    multiple=True,
    metavar="NAME",
    help="Run only this collector; repeatable (see --list).",
)
@click.option("--skip", multiple=True, metavar="NAME", help="Leave this collector out; repeatable.")
@click.option(
    "--extra",
    multiple=True,
    metavar="NAME=COMMAND",
    help="Also run COMMAND (a shell command line) into NAME.txt; repeatable.",
)
@click.option(
    "--config",
    "config_file",
    type=click.Path(dir_okay=False, exists=True),
    help="TOML (or .json) file with collectors to add and only/skip lists.",
)
@click.option(
    "--bag",
    "bag_topics",
    multiple=True,
    metavar="TOPIC",
    help="Record this topic into a short bag (rosbag / ros2 bag); repeatable. The "
    "fetch profile records /robot_state /diagnostics /diagnostics_agg "
    "/battery_state unless given.",
)
@click.option(
    "--bag-duration",
    type=click.FloatRange(min=0, min_open=True, max=3600),
    default=DEFAULT_BAG_DURATION,
    show_default=True,
    metavar="SECONDS",
    help="How long to record the bag.",
)
@click.option(
    "--sudo/--no-sudo",
    "use_sudo",
    default=None,
    help="Run dmesg, the journal and other collectors that need it through sudo "
    f"(the password from ${PASSWORD_VAR} or asked once). Default: when the login "
    "user is not root and a password is to be had.",
)
@click.option(
    "--fetch-password",
    is_flag=False,
    flag_value="",
    default=None,
    hidden=True,
    help="fetch_tools' option: the sudo password (bare: ask for it).",
)
@click.option(
    "--jobs",
    "-j",
    type=click.IntRange(1, MAX_JOBS),
    default=DEFAULT_JOBS,
    show_default=True,
    help="Commands run at once (one SSH channel each).",
)
@click.option(
    "--list",
    "list_only",
    is_flag=True,
    help="Print the collectors that would run and exit; connects to nothing.",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of text.")
@fleet_options(jobs=False)  # -j is the commands at once on each robot
@click.pass_context
def command(
    ctx: click.Context,
    robot: str | None,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    profile: str | None,
    as_zip: bool | None,
    output: str,
    only: tuple[str, ...],
    skip: tuple[str, ...],
    extra: tuple[str, ...],
    config_file: str | None,
    bag_topics: tuple[str, ...],
    bag_duration: float,
    use_sudo: bool | None,
    fetch_password: str | None,
    jobs: int,
    list_only: bool,
    as_json: bool,
    fail_fast: bool,
    retry_failed: bool,
) -> None:
    """Collect diagnostics from the robot into one timestamped archive.

    System state (kernel, OS, memory, disks, processes, kernel log, journal,
    network, USB and PCI devices, installed ROS packages) and ROS state (nodes,
    topics, services, parameters; ROS 1 or ROS 2, whichever the robot has),
    optionally a short bag. Commands run in parallel, each with a timeout; a
    tool the robot lacks is recorded as missing. manifest.json in the archive
    lists every command with its exit code, duration and status.

    As debug-snapshot (fetch_tools' name): --profile fetch into a .zip.

    On several robots (--robot a,b or @group), up to 8 robots at once, each
    archive named after its robot in the --output directory; a table ends it.
    """
    fetch_tools = ctx.info_name == FETCH_TOOLS_NAME
    profile = profile or ("fetch" if fetch_tools else "generic")
    if as_zip is None:
        as_zip = fetch_tools or output.lower().endswith(".zip")
    config = load_config(config_file) if config_file else None
    collectors = select_collectors(
        config=config,
        only=only,
        skip=skip,
        extra=[parse_extra(e) for e in extra],
        base=PROFILES[profile],
    )
    if profile == "fetch":
        bag_topics = bag_topics or FETCH_BAG_TOPICS
        user = user or FETCH_LOGIN
    if list_only:
        _print_list(collectors, as_json)
        return
    if fetch_password:
        click.echo(
            "fetchsync: warning: a password on the command line is visible to other "
            f"users of this machine; set {PASSWORD_VAR} or let fetchsync ask",
            err=True,
        )
    policy = (
        "auto"
        if use_sudo is None and fetch_password is None
        else ("never" if use_sudo is False else "always")
    )

    from fetchsync.chores.snapshot import take_snapshot
    from fetchsync.link.session import open_transport

    robots = robots_for(ctx.info_name or "snapshot", robot, retry_failed=retry_failed)
    if robots is not None:
        sys.exit(
            _fleet_snapshot(
                robots,
                user=user,
                workspace=workspace,
                remote_workspace=remote_workspace,
                accept_host_key=accept_host_key,
                collectors=collectors,
                output=output,
                jobs=jobs,
                policy=policy,
                password=_fleet_password(policy, fetch_password),
                bag_topics=bag_topics,
                bag_duration=bag_duration,
                archive_format="zip" if as_zip else "tar",
                as_json=as_json,
                fail_fast=fail_fast,
            )
        )
    target, overlay = _target(robot, user, workspace, remote_workspace)
    from fetchsync.cli.common import say_where

    say_where("snapshot", target, local=Path(output).resolve(), remote=overlay, direction="from")
    progress = _Progress(total=len(collectors) + bool(bag_topics), enabled=not as_json)
    transport = open_transport(target, accept_fingerprint=accept_host_key, persistent=False)
    try:
        snap = take_snapshot(
            transport,
            robot=target.robot,
            collectors=collectors,
            output=output,
            jobs=jobs,
            sudo=policy,
            password=_password_source(target.robot, fetch_password),
            bag_topics=bag_topics,
            bag_duration=bag_duration,
            overlay=overlay,
            progress=progress,
            archive_format="zip" if as_zip else "tar",
        )
    finally:
        progress.close()
        transport.close()
    _print_snapshot(snap, as_json)
    if snap.link_lost:
        from fetchsync.errors import LinkLostError

        raise LinkLostError(f"{snap.link_lost}; the archive holds what was collected before")


def _target(
    robot: str | None, user: str | None, workspace: str | None, remote_workspace: str | None
) -> tuple[Any, str | None]:
    """The target, and the remote workspace to source (None when none is configured).

    A snapshot needs no workspace: without one (no option, variable or
    ROS_DISTRO) it is resolved against a placeholder and not sourced.
    """
    from fetchsync.config import REMOTE_WORKSPACE_VARS, WORKSPACE_VARS

    known = (
        workspace
        or remote_workspace
        or any(os.environ.get(v) for v in (*WORKSPACE_VARS, *REMOTE_WORKSPACE_VARS, "ROS_DISTRO"))
    )
    if known:
        target = resolve(robot, user, workspace, remote_workspace)
        return target, target.remote_workspace
    placeholder = str(Path.home() / ".fetchsync-snapshot-no-workspace")
    return resolve(robot, user, placeholder, None), None


def _password_source(robot: str, given: str | None) -> PasswordSource:
    """The password from --fetch-password, else $FETCHSYNC_SUDO_PASSWORD, else the terminal.

    A fixed password is offered once; the terminal is asked up to three times.
    """
    fixed = given or os.environ.get(PASSWORD_VAR) or None

    def source(attempt: int) -> str | None:
        if fixed is not None:
            return fixed if attempt == 0 else None
        if not sys.stdin.isatty():
            return None
        if attempt:
            click.echo("Sorry, try again.", err=True)
        value: str = click.prompt(
            f"[sudo] password on {robot}", hide_input=True, err=True, default="", show_default=False
        )
        return value or None

    return source


def _fleet_password(policy: str, given: str | None) -> PasswordSource:
    """The sudo password for several robots: --fetch-password or $FETCHSYNC_SUDO_PASSWORD,
    else asked once here, before the robots are worked on, with --sudo at a terminal;
    never asked from the robots' threads."""
    fixed = given or os.environ.get(PASSWORD_VAR) or None
    if fixed is None and policy == "always" and sys.stdin.isatty():
        fixed = (
            click.prompt(
                "[sudo] password on the robots",
                hide_input=True,
                err=True,
                default="",
                show_default=False,
            )
            or None
        )

    def source(attempt: int) -> str | None:
        return fixed if attempt == 0 else None

    return source


def _fleet_snapshot(
    robots: list[str],
    *,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    collectors: tuple[Collector, ...],
    output: str,
    jobs: int,
    policy: str,
    password: PasswordSource,
    bag_topics: tuple[str, ...],
    bag_duration: float,
    archive_format: str,
    as_json: bool,
    fail_fast: bool,
) -> int:
    """A snapshot of each robot into the ``output`` directory, in parallel; the table, the
    exit status. A robot whose link was lost midway keeps its partial archive and fails."""
    from fetchsync.chores.snapshot import take_snapshot
    from fetchsync.cli.fleet import (
        DEFAULT_JOBS,
        Prefixed,
        RobotResult,
        finish,
        run_all,
    )
    from fetchsync.errors import LinkLostError, UsageError
    from fetchsync.link.session import open_transport

    if not Path(output).is_dir():
        raise UsageError(
            f"with several robots, --output is a directory for their archives, not {output}"
        )

    def work(name: str, out: Prefixed) -> RobotResult:
        target, overlay = _target(name, user, workspace, remote_workspace)
        transport = open_transport(target, accept_fingerprint=accept_host_key, persistent=False)
        try:
            snap = take_snapshot(
                transport,
                robot=target.robot,
                collectors=collectors,
                output=output,
                jobs=jobs,
                sudo=policy,
                password=password,
                bag_topics=bag_topics,
                bag_duration=bag_duration,
                overlay=overlay,
                progress=lambda _result: None,
                archive_format=archive_format,
            )
        finally:
            transport.close()
        counts = snap.counts()
        if not as_json:
            out.line(
                f"snapshot: {counts['ok']} ok, {counts['failed']} failed, "
                f"{counts['missing']} missing; {_shown_path(snap.archive)} ({_human(snap.size)})",
                err=False,
            )
        lost = f"{snap.link_lost}; the archive holds what was collected before"
        return RobotResult(
            name,
            result="failed" if snap.link_lost else "ok",
            exit_code=LinkLostError.exit_code if snap.link_lost else 0,
            files=counts["ok"],
            bytes_sent=snap.size,
            error=lost if snap.link_lost else "",
            report=snap.to_json(),
        )

    results = run_all(robots, work, jobs=DEFAULT_JOBS, fail_fast=fail_fast)
    return finish("snapshot", results, as_json=as_json)


class _Progress:
    """``snapshot: 7/25`` on a terminal's stderr while commands finish."""

    def __init__(self, *, total: int, enabled: bool) -> None:
        self.total = total
        self.done = 0
        self.enabled = enabled and sys.stderr.isatty()

    def __call__(self, result: CommandResult) -> None:
        self.done += 1
        if self.enabled:
            sys.stderr.write(f"\rsnapshot: {self.done}/{self.total} {result.name:<24.24}")
            sys.stderr.flush()

    def close(self) -> None:
        if self.enabled and self.done:
            sys.stderr.write("\r" + " " * 50 + "\r")
            sys.stderr.flush()


def _human(n: float) -> str:
    for unit in ("B", "KiB", "MiB"):
        if n < 1024:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def _shown_path(path: Path) -> str:
    try:
        rel = os.path.relpath(path)
    except ValueError:
        return str(path)
    return str(path) if rel.startswith("..") else rel


def _print_snapshot(snap: Snapshot, as_json: bool) -> None:
    if as_json:
        click.echo(json.dumps(snap.to_json(), sort_keys=True))
        return
    counts = snap.counts()
    parts = [f"{counts['ok']} ok", f"{counts['failed']} failed", f"{counts['missing']} missing"]
    parts += [f"{counts[s]} {s}" for s in ("timeout", "skipped") if counts[s]]
    click.echo(
        f"snapshot: {', '.join(parts)}; {_shown_path(snap.archive)} "
        f"({_human(snap.size)}); {snap.manifest['duration']:.1f}s"
    )
    for entry in snap.manifest["commands"]:
        status = entry["status"]
        if status == "failed":
            why = entry.get("error") or f"exit {entry['exit_code']}"
            click.echo(f"  failed: {entry['name']} ({why})", err=True)
        elif status in ("missing", "timeout"):
            click.echo(f"  {status}: {entry['name']}", err=True)
        elif status == "skipped" and str(entry.get("error", "")).startswith("not on the robot"):
            click.echo(f"  skipped: {entry['name']} ({entry['error']})", err=True)
    for note in snap.notes:
        click.echo(f"  note: {note}", err=True)


def _print_list(collectors: tuple[Collector, ...], as_json: bool) -> None:
    if as_json:
        click.echo(
            json.dumps(
                [
                    {
                        "name": c.name,
                        "kind": c.kind,
                        "timeout": c.timeout,
                        "needs_sudo": c.needs_sudo,
                        "command": c.command,
                    }
                    for c in collectors
                ]
            )
        )
        return
    for c in collectors:
        sudo = "sudo" if c.needs_sudo else ""
        click.echo(f"{c.name:<14} {c.kind:<7} {c.timeout:>4g}s {sudo:<4}  {c.command}")
