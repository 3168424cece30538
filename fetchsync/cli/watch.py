"""``fetchsync watch``, ``status`` and ``flush``: the live agent and how to talk to it."""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any, Callable

import click

from fetchsync.cli.build_flags import BUILD_TYPES, TOOLS, BuildCommand
from fetchsync.cli.common import resolve, target_options, where_line
from fetchsync.errors import SyncError, UsageError


def _stamp() -> str:
    return time.strftime("%H:%M:%S")


class _WatchCommand(BuildCommand):
    """``--build [ARGS]`` as push's, also before another of watch's ``--option=value with spaces``
    (which the optional value's rule would otherwise take as ARGS)."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        names = {
            name for p in self.params for name in getattr(p, "opts", ()) if name.startswith("--")
        }
        out = list(args)
        for i, arg in enumerate(out[:-1]):
            if arg == "--":
                break
            if arg == "--build" and out[i + 1].split("=", 1)[0] in names:
                out[i] = "--build="
        return super().parse_args(ctx, out)


@click.command(cls=_WatchCommand)
@target_options
@click.option(
    "--exclude",
    "excludes",
    multiple=True,
    metavar="PATTERN",
    help="Exclude paths matching PATTERN (gitignore syntax); repeatable.",
)
@click.option(
    "--strict",
    is_flag=True,
    help="Refuse to replace files changed on the robot since the last sync.",
)
@click.option(
    "--build",
    "builds",
    multiple=True,
    metavar="[ARGS]",
    help="After each batch, rebuild on the robot the packages it changed, passing ARGS "
    "to the build tool (--build=-j4), as push --build; a newer batch cancels a "
    "build in progress.",
)
# the spelling of --build=ARGS before push and watch shared one; kept for units written then
@click.option("--build-args", hidden=True, default=None)
@click.option(
    "--build-type",
    type=click.Choice(BUILD_TYPES),
    default="default",
    help="CMAKE_BUILD_TYPE of the builds ('default' passes none).",
)
@click.option(
    "--build-tool",
    type=click.Choice(TOOLS),
    default="auto",
    help="catkin_make, catkin (catkin build) or colcon. Default: what the remote "
    "workspace is set up for.",
)
@click.option(
    "--install-service",
    is_flag=True,
    help="Write a systemd user unit running this watch (with these options) and "
    "print how to enable it; does not start watching.",
)
@click.option(
    "--uninstall-service",
    is_flag=True,
    help="Remove the systemd user unit of this workspace and robot.",
)
def watch(
    robot: str | None,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    excludes: tuple[str, ...],
    strict: bool,
    builds: tuple[str, ...],
    build_args: str | None,
    build_type: str,
    build_tool: str,
    install_service: bool,
    uninstall_service: bool,
) -> None:
    """Keep the robot's src/ identical to the local one while you work.

    Checks everything once, says it is live, then mirrors each change within
    milliseconds. When the robot drops off the network, changes are kept and
    sent when it is back. Stop with Ctrl-C. Talk to it with `fetchsync status`
    and `fetchsync flush`; `fetchsync push` goes through it.

    With --build [ARGS], each batch that changed something is followed by a build on
    the robot of the packages it touched (the nearest package.xml above each
    path), its output streamed here.
    """
    from fetchsync.agent.service import Agent
    from fetchsync.cli.fleet import names_given
    from fetchsync.sync.engine import build_rules

    names = names_given(robot)
    if names is not None and (install_service or uninstall_service):
        raise UsageError(
            f"a service watches one robot ({', '.join(names)} given): install one per robot"
        )
    target = resolve(names[0] if names else robot, user, workspace, remote_workspace)
    given = [*builds, *([build_args] if build_args is not None else [])]
    with_args = [b for b in given if b.strip()]
    if len(with_args) > 1:
        raise UsageError("watch builds each batch one way: give --build ARGS once")
    build, build_args = bool(given), (with_args[0] if with_args else "")
    if not build and (build_type != "default" or build_tool != "auto"):
        click.echo(
            "fetchsync: warning: --build-type and --build-tool have no effect without --build",
            err=True,
        )
    if install_service and uninstall_service:
        raise UsageError("--install-service and --uninstall-service do not go together")
    if install_service or uninstall_service:
        from fetchsync.agent import unit

        if uninstall_service:
            _path, notes = unit.uninstall(target)
        else:
            args: list[str] = []
            for pattern in excludes:
                args += ["--exclude", pattern]
            if strict:
                args.append("--strict")
            if accept_host_key:
                args += ["--accept-host-key", accept_host_key]
            if build:
                args.append(f"--build={build_args}" if build_args.strip() else "--build")
                if build_type != "default":
                    args += ["--build-type", build_type]
                if build_tool != "auto":
                    args += ["--build-tool", build_tool]
            _path, notes = unit.install(target, args)
        for line in notes:
            click.echo(line)
        return
    src = target.workspace / "src"
    if not src.is_dir():
        raise SyncError(f"{src} does not exist; nothing to watch", hint="check --workspace")

    def say(line: str) -> None:
        from fetchsync.console import printable

        click.echo(
            f"{_stamp()} {printable(line)}",
            err=line.startswith(("error", "conflict", "offline", "build: error")),
        )

    build_options = (
        {"tool": build_tool, "build_type": build_type, "args": build_args} if build else None
    )
    if names is not None:
        _fleet_watch(
            names,
            src=src,
            user=user,
            workspace=workspace,
            remote_workspace=remote_workspace,
            accept_host_key=accept_host_key,
            excludes=excludes,
            strict=strict,
            build_options=build_options,
            say=say,
        )
        return
    agent = Agent(
        target,
        rules=build_rules(excludes),
        policy="refuse" if strict else "preserve",
        accept_fingerprint=accept_host_key,
        on_event=say,
        build=build_options,
    )
    agent.acquire()

    def on_signal(_signo: int, _frame: Any) -> None:
        agent.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    where = where_line("watch", target, local=src, remote=target.remote_workspace + "/src")
    click.echo(f"{_stamp()} {where} (status: fetchsync status)", err=True)
    try:
        agent.run()
    finally:
        agent.release()
    click.echo(f"{_stamp()} stopped", err=True)


def _fleet_watch(
    names: list[str],
    *,
    src: Path,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    excludes: tuple[str, ...],
    strict: bool,
    build_options: dict[str, Any] | None,
    say: Callable[[str], None],
) -> None:
    """``watch`` of several robots: one watcher feeding one agent per robot
    (:mod:`fetchsync.agent.fleet`); each robot's lines are prefixed ``[robot]``."""
    from fetchsync.agent.fleet import FleetWatch
    from fetchsync.agent.service import Agent
    from fetchsync.console import printable
    from fetchsync.sync.engine import build_rules

    agents: list[Agent] = []
    for name in names:
        target = resolve(name, user, workspace, remote_workspace)
        prefix = f"[{printable(name)}] "

        def on_event(line: str, prefix: str = prefix) -> None:
            say(prefix + line)

        agents.append(
            Agent(
                target,
                rules=build_rules(excludes),
                policy="refuse" if strict else "preserve",
                accept_fingerprint=accept_host_key,
                on_event=on_event,
                build=build_options,
                own_watcher=False,
            )
        )
    fleet = FleetWatch(agents, src=str(src), rules=build_rules(excludes), say=say)
    fleet.acquire()

    def on_signal(_signo: int, _frame: Any) -> None:
        fleet.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    for name, agent in zip(names, agents):
        t = agent.target
        where = where_line("watch", t, local=src, remote=t.remote_workspace + "/src")
        click.echo(f"{_stamp()} [{printable(name)}] {where}", err=True)
    click.echo(f"{_stamp()} watching for {len(agents)} robots (status: fetchsync status)", err=True)
    try:
        fleet.run()
    finally:
        fleet.release()
    click.echo(f"{_stamp()} stopped", err=True)


