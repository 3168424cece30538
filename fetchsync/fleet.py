"""Several robots at once: naming them, and running one verb on each of them in parallel.

A lab pushes the same code to a demo's three Fetches or a class's twenty; a shell
loop takes the sum of their times and buries one robot's failure in the scroll.
Here each robot is one thread calling the library code the single-robot verb
calls, up to ``jobs`` at once; one robot's failure (a dead link, a refused login,
a failed build) is that robot's row of the table at the end and leaves the others
running. Each robot resolves its own user and workspaces as a single robot does.

Naming: ``--robot a --robot b``, ``--robot a,b``, ``--robot @lab`` with ``lab =
["fetch1", "fetch2"]`` in ``~/.config/fetchsync/robots.toml`` (or under
``$XDG_CONFIG_HOME``), and the same in ``FETCHSYNC_ROBOT``/``FETCH_ROBOT``. The
file may also give a robot its own remote workspace, which then counts as that
robot's ``--remote-workspace``::

    lab = ["fetch1", "fetch2"]

    [robots.fetch2]
    remote_workspace = "~/melodic_ws"

Questions (an unknown host key, a password) cannot be asked of several robots at
once on one terminal: at a terminal the connections are opened one at a time
(the rest of each robot's work runs in parallel); without one, a robot that would
ask fails with its own line, as a single robot does.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fetchsync.errors import ConfigError, FetchsyncError, UsageError

DEFAULT_JOBS = 8
"""Robots worked on at once: a lab's demo fits, a class of twenty takes three waves
of links that are each a Wi-Fi hop (the laptop's CPU is rarely what they wait on)."""

MAX_JOBS = 64
SETTINGS_TABLE = "robots"
"""The table of robots.toml holding per-robot settings (so no group is called that)."""

ROBOT_KEYS = frozenset({"remote_workspace"})


# --------------------------------------------------------------------------- naming
def groups_file(environ: Mapping[str, str] = os.environ) -> Path:
    """``$XDG_CONFIG_HOME/fetchsync/robots.toml``, else ``~/.config/fetchsync/robots.toml``."""
    base = environ.get("XDG_CONFIG_HOME", "").strip()
    if not base:
        home = environ.get("HOME", "").strip() or os.path.expanduser("~")
        base = os.path.join(home, ".config")
    return Path(base) / "fetchsync" / "robots.toml"


def _load(environ: Mapping[str, str]) -> dict[str, Any]:
    """robots.toml as a dict ({} when there is none); a one-line error when it is unreadable."""
    path = groups_file(environ)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return {}
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc.strerror or exc}") from exc
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        try:
            import tomli as tomllib  # type: ignore[no-redef]
        except ModuleNotFoundError:
            raise ConfigError(f"reading {path} needs Python 3.11 or the tomli package",
                              hint="pip install tomli") from None
    try:
        return tomllib.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from exc


def groups(*, environ: Mapping[str, str] = os.environ) -> dict[str, list[str]]:
    """The named groups of robots.toml: ``name = ["robot", ...]``."""
    path = groups_file(environ)
    out: dict[str, list[str]] = {}
    for name, value in _load(environ).items():
        if name == SETTINGS_TABLE:
            continue
        if not isinstance(value, list) or not all(isinstance(v, str) and v.strip() for v in value):
            raise ConfigError(f"{path}: group {name!r} must be a list of robot names")
        out[name] = [v.strip() for v in value]
    return out


def robot_settings(robot: str, *, environ: Mapping[str, str] = os.environ) -> dict[str, str]:
    """What robots.toml's ``[robots.NAME]`` says of ``robot`` ({} when nothing)."""
    data = _load(environ)
    table = data.get(SETTINGS_TABLE, {})
    path = groups_file(environ)
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [{SETTINGS_TABLE}] must be a table of robots")
    mine = table.get(robot, {})
    if not isinstance(mine, dict):
        raise ConfigError(f"{path}: [{SETTINGS_TABLE}.{robot}] must be a table")
    unknown = set(mine) - ROBOT_KEYS
    if unknown or not all(isinstance(v, str) and v.strip() for v in mine.values()):
        raise ConfigError(f"{path}: [{SETTINGS_TABLE}.{robot}] takes {', '.join(sorted(ROBOT_KEYS))} "
                          "(a string)" + (f", not {', '.join(sorted(unknown))}" if unknown else ""))
    return {k: v.strip() for k, v in mine.items()}


