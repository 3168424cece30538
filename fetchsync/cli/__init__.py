"""The command line: parse, call the library, print. Nothing else lives here.

Every :class:`~fetchsync.errors.FetchsyncError` becomes a one-line message on
stderr and its exit code; heavy modules are imported inside the commands so
that ``fetchsync --help`` and a no-op push start fast.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import click

from fetchsync import __version__
from fetchsync.agent.quick import human, pushable
from fetchsync.cli.build_flags import BuildCommand, build_options, build_request
from fetchsync.cli.common import resolve as _resolve
from fetchsync.cli.common import say_where, target_options
from fetchsync.cli.fleet import fleet_options, robots_for
from fetchsync.errors import FetchsyncError
from fetchsync.trace import mark

# verb -> "module:attribute" of its click command, imported only when used
LAZY_COMMANDS: dict[str, str] = {
    "config": "fetchsync.cli.config:command",
    "conflicts": "fetchsync.cli.conflicts:command",
    "create-account": "fetchsync.cli.create_account:command",
    "lint": "fetchsync.cli.lint:command",
    "run": "fetchsync.cli.run:command",
    "shell-init": "fetchsync.cli.shell_init:command",
    "snapshot": "fetchsync.cli.snapshot:command",
    "debug-snapshot": "fetchsync.cli.snapshot:command",
    "workspace-status": "fetchsync.cli.workspace_status:command",
    "watch": "fetchsync.cli.watch:watch",
    "status": "fetchsync.cli.watch:status",
    "flush": "fetchsync.cli.watch:flush",
}
# each lazy verb's first sentence, for ``--help`` and tab completion without importing
# every verb's module (snapshot, lint, workspace-status: ~70 ms); a test checks that
# each still is its command's own
LAZY_HELP: dict[str, str] = {
    "config": "Show each resolved setting and where it came from.",
    "conflicts": "List, diff or restore the robot's kept versions of files.",
    "create-account": "Create a user's account on the robot, or repair an existing one.",
    "lint": "Lint a file, a directory or a workspace package with ROS's own rules.",
    "run": "Run COMMAND on the robot, with the robot's ROS environment.",
    "shell-init": "Print shell code defining fetch_tools' fetch command, helpers and tab "
    "completion.",
    "snapshot": "Collect diagnostics from the robot into one timestamped archive.",
    "debug-snapshot": "Collect diagnostics from the robot into one timestamped archive.",
    "workspace-status": "Show every git repository under src/ and whether the robot's copy "
    "matches.",
    "watch": "Keep the robot's src/ identical to the local one while you work.",
    "status": "Show what the running agent is doing: live, syncing or offline.",
    "flush": "Return once the files saved before this call are on the robot.",
}


def sync_options(func: Callable[..., Any]) -> Callable[..., Any]:
    opts = [
        click.option(
            "--exclude",
            "excludes",
            multiple=True,
            metavar="PATTERN",
            help="Exclude paths matching PATTERN (gitignore syntax); repeatable.",
        ),
        click.option(
            "--json", "as_json", is_flag=True, help="Print a JSON report instead of text."
        ),
        click.option(
            "--dry-run", "-n", is_flag=True, help="Show what would change; change nothing."
        ),
    ]
    for opt in reversed(opts):
        func = opt(func)
    return func


class _Progress:
    """A progress line on stderr for transfers longer than a second (terminal only)."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled and sys.stderr.isatty()
        self.start = time.monotonic()
        self.shown = False

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled or time.monotonic() - self.start < 1.0 or total <= 0:
            return
        frac = min(done / total, 1.0)
        bar = "#" * int(frac * 30)
        sys.stderr.write(f"\r[{bar:<30}] {frac * 100:5.1f}% {human(done)} of {human(total)}")
        sys.stderr.flush()
        self.shown = True

    def close(self) -> None:
        if self.shown:
            sys.stderr.write("\r" + " " * 70 + "\r")
            sys.stderr.flush()


def _push_via_agent(target: Any) -> Any:
    """The report of a full push made by the running watch agent or resident, or None if
    none runs (or it declined: another install's, busy, gone mid-request)."""
    from fetchsync.agent.control import agent_paths
    from fetchsync.agent.quick import Asked, answered_report, ask
    from fetchsync.errors import ConnectError

    try:
        sock = agent_paths(target)[1]
    except ConnectError:
        return None  # no private socket directory: no agent can be listening
    if str(sock) in Asked.asked:
        return None  # the fast path asked already (fetchsync.__main__), and fell back
    if not sock.exists():
        return None
    reply = ask(sock, target)
    if reply is None:
        return None
    data = answered_report(reply)
    if data is None:
        return None
    from fetchsync.sync.engine import Report

    fields = Report.__dataclass_fields__
    return Report(**{k: v for k, v in data.items() if k in fields})