def _fleet_sockets(
    robot: str | None, user: str | None, workspace: str | None, remote_workspace: str | None
) -> list[tuple[str, Path]] | None:
    """The robots and agent sockets status and flush talk to when they are several: those
    ``--robot`` (or the robot variables) name as a fleet, else, with no ``--robot``, those
    of a fleet watch running on this workspace; None for the single-robot way."""
    from fetchsync.agent.control import agent_paths, call
    from fetchsync.agent.fleet import fleet_paths
    from fetchsync.cli.fleet import names_given
    from fetchsync.config import resolve_workspace

    names = names_given(robot)
    if names is not None:
        return [
            (name, agent_paths(resolve(name, user, workspace, remote_workspace))[1])
            for name in names
        ]
    if robot is not None:
        return None
    src = resolve_workspace(workspace) / "src"
    reply = call(fleet_paths(src)[1], {"cmd": "status"}, timeout=5)
    fleet = reply.get("fleet") if reply else None
    if not isinstance(fleet, dict):
        return None
    return [
        (str(r["robot"]), Path(str(r["socket"])))
        for r in fleet.get("robots", [])
        if isinstance(r, dict) and "robot" in r and "socket" in r
    ] or None


def _in_parallel(
    sockets: list[tuple[str, Path]], ask: Callable[[Path], dict[str, Any] | None]
) -> list[dict[str, Any] | None]:
    """``ask(socket)`` of each robot's agent at once (one offline robot's wait is not the
    others'), the replies in the robots' order."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=max(1, min(len(sockets), 32))) as pool:
        return list(pool.map(lambda pair: ask(pair[1]), sockets))


def _agent_socket(
    robot: str | None, user: str | None, workspace: str | None, remote_workspace: str | None
) -> tuple[Any, Path]:
    from fetchsync.agent.control import agent_paths

    target = resolve(robot, user, workspace, remote_workspace)
    return target, agent_paths(target)[1]


@click.command()
@target_options(host_key=False)  # it asks the agent, which holds the connection
@click.option("--json", "as_json", is_flag=True, help="Print the status as JSON.")
def status(
    robot: str | None,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    as_json: bool,
) -> None:
    """Show what the running agent is doing: live, syncing or offline."""
    from fetchsync.agent.control import call
    from fetchsync.console import printable

    several = _fleet_sockets(robot, user, workspace, remote_workspace)
    if several is not None:
        replies = _in_parallel(several, lambda sock: call(sock, {"cmd": "status"}, timeout=5))
        states = [r["status"] if r and isinstance(r.get("status"), dict) else None for r in replies]
        if as_json:
            click.echo(
                json.dumps(
                    [
                        st or {"state": "stopped", "robot": name}
                        for (name, _), st in zip(several, states)
                    ],
                    sort_keys=True,
                )
            )
        else:
            for (name, _), st in zip(several, states):
                if st is None:
                    click.echo(
                        f"[{printable(name)}] stopped: no agent is watching for {printable(name)}"
                    )
                    continue
                line = _status_line(st)
                if st.get("last_error") and st.get("state") != "live":
                    line += f"; last error: {printable(st['last_error'])}"
                click.echo(f"[{printable(name)}] {line}")
        if any(st is None for st in states):
            sys.exit(3)
        return
    target, sock = _agent_socket(robot, user, workspace, remote_workspace)
    reply = call(sock, {"cmd": "status"}, timeout=5)
    if reply is None:
        if as_json:
            click.echo(json.dumps({"state": "stopped", "robot": target.robot}))
        else:
            click.echo(f"no agent is watching {target.workspace / 'src'} for {target.robot}")
        sys.exit(3)
    st = reply["status"]
    if as_json:
        click.echo(json.dumps(st, sort_keys=True))
        return
    click.echo(_status_line(st))
    if st.get("last_error"):
        click.echo(f"last error: {printable(st['last_error'])}")


def _status_line(st: dict[str, Any]) -> str:
    """One agent's status as one line: state, places, last sync, pending, conflicts, build."""
    when = (
        time.strftime("%H:%M:%S", time.localtime(st["last_sync"]))
        if st.get("last_sync")
        else "never"
    )
    line = f"{st['state']}: {st['workspace']} -> {st['robot']}:{st['remote']}; last sync {when}"
    if st.get("offline_since"):
        line += f"; offline since {time.strftime('%H:%M:%S', time.localtime(st['offline_since']))}"
    line += f"; {st['pending']} pending; {len(st.get('conflicts', []))} conflicts"
    b = st.get("build")
    if b:
        line += f"; build {b['state']}"
        if b.get("building"):
            line += f" ({' '.join(b['building']) or 'everything'})"
        elif b.get("last"):
            last = b["last"]
            pk = (
                last["packages"]
                if isinstance(last["packages"], str)
                else " ".join(last["packages"])
            )
            line += f", last {last['result']} ({pk})"
    return line