def expand(value: str, *, source: str = "--robot",
           environ: Mapping[str, str] = os.environ) -> list[str]:
    """The robots ``value`` names: comma-separated names and ``@group``s, in order, each once."""
    names: list[str] = []
    known: dict[str, list[str]] | None = None
    for word in (w.strip() for w in value.split(",")):
        if not word:
            continue
        if word.startswith("@"):
            if known is None:
                known = groups(environ=environ)
            members = known.get(word[1:])
            if members is None:
                listed = ", ".join("@" + g for g in sorted(known)) or "none"
                raise ConfigError(f"unknown group {word} (from {source}); known groups in "
                                  f"{groups_file(environ)}: {listed}")
            names.extend(members)
        else:
            names.append(word)
    unique = list(dict.fromkeys(names))
    if not unique:
        raise ConfigError(f"no robot named (from {source})")
    return unique


def names_given(robot: str | None, *, environ: Mapping[str, str] = os.environ) -> list[str] | None:
    """The robots of the option or the robot variables when they name a fleet (a list or a
    group); None when they name one robot the single-robot way (or none)."""
    from fetchsync.config import ROBOT_VARS

    source, value = "--robot", robot.strip() if robot else None
    if not value:
        for name in ROBOT_VARS:
            value = environ.get(name, "").strip() or None
            if value:
                source = name
                break
    if not value or ("," not in value and not value.startswith("@")):
        return None
    return expand(value, source=source, environ=environ)


def one_robot(value: str, source: str, *, environ: Mapping[str, str] = os.environ) -> str:
    """For verbs that take one robot: the one ``value`` names, or a one-line refusal (exit 2)."""
    names = expand(value, source=source, environ=environ)
    if len(names) > 1:
        raise UsageError(f"several robots ({', '.join(names)}, from {source}): only push and run "
                         "take several; give one robot")
    return names[0]


# --------------------------------------------------------------------------- results
@dataclass
class RobotResult:
    """One robot's row of the table, and its entry in ``--json``'s list."""

    robot: str
    result: str = "not started"      # "ok", "failed", "not started"
    exit_code: int = 0
    files: int | None = None
    bytes_sent: int | None = None
    conflicts: int | None = None
    build: str = "-"                 # "-", "ok", "failed"
    seconds: float = 0.0
    error: str = ""
    report: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.result == "ok"

    def to_json(self) -> dict[str, Any]:
        out = dict(self.report)
        out.update(robot=self.robot, ok=self.ok, result=self.result, exit_code=self.exit_code,
                   build=self.build, fleet_seconds=round(self.seconds, 3), error=self.error)
        return out


def _human(n: int | None) -> str:
    if n is None:
        return "-"
    size = float(n)
    for unit in ("B", "KiB", "MiB"):
        if size < 1024:
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1024
    return f"{size:.1f} GiB"


def table(results: Sequence[RobotResult]) -> str:
    """The table printed at the end: robot, result, files, bytes, conflicts, build, time, error."""
    from fetchsync.console import printable

    head = ("robot", "result", "files", "bytes", "conflicts", "build", "time", "error")
    rows = [head] + [(printable(r.robot), r.result, "-" if r.files is None else str(r.files),
                      _human(r.bytes_sent), "-" if r.conflicts is None else str(r.conflicts),
                      r.build, f"{r.seconds:.1f}s", printable(r.error) or "-") for r in results]
    widths = [max(len(row[i]) for row in rows) for i in range(len(head) - 1)]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(row, widths)) + "  " + row[-1]
                     for row in rows)


def exit_status(results: Sequence[RobotResult]) -> int:
    """0 when every robot succeeded; else the failures' common exit status, or 1 when they
    differ (robots not started after ``--fail-fast`` add none of their own)."""
    codes = {r.exit_code or 1 for r in results if r.result == "failed"} or \
        {1 for r in results if not r.ok}
    if not codes:
        return 0
    return codes.pop() if len(codes) == 1 else 1


def last_path() -> Path:
    from fetchsync.state import state_dir
    return state_dir() / "fleet-last.json"