def _start_resident(target: Any) -> None:
    """Leave a resident behind for the next plain push (fetchsync.agent.resident), unless
    turned off or something already answers at the agent's socket."""
    from fetchsync.agent.control import agent_paths
    from fetchsync.agent.quick import Asked, idle_seconds, start_resident
    from fetchsync.errors import ConnectError

    if idle_seconds() <= 0:
        return
    try:
        sock = agent_paths(target)[1]
    except ConnectError:
        return
    if str(sock) in Asked.answered:
        return
    start_resident(target, sock)
    mark("push: resident started")


def _open_state(target: Any) -> Any:
    """The target's state, saying in one line if it was damaged and set aside."""
    from fetchsync.sync.state import open_state

    state = open_state(target)
    if state.note:
        click.echo(f"fetchsync: note: {state.note}", err=True)
    return state


def _resume_agent(target: Any) -> None:
    """Have a running agent (one paused before a mass deletion, say) push once more, now
    that a forced push made the robot match: it then finds nothing to delete."""
    from fetchsync.agent.control import agent_paths, call

    call(agent_paths(target)[1], {"cmd": "push"}, timeout=60)


def _connection_kind(conn: Any) -> str:
    name = type(conn.transport).__name__
    return {"MuxTransport": "master", "LocalTransport": "local"}.get(name, "ssh")


def _print_report(report: Any, as_json: bool) -> None:
    from fetchsync.agent.quick import print_report

    print_report(report.to_json(), as_json)


# another name for a command, kept for fetch_tools' users: named on its command's
# line in the list, not listed itself
ALIASES: dict[str, str] = {"debug-snapshot": "snapshot"}

_VERBOSE = "fetchsync.verbose"
_ARGV = "fetchsync.argv"
QUIET = "fetchsync.quiet"


def quote_build_hint(args: list[str], option: str) -> str | None:
    """For ``--build --pkg x`` (fetch_tools' users type it so), how to pass ``--pkg x`` to
    the build tool: quoted as one argument, which ``--build`` then takes; None when
    ``option`` did not follow a bare ``--build``."""
    import shlex

    for i in range(1, len(args)):
        if args[i] == "--":
            break
        if args[i] == option and args[i - 1] == "--build":
            words = [option]
            for word in args[i + 1 :]:
                if word.startswith("-"):
                    break
                words.append(word)
            text = " ".join(words)
            if len(words) == 1:
                return f"to pass {option} to the build tool, write --build={shlex.quote(option)}"
            quoted = (
                f'"{text}"'
                if all(c.isalnum() or c in " _-.,=:/+@%" for c in text)
                else shlex.quote(text)
            )
            return f"to pass it to the build tool, quote it with its value: --build {quoted}"
    return None


def _verbose(ctx: click.Context, _param: click.Parameter, count: int) -> None:
    """More log output; counts add up wherever ``-v`` is given (before or after the verb)."""
    if not count:
        return
    import logging

    meta = ctx.find_root().meta
    meta[_VERBOSE] = meta.get(_VERBOSE, 0) + count
    root = logging.getLogger()
    if not root.handlers:
        logging.basicConfig(format="%(name)s: %(message)s")
    root.setLevel(logging.DEBUG if meta[_VERBOSE] > 1 else logging.INFO)


def _quiet(ctx: click.Context, _param: click.Parameter, quiet: bool) -> None:
    if quiet:
        ctx.find_root().meta[QUIET] = True


def _everywhere_options() -> list[click.Option]:
    """The options every verb takes, as the group does: ``-v``, ``-q``."""
    return [
        click.Option(
            ["-v", "--verbose"],
            count=True,
            expose_value=False,
            callback=_verbose,
            help="More log output (repeat for debug).",
        ),
        click.Option(
            ["-q", "--quiet"],
            is_flag=True,
            expose_value=False,
            callback=_quiet,
            help="Do not say where the answer goes (the line before a robot verb starts).",
        ),
    ]