@click.command()
@target_options
@click.argument("paths", nargs=-1, type=click.Path())
@click.option(
    "--timeout",
    default=30.0,
    show_default=True,
    metavar="SECONDS",
    help="How long to wait for the agent.",
)
def flush(
    robot: str | None,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    paths: tuple[str, ...],
    timeout: float,
) -> None:
    """Return once the files saved before this call are on the robot.

    The save hook for editors: give the saved file(s) and it returns as soon
    as they are there (non-zero if they cannot be). With no agent running it
    does a one-shot push instead (for which --accept-host-key is).
    """
    from fetchsync.agent.control import call

    several = _fleet_sockets(robot, user, workspace, remote_workspace)
    if several is not None:
        from fetchsync.config import resolve_workspace

        rel = _relative(paths, (resolve_workspace(workspace) / "src").resolve())
        _fleet_flush(
            several,
            rel,
            timeout=timeout,
            options={
                "robot": robot,
                "user": user,
                "workspace": workspace,
                "remote_workspace": remote_workspace,
                "accept_host_key": accept_host_key,
            },
        )
        return
    target, sock = _agent_socket(robot, user, workspace, remote_workspace)
    rel = _relative(paths, (target.workspace / "src").resolve())
    reply = call(sock, {"cmd": "flush", "paths": rel}, timeout=timeout)
    if reply is None:
        ctx = click.get_current_context()
        from fetchsync.cli import push

        ctx.invoke(
            push,
            robot=robot,
            user=user,
            workspace=workspace,
            remote_workspace=remote_workspace,
            accept_host_key=accept_host_key,
        )
        return
    if not reply.get("ok"):
        raise SyncError(f"not on the robot yet: {reply.get('error') or 'unknown error'}")