def save_last(verb: str, results: Sequence[RobotResult]) -> None:
    """Keep which robots failed, for ``--retry-failed`` (best effort: a note when it cannot)."""
    path = last_path()
    data = {"verb": verb, "robots": [r.robot for r in results],
            "failed": [r.robot for r in results if not r.ok]}
    try:
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        tmp = path.with_name(f".{path.name}.{os.getpid()}")
        tmp.write_text(json.dumps(data))
        os.replace(tmp, path)
    except OSError as exc:
        _write(2, f"fetchsync: note: cannot keep this fleet's result in {path}: {exc.strerror or exc}\n")


def failed_last(verb: str) -> list[str]:
    """The robots that failed in the last fleet ``verb``; a one-line error when there are none."""
    path = last_path()
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        raise UsageError(f"no earlier fleet result to retry (none kept in {path})") from None
    if not isinstance(data, dict) or data.get("verb") != verb:
        raise UsageError(f"the last fleet call was not a {verb}: nothing to retry")
    failed = [r for r in data.get("failed", []) if isinstance(r, str)]
    if not failed:
        raise UsageError(f"every robot of the last fleet {verb} succeeded: nothing to retry")
    return failed


# --------------------------------------------------------------------------- output
_OUT_LOCK = threading.Lock()


def _write(fd: int, text: str) -> None:
    data = text.encode("utf-8", "replace")
    with _OUT_LOCK:
        view = memoryview(data)
        while view:
            try:
                n = os.write(fd, view)
            except BrokenPipeError:
                return
            view = view[n:]


class Prefixed:
    """A robot's output streams: pipes whose lines reach ours prefixed ``[robot] ``, whole
    lines at a time so robots' lines never interleave mid-line."""

    def __init__(self, robot: str, *, stdout: int = 1, stderr: int = 2) -> None:
        from fetchsync.console import printable

        self.prefix = f"[{printable(robot)}] "
        self.stdout_target, self.stderr_target = stdout, stderr
        self._pumps: list[threading.Thread] = []
        self.out = self._pipe(stdout)
        self.err = self._pipe(stderr)

    def _pipe(self, target: int) -> int:
        r, w = os.pipe()
        thread = threading.Thread(target=self._pump, args=(r, target), daemon=True,
                                  name=f"fetchsync-prefix{self.prefix}")
        thread.start()
        self._pumps.append(thread)
        return w

    def _pump(self, r: int, target: int) -> None:
        pending = b""
        try:
            while True:
                chunk = os.read(r, 65536)
                if not chunk:
                    break
                pending += chunk
                *lines, pending = pending.split(b"\n")
                if lines:
                    _write(target, "".join(f"{self.prefix}{line.decode('utf-8', 'replace')}\n"
                                           for line in lines))
            if pending:
                _write(target, f"{self.prefix}{pending.decode('utf-8', 'replace')}\n")
        finally:
            os.close(r)

    def line(self, text: str, *, err: bool = True) -> None:
        """One line of ours about this robot."""
        _write(self.stderr_target if err else self.stdout_target, f"{self.prefix}{text}\n")

    def close(self) -> None:
        for fd in (self.out, self.err):
            os.close(fd)
        for thread in self._pumps:
            thread.join()


# --------------------------------------------------------------------------- running
def question_lock() -> Any:
    """What serialises opening connections, which may ask on the terminal (a host key, a
    password): a lock at a terminal, so one robot's question is asked at a time and
    answered before the next; nothing without one, where nothing can ask."""
    from contextlib import nullcontext

    from fetchsync.session import terminal_prompt

    return threading.Lock() if terminal_prompt() is not None else nullcontext()