class _Group(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(super().list_commands(ctx)) | set(LAZY_COMMANDS))

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name in LAZY_COMMANDS and name not in self.commands:
            import importlib

            module, attr = LAZY_COMMANDS[name].split(":")
            cmd = getattr(importlib.import_module(module), attr)
            self.add_command(cmd, name)
        cmd = super().get_command(ctx, name)
        if cmd is not None and not any(p.name == "verbose" for p in cmd.params):
            cmd.params.extend(_everywhere_options())
        return cmd

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The list of verbs with each one's whole first sentence (click cuts them to the
        terminal's width), and an alias on its command's line."""
        rows = []
        for name in self.list_commands(ctx):
            if name in ALIASES:
                continue
            text = self._short_help(ctx, name, limit=1000)
            if text is None:
                continue
            aliases = [a for a, target in ALIASES.items() if target == name]
            if aliases:
                text = f"{text.rstrip('.')} (fetch_tools' name: {', '.join(aliases)})."
            rows.append((name, text))
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)

    def _short_help(self, ctx: click.Context, name: str, *, limit: int) -> str | None:
        """A verb's first sentence (cut to ``limit``), without importing a lazy verb's
        module; None for a hidden or unknown verb."""
        if name in LAZY_HELP and name not in self.commands:
            from click.utils import make_default_short_help

            return make_default_short_help(LAZY_HELP[name], limit)
        cmd = self.get_command(ctx, name)
        return None if cmd is None or cmd.hidden else cmd.get_short_help_str(limit=limit)

    def shell_complete(self, ctx: click.Context, incomplete: str) -> list[Any]:
        """The verbs (with their help, for shells that show it) and the group's options,
        as click's, without importing every verb's module at each tab."""
        from click.shell_completion import CompletionItem

        verbs = []
        for name in self.list_commands(ctx):
            if name.startswith(incomplete):
                text = self._short_help(ctx, name, limit=45)
                if text is not None:
                    verbs.append(CompletionItem(name, help=text))
        return verbs + click.Command.shell_complete(self, ctx, incomplete)

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        ctx.meta[_ARGV] = list(args)
        return super().parse_args(ctx, args)

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except click.NoSuchOption as exc:
            hint = quote_build_hint(ctx.meta.get(_ARGV, []), exc.option_name)
            if hint:
                exc.message = f"{exc.message.rstrip('.')}; {hint}"
            raise
        except FetchsyncError as exc:  # a robot's malformed answer (ProtocolError) too
            from fetchsync.console import printable

            click.echo(f"fetchsync: error: {printable(exc)}", err=True)
            sys.exit(exc.exit_code)
        except KeyboardInterrupt:
            click.echo("fetchsync: interrupted", err=True)
            sys.exit(130)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="fetchsync")
@click.option(
    "-v",
    "--verbose",
    count=True,
    expose_value=False,
    callback=_verbose,
    help="More log output (repeat for debug); also after the verb.",
)
@click.option(
    "-q",
    "--quiet",
    is_flag=True,
    expose_value=False,
    callback=_quiet,
    help="Do not say where the answer goes; also after the verb.",
)
def cli() -> None:
    """Mirror a ROS workspace's src/ to a robot over SSH, safely."""