def _relative(paths: tuple[str, ...], src: Path) -> list[str]:
    """The saved files as paths under ``src``; a one-line error for one outside it."""
    rel: list[str] = []
    for p in paths:
        full = Path(os.path.abspath(p))
        try:
            rel.append(
                full.relative_to(src).as_posix()
                if full.is_relative_to(src)
                else Path(os.path.realpath(full)).relative_to(src).as_posix()
            )
        except ValueError:
            raise UsageError(f"{p} is not under {src}") from None
    return rel


def _fleet_flush(
    sockets: list[tuple[str, Path]],
    rel: list[str],
    *,
    timeout: float,
    options: dict[str, Any],
) -> None:
    """``flush`` of several robots: each agent at once; returns once the files are on every
    robot that is online, and fails naming each robot they are not on (one that is offline
    is not waited for: its agent sends them when it is back). With no agent for any of
    them, a fleet push of the robots named (``options``: the target options), as a single
    flush pushes."""
    from fetchsync.agent.control import call
    from fetchsync.cli.fleet import _write
    from fetchsync.console import printable

    payload = {"cmd": "flush", "paths": rel, "skip_offline": True}
    replies = _in_parallel(sockets, lambda sock: call(sock, payload, timeout=timeout))
    if all(r is None for r in replies) and options.get("robot") is not None:
        from fetchsync.cli import push

        click.get_current_context().invoke(push, **options)
        return
    missing = []
    for (name, _), reply in zip(sockets, replies):
        if reply is None:
            why = "no agent is watching for it"
        elif reply.get("ok"):
            continue
        else:
            why = str(reply.get("error") or "unknown error")
        missing.append(name)
        _write(2, f"fetchsync: [{printable(name)}] not on the robot yet: {printable(why)}\n")
    if missing:
        raise SyncError(f"not on {len(missing)} of {len(sockets)} robots yet: {', '.join(missing)}")