def run_all(robots: Sequence[str], work: Callable[[str, Prefixed], RobotResult], *,
            jobs: int, fail_fast: bool, stdout: int = 1) -> list[RobotResult]:
    """``work(robot, output)`` for each robot, ``jobs`` at a time; with ``fail_fast`` no
    robot starts after one failed (those are "not started"). One robot's exception is
    its row, never the others' end."""
    from concurrent.futures import ThreadPoolExecutor

    results = {name: RobotResult(name) for name in robots}
    stop = threading.Event()

    def one(name: str) -> None:
        if fail_fast and stop.is_set():
            return
        out = Prefixed(name, stdout=stdout)
        t0 = time.monotonic()
        try:
            result = work(name, out)
        except FetchsyncError as exc:
            from fetchsync.console import printable

            result = RobotResult(name, result="failed", exit_code=exc.exit_code, error=str(exc))
            out.line(f"fetchsync: error: {printable(exc)}")
        except Exception as exc:  # noqa: BLE001 - a bug on one robot is its row, not a traceback
            result = RobotResult(name, result="failed", exit_code=1,
                                 error=f"internal error: {type(exc).__name__}: {exc}")
            out.line(f"fetchsync: error: {result.error}")
        finally:
            out.close()
        result.seconds = time.monotonic() - t0
        results[name] = result
        if not result.ok:
            stop.set()

    pool = ThreadPoolExecutor(max_workers=max(1, min(jobs, len(robots))),
                              thread_name_prefix="fetchsync-fleet")
    try:
        for future in [pool.submit(one, name) for name in robots]:
            future.result()
    finally:
        # Ctrl-C must not wait for the robots still working: the process ends, and
        # with it their links (a command run there is stopped as a single run's is)
        pool.shutdown(wait=False, cancel_futures=True)
    return [results[name] for name in robots]


def finish(verb: str, results: Sequence[RobotResult], *, as_json: bool = False) -> int:
    """Print the table (stderr) and, with ``as_json``, the list of reports (stdout); keep
    the failures for ``--retry-failed``; the exit status."""
    _write(2, table(results) + "\n")
    failed = [r.robot for r in results if r.result == "failed"]
    left = [r.robot for r in results if r.result == "not started"]
    ok = len(results) - len(failed) - len(left)
    _write(2, f"{verb}: {ok} of {len(results)} robots succeeded"
              + (f"; failed: {', '.join(failed)}" if failed else "")
              + (f"; not started: {', '.join(left)}" if left else "")
              + ("; --retry-failed runs again on those\n" if failed or left else "\n"))
    if as_json:
        _write(1, json.dumps([r.to_json() for r in results], sort_keys=True) + "\n")
    save_last(verb, results)
    return exit_status(results)


# --------------------------------------------------------------------------- verbs
def fleet_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """``-j/--jobs``, ``--fail-fast``, ``--retry-failed``: how a verb runs on several robots."""
    import click

    opts = [
        click.option("--jobs", "-j", type=click.IntRange(1, MAX_JOBS), default=DEFAULT_JOBS,
                     show_default=True, help="With several robots: how many at once."),
        click.option("--fail-fast", is_flag=True,
                     help="With several robots: start no more robots once one failed."),
        click.option("--retry-failed", is_flag=True,
                     help="Run again on the robots that failed in the last call on several robots."),
    ]
    for opt in reversed(opts):
        func = opt(func)
    return func


def robots_for(verb: str, robot: str | None, *, retry_failed: bool) -> list[str] | None:
    """The robots a fleet ``verb`` runs on, or None for the single-robot verb."""
    if retry_failed:
        if robot:
            raise UsageError("--retry-failed takes the robots that failed last time: give no --robot")
        return failed_last(verb)
    return names_given(robot)


def remote_option(robot: str | None, remote_workspace: str | None) -> str | None:
    """The robot's ``--remote-workspace``: the option, else robots.toml's for the robot
    ``robot`` (or the robot variables) names; None when neither gives one."""
    if remote_workspace is not None:
        return remote_workspace
    from fetchsync.config import resolve_robot

    try:
        name = resolve_robot(robot)
    except ConfigError:
        return None  # no robot (yet): the verb's resolution says so in its own words
    return robot_settings(name).get("remote_workspace")


def _quiet() -> bool:
    import click

    ctx = click.get_current_context(silent=True)
    return bool(ctx is not None and ctx.find_root().meta.get("fetchsync.quiet"))