@cli.command(cls=BuildCommand)
@target_options
@sync_options
@click.option(
    "--strict",
    is_flag=True,
    help="Refuse to replace files changed on the robot since the last sync.",
)
@click.option(
    "--force",
    is_flag=True,
    help="Push even a missing or empty src/, or one that deletes most of the robot's files.",
)
@build_options
@fleet_options
def push(
    robot: str | None,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    excludes: tuple[str, ...],
    as_json: bool,
    dry_run: bool,
    strict: bool,
    force: bool,
    builds: tuple[str, ...],
    build_type: str,
    build_tool: str,
    install_deps: bool,
    jobs: int,
    fail_fast: bool,
    retry_failed: bool,
) -> None:
    """Make the robot's <remote workspace>/src identical to the local src/.

    Files changed on the robot since the last sync are kept under
    <remote workspace>/.fetchsync/conflicts/ before being replaced (--strict
    refuses instead); deleted files go to a bounded .fetchsync/trash/.
    A push that would delete most of the robot's files needs --force (which
    also resumes a watch agent paused for that reason).
    With --build or --install-deps, then builds on the robot.
    Several robots (--robot a,b or @group) are pushed in parallel; a table ends it.
    """
    mark("push: start")
    from fetchsync.link.session import connect
    from fetchsync.protocol.ignore import build_rules

    _collect_less()
    mark("push: session imported")
    robots = robots_for("push", robot, retry_failed=retry_failed)
    if robots is not None:
        sys.exit(
            _fleet_push(
                robots,
                user=user,
                workspace=workspace,
                remote_workspace=remote_workspace,
                accept_host_key=accept_host_key,
                excludes=excludes,
                as_json=as_json,
                dry_run=dry_run,
                strict=strict,
                force=force,
                jobs=jobs,
                fail_fast=fail_fast,
                request=build_request(builds, build_type, build_tool, install_deps),
            )
        )
    target = _resolve(robot, user, workspace, remote_workspace)
    src = pushable(target.workspace / "src", force=force, whose="the robot's")
    say_where("push", target, local=src, remote=target.remote_workspace + "/src")
    rules = build_rules(excludes)
    # a running watch agent for this robot and workspace already holds the
    # connection and the state: a plain push goes through it
    mark("push: target resolved")
    request = build_request(builds, build_type, build_tool, install_deps)
    plain = not (dry_run or strict or excludes or force or request)
    report = None if (dry_run or strict or excludes or force) else _push_via_agent(target)
    mark("push: asked for an agent")
    start_resident = False
    if report is None:
        progress = _Progress(not as_json)
        done = False  # the push went through: the state holds its last commit
        opened: list[Any] = []  # the state, opened while the robot's endpoint starts
        scanned: list[Any] = []  # the local scan, if made then

        def prepare(started: Callable[[], bool]) -> None:
            """The local work done while the endpoint's command is on its way: open the
            state, import the engine; scan the tree too if the endpoint is not up yet (a
            direct connection's takes tenths of a second to start). A connection master's
            warm endpoint has answered by then: the push then scans while the robot lists
            its tree (Syncer.push), under that request's round trip and the robot's work
            instead of before it."""
            opened.append(_open_state(target))
            mark("push: state open")
            from fetchsync.sync.engine import scan_tree

            if not started():
                scanned.append(scan_tree(str(src), rules))

        try:
            with connect(target, accept_fingerprint=accept_host_key, meanwhile=prepare) as conn:
                from fetchsync.sync.engine import Syncer

                mark("push: connected")
                if not opened:  # the endpoint's start was retried without the local work
                    opened.append(_open_state(target))
                state = opened[0]
                syncer = Syncer(
                    conn,
                    state,
                    local_root=str(src),
                    remote_workspace=target.remote_workspace,
                    rules=rules,
                    policy="refuse" if strict else "preserve",
                )
                report = syncer.push(
                    dry_run=dry_run,
                    progress=progress,
                    scanned=scanned[0] if scanned else None,
                    confirm_deletions=force,
                )
                report.connection = _connection_kind(conn)
                mark("push: done")
                # a direct connection leaves a master behind as it closes (not after a
                # password login): the resident connects through it, or exits
                start_resident = plain and report.connection in ("master", "ssh")
            done = True
        finally:
            progress.close()
            if not (done and _ONE_SHOT):
                for each in opened:
                    each.close()
                mark("push: state closed")
        if force and not dry_run:
            _resume_agent(target)
    report.robot, report.local, report.remote = (
        target.robot,
        str(src),
        target.remote_workspace + "/src",
    )
    mark("push: connection closed")
    _print_report(report, as_json)
    if start_resident:
        _start_resident(target)
    from fetchsync.sync.engine import raise_for

    raise_for(report, strict=strict)
    if request and not dry_run:
        from fetchsync.chores.build import build_on_robot

        build_on_robot(
            target, request, src=src, accept_fingerprint=accept_host_key, quiet_stdout=as_json
        )