def push(robots: Sequence[str], *, user: str | None, workspace: str | None,
         remote_workspace: str | None, accept_host_key: str | None, excludes: Sequence[str],
         as_json: bool, dry_run: bool, strict: bool, force: bool, request: Any, jobs: int,
         fail_fast: bool) -> int:
    """``push`` (and its build) to each robot; the exit status. The local tree is checked
    and scanned once; each robot then hashes against its own state, as a single push does."""
    from contextlib import ExitStack

    from fetchsync import cli
    from fetchsync.build import build_on_robot
    from fetchsync.commands.common import resolve, where_line
    from fetchsync.config import resolve_workspace
    from fetchsync.connection import Connection, remote_python
    from fetchsync.console import printable
    from fetchsync.errors import SyncError
    from fetchsync.protocol.ignore import build_rules
    from fetchsync.session import open_state, open_transport
    from fetchsync.sync import Syncer, raise_for, scan_tree

    src = resolve_workspace(workspace) / "src"
    if not force:
        if not src.is_dir():
            raise ConfigError(f"{src} does not exist; nothing to push",
                              hint="check --workspace; fetchsync config shows where it came from")
        if not cli._holds_files(src):
            raise SyncError(f"{src} holds no files (only directories or ignore markers, if "
                            "anything); pushing it would empty the robots' src/",
                            hint="pass --force if that is what you want")
    else:
        src.mkdir(parents=True, exist_ok=True)
    rules = build_rules(tuple(excludes))
    scanned = scan_tree(str(src), rules)  # once for all robots: it is only read
    asking = question_lock()
    quiet = _quiet()

    def work(name: str, out: Prefixed) -> RobotResult:
        target = resolve(name, user, workspace, remote_workspace)
        if not quiet:
            out.line(where_line("push", target, local=src, remote=target.remote_workspace + "/src"))
        report = None if (dry_run or strict or excludes or force) else cli._push_via_agent(target)
        if report is None:
            state = open_state(target)
            if state.note:
                out.line(f"fetchsync: note: {state.note}")
            try:
                with ExitStack() as stack:
                    # as session.connect, but only the opening (which may ask) is one at a time
                    with asking:
                        transport = open_transport(target, accept_fingerprint=accept_host_key)
                    stack.callback(transport.close)
                    conn = Connection.open(transport, python=remote_python())
                    stack.callback(conn.close)
                    syncer = Syncer(conn, state, local_root=str(src),
                                    remote_workspace=target.remote_workspace, rules=rules,
                                    policy="refuse" if strict else "preserve")
                    report = syncer.push(dry_run=dry_run, scanned=scanned, confirm_deletions=force)
                    report.connection = cli._connection_kind(conn)
            finally:
                state.close()
            if force and not dry_run:
                cli._resume_agent(target)
        report.robot, report.local, report.remote = name, str(src), target.remote_workspace + "/src"
        result = RobotResult(name, result="ok", files=report.files, bytes_sent=report.bytes_sent,
                             conflicts=len(report.conflicts), report=report.to_json())
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
                build_on_robot(target, request, src=src, accept_fingerprint=accept_host_key,
                               stdout=out.err if as_json else out.out, stderr=out.err)
            except FetchsyncError as exc:
                result.build, result.result = "failed", "failed"
                result.exit_code, result.error = exc.exit_code, str(exc)
                out.line(f"fetchsync: error: {printable(exc)}")
                return result
            result.build = "ok"
        return result

    results = run_all(robots, work, jobs=jobs, fail_fast=fail_fast)
    return finish("push", results, as_json=as_json)


def run(robots: Sequence[str], *, user: str | None, workspace: str | None,
        remote_workspace: str | None, accept_host_key: str | None, line: str, jobs: int,
        fail_fast: bool) -> int:
    """``run`` of one command line on each robot, with an empty stdin (several robots cannot
    share ours) and no terminal; its output prefixed per robot; the exit status."""
    from fetchsync.commands.run import LINK_EXIT, _target
    from fetchsync.connection import remote_python
    from fetchsync.console import NO_STATUS, attach
    from fetchsync.errors import TransportError
    from fetchsync.remote import ros_environment, script, wrap
    from fetchsync.session import open_transport

    asking = question_lock()

    def work(name: str, out: Prefixed) -> RobotResult:
        target, remote_ws = _target(name, user, workspace, remote_option(name, remote_workspace))
        body = script(line, environment=ros_environment(remote_ws))
        try:
            with asking:
                transport = open_transport(target, accept_fingerprint=accept_host_key,
                                           persistent=False)
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
            return RobotResult(name, result="failed", exit_code=LINK_EXIT,
                               error="the command ended without an exit status")
        if status != 0:
            return RobotResult(name, result="failed", exit_code=status, error=f"exit status {status}")
        return RobotResult(name, result="ok")

    results = run_all(robots, work, jobs=jobs, fail_fast=fail_fast)
    return finish("run", results)