@cli.command(cls=BuildCommand)
@target_options
@sync_options
@click.option("--yes", "-y", "yes", is_flag=True, help="Do not ask for confirmation.")
@click.option("--no-safety", "yes", is_flag=True, help="fetch_tools' name for --yes.")
@build_options
def pull(
    robot: str | None,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    excludes: tuple[str, ...],
    as_json: bool,
    dry_run: bool,
    yes: bool,
    builds: tuple[str, ...],
    build_type: str,
    build_tool: str,
    install_deps: bool,
) -> None:
    """Make the local src/ identical to the robot's.

    Asks first (unless --yes). Local files it replaces or deletes are kept in
    <workspace>/.fetchsync/trash/ and .fetchsync/conflicts/.
    With --build or --install-deps, then builds here.
    """
    _collect_less()
    from fetchsync.errors import UsageError
    from fetchsync.link.session import connect
    from fetchsync.sync.engine import build_rules, raise_for
    from fetchsync.sync.engine import pull as do_pull

    target = _resolve(robot, user, workspace, remote_workspace)

    def confirm(preview: Any) -> bool:
        if yes:
            return True
        if not sys.stdin.isatty():
            raise UsageError(
                "pull would change local files and there is no terminal to ask",
                hint="pass --yes (or --no-safety)",
            )
        return click.confirm(
            f"pull will write {preview.files + preview.links} and delete {preview.deleted} local "
            f"paths under {target.workspace / 'src'} (replaced files are kept in .fetchsync/). Continue?",
            default=False,
        )

    say_where(
        "pull",
        target,
        local=target.workspace / "src",
        remote=target.remote_workspace + "/src",
        direction="from",
    )
    rules = build_rules(excludes)
    progress = _Progress(not as_json)
    state = _open_state(target)
    try:
        with connect(target, accept_fingerprint=accept_host_key) as conn:
            report = do_pull(
                conn,
                state,
                local_workspace=str(target.workspace),
                remote_workspace=target.remote_workspace,
                rules=rules,
                confirm=confirm,
                dry_run=dry_run,
                progress=progress,
            )
            report.connection = _connection_kind(conn)
    finally:
        progress.close()
        state.close()
    report.robot, report.local, report.remote = (
        target.robot,
        str(target.workspace / "src"),
        target.remote_workspace + "/src",
    )
    _print_report(report, as_json)
    raise_for(report, strict=False)
    request = build_request(builds, build_type, build_tool, install_deps)
    if request and not dry_run:
        from fetchsync.chores.build import build_locally

        build_locally(target.workspace, request, quiet_stdout=as_json)


def _fleet_push(
    robots: Sequence[str],
    *,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    excludes: Sequence[str],
    as_json: bool,
    dry_run: bool,
    strict: bool,
    force: bool,
    request: Any,
    jobs: int,
    fail_fast: bool,
) -> int:
    """``push`` (and its build) to each robot; the exit status. The local tree is checked
    and scanned once; each robot then hashes against its own state, as a single push does."""
    from concurrent.futures import ThreadPoolExecutor
    from contextlib import ExitStack

    from fetchsync.chores.build import build_on_robot
    from fetchsync.cli.common import resolve, where_line
    from fetchsync.cli.fleet import Prefixed, RobotResult, finish, quiet, run_all
    from fetchsync.config import resolve_workspace
    from fetchsync.console import printable
    from fetchsync.link.connection import Connection, remote_python
    from fetchsync.link.session import open_transport
    from fetchsync.protocol.ignore import build_rules
    from fetchsync.sync.engine import SharedPacks, Syncer, raise_for, scan_tree
    from fetchsync.sync.state import open_state

    src = pushable(resolve_workspace(workspace) / "src", force=force, whose="the robots'")
    rules = build_rules(tuple(excludes))
    scanned = scan_tree(str(src), rules)  # once for all robots: it is only read
    packs = SharedPacks()  # each batch compressed once for the robots that send it
    silent = quiet()
    connector = ThreadPoolExecutor(
        max_workers=max(1, min(jobs, len(robots))), thread_name_prefix="fetchsync-link"
    )

    def link(target: Any) -> tuple[Any, Any]:
        transport = open_transport(target, accept_fingerprint=accept_host_key)
        try:
            return transport, Connection.open(transport, python=remote_python())
        except BaseException:
            transport.close()
            raise

    def work(name: str, out: Prefixed) -> RobotResult:
        target = resolve(name, user, workspace, remote_workspace)
        if not silent:
            out.line(where_line("push", target, local=src, remote=target.remote_workspace + "/src"))
        report = None if (dry_run or strict or excludes or force) else _push_via_agent(target)
        if report is None:
            # the robot's connection opens while its state does (a database on the
            # laptop's disk, new ones synced to it: 20 at once took 0.1-0.3 s on the bench)
            linked = connector.submit(link, target)
            try:
                state = open_state(target)
            except BaseException:
                linked.add_done_callback(_unlink)
                raise
            if state.note:
                out.line(f"fetchsync: note: {state.note}")
            try:
                with ExitStack() as stack:
                    transport, conn = linked.result()
                    stack.callback(transport.close)
                    stack.callback(conn.close)
                    syncer = Syncer(
                        conn,
                        state,
                        local_root=str(src),
                        remote_workspace=target.remote_workspace,
                        rules=rules,
                        policy="refuse" if strict else "preserve",
                    )
                    syncer.packs = packs
                    report = syncer.push(dry_run=dry_run, scanned=scanned, confirm_deletions=force)
                    report.connection = _connection_kind(conn)
            finally:
                state.close()
            if force and not dry_run:
                _resume_agent(target)
        report.robot, report.local, report.remote = name, str(src), target.remote_workspace + "/src"
        result = RobotResult(
            name,
            result="ok",
            files=report.files,
            bytes_sent=report.bytes_sent,
            conflicts=len(report.conflicts),
            report=report.to_json(),
        )
        for c in report.conflicts:
            how = "left as it is" if c.get("refused") else f"kept in {printable(c['kept'])}"
            out.line(f"conflict: {printable(c['path'])} changed on the robot; {how}")
        for e in report.errors:
            out.line(f"error: {printable(e['path'])}: {printable(e['error'])}")
        try:
            raise_for(report, strict=strict)
        except FetchsyncError as exc:
            result.result, result.exit_code, result.error = "failed", exc.exit_code, str(exc)
            out.line(f"fetchsync: error: {printable(exc)}")
            return result
        if request and not dry_run:
            try:
                build_on_robot(
                    target,
                    request,
                    src=src,
                    accept_fingerprint=accept_host_key,
                    stdout=out.err if as_json else out.out,
                    stderr=out.err,
                )
            except FetchsyncError as exc:
                result.build, result.result = "failed", "failed"
                result.exit_code, result.error = exc.exit_code, str(exc)
                out.line(f"fetchsync: error: {printable(exc)}")
                return result
            result.build = "ok"
        return result

    try:
        results = run_all(robots, work, jobs=jobs, fail_fast=fail_fast)
    finally:
        connector.shutdown(wait=False, cancel_futures=True)
    return finish("push", results, as_json=as_json)


def _unlink(linked: Any) -> None:
    """Close a robot's connection that opened for a push that failed before using it."""
    if not linked.cancelled() and linked.exception() is None:
        transport, conn = linked.result()
        conn.close()
        transport.close()


def _collect_less() -> None:
    """Let a one-shot push or pull run (nearly) without the cyclic garbage collector.

    It builds a few objects per file and no cycles worth the name, yet the default
    thresholds ran ~200 collections in a 7,000-file push: 0.1-0.2 s of CPU
    (bench/README.md). Not for the watch agent, which lives on.
    """
    import gc

    gc.freeze()  # what the imports made stays, unexamined
    gc.set_threshold(100_000, 50, 100)


# Whether this process ends with _exit once the command returns (main), rather than a
# caller that goes on (click's test runner). A push that went through then leaves its
# state's database open: every write of it is committed (SQLite's WAL with
# synchronous=FULL: on disk when the commit returns), and closing the last connection
# only checkpoints the log into the database file and syncs it: 17-30 ms at the end of
# rclcpp's first push on wifi here (bench/firststart.py, "push: state closed" after
# "push: progress closed", load 3-5) that the exit waited for. Left open, the exit is to
# SQLite what a crash is, which it is made for: the next connection reads the log, and a
# later commit checkpoints it once it passes 1,000 pages (SQLite's default).
_ONE_SHOT = False


def main() -> None:
    global _ONE_SHOT
    mark("cli: imported")
    _ONE_SHOT = True
    from fetchsync.agent.quick import fast_main

    # a console script made before the entry moved to fetchsync.__main__ comes here
    fast = fast_main(sys.argv[1:])
    if fast is not None:
        _exit(fast)
    try:
        cli(prog_name="fetchsync")
        code: Any = 0
    except SystemExit as exc:
        code = exc.code
    if isinstance(code, str):
        print(code, file=sys.stderr)
        code = 1
    _exit(0 if code is None else int(code))


def _exit(code: int) -> None:
    """End the process without the interpreter's teardown.

    A no-op push builds tens of thousands of small objects, and freeing them
    one by one at exit took 20-80 ms, a fifth of the whole call. Exit
    handlers still run and output is flushed; then the kernel frees it all.
    """
    import atexit

    atexit._run_exitfuncs()
    mark("exit: exit handlers ran")
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            code = code or 1  # a closed or broken stdout is a failure to report
    mark("exit: output flushed")
    os._exit(code)


if __name__ == "__main__":
    main()
