"""Several robots at once: running one verb on each of them in parallel.

A lab pushes the same code to a demo's three Fetches or a class's twenty; a shell
loop takes the sum of their times and buries one robot's failure in the scroll.
Here each robot is one thread calling the library code the single-robot verb
calls, up to ``jobs`` at once; one robot's failure (a dead link, a refused login,
a failed build) is that robot's row of the table at the end and leaves the others
running. Each robot resolves its own user and workspaces as a single robot does.

Naming robots (``--robot a,b``, ``@group``s of robots.toml) is :mod:`fetchsync.robots`.

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
from fetchsync.robots import expand, robot_settings

DEFAULT_JOBS = 8
"""Robots worked on at once: a lab's demo fits, a class of twenty takes three waves
of links that are each a Wi-Fi hop (the laptop's CPU is rarely what they wait on)."""

MAX_JOBS = 64


# --------------------------------------------------------------------------- naming
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


# --------------------------------------------------------------------------- results
@dataclass
class RobotResult:
    """One robot's row of the table, and its entry in ``--json``'s list."""

    robot: str
    result: str = "not started"  # "ok", "failed", "not started"
    exit_code: int = 0
    files: int | None = None
    bytes_sent: int | None = None
    conflicts: int | None = None
    build: str = "-"  # "-", "ok", "failed"
    seconds: float = 0.0
    error: str = ""
    report: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.result == "ok"

    def to_json(self) -> dict[str, Any]:
        out = dict(self.report)
        out.update(
            robot=self.robot,
            ok=self.ok,
            result=self.result,
            exit_code=self.exit_code,
            build=self.build,
            fleet_seconds=round(self.seconds, 3),
            error=self.error,
        )
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
    rows = [head] + [
        (
            printable(r.robot),
            r.result,
            "-" if r.files is None else str(r.files),
            _human(r.bytes_sent),
            "-" if r.conflicts is None else str(r.conflicts),
            r.build,
            f"{r.seconds:.1f}s",
            printable(r.error) or "-",
        )
        for r in results
    ]
    widths = [max(len(row[i]) for row in rows) for i in range(len(head) - 1)]
    return "\n".join(
        "  ".join(c.ljust(w) for c, w in zip(row, widths)) + "  " + row[-1] for row in rows
    )


def exit_status(results: Sequence[RobotResult]) -> int:
    """0 when every robot succeeded; else the failures' common exit status, or 1 when they
    differ (robots not started after ``--fail-fast`` add none of their own)."""
    codes = {r.exit_code or 1 for r in results if r.result == "failed"} or {
        1 for r in results if not r.ok
    }
    if not codes:
        return 0
    return codes.pop() if len(codes) == 1 else 1


def last_path() -> Path:
    from fetchsync.sync.state import state_dir

    return state_dir() / "fleet-last.json"


def save_last(verb: str, results: Sequence[RobotResult]) -> None:
    """Keep which robots failed, for ``--retry-failed`` (best effort: a note when it cannot)."""
    path = last_path()
    data = {
        "verb": verb,
        "robots": [r.robot for r in results],
        "failed": [r.robot for r in results if not r.ok],
    }
    try:
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        tmp = path.with_name(f".{path.name}.{os.getpid()}")
        tmp.write_text(json.dumps(data))
        os.replace(tmp, path)
    except OSError as exc:
        _write(
            2,
            f"fetchsync: note: cannot keep this fleet's result in {path}: {exc.strerror or exc}\n",
        )


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
        thread = threading.Thread(
            target=self._pump, args=(r, target), daemon=True, name=f"fetchsync-prefix{self.prefix}"
        )
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
                    _write(
                        target,
                        "".join(
                            f"{self.prefix}{line.decode('utf-8', 'replace')}\n" for line in lines
                        ),
                    )
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
def run_all(
    robots: Sequence[str],
    work: Callable[[str, Prefixed], RobotResult],
    *,
    jobs: int,
    fail_fast: bool,
    stdout: int = 1,
) -> list[RobotResult]:
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
            result = RobotResult(
                name,
                result="failed",
                exit_code=1,
                error=f"internal error: {type(exc).__name__}: {exc}",
            )
            out.line(f"fetchsync: error: {result.error}")
        finally:
            out.close()
        result.seconds = time.monotonic() - t0
        results[name] = result
        if not result.ok:
            stop.set()

    pool = ThreadPoolExecutor(
        max_workers=max(1, min(jobs, len(robots))), thread_name_prefix="fetchsync-fleet"
    )
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
    _write(
        2,
        f"{verb}: {ok} of {len(results)} robots succeeded"
        + (f"; failed: {', '.join(failed)}" if failed else "")
        + (f"; not started: {', '.join(left)}" if left else "")
        + ("; --retry-failed runs again on those\n" if failed or left else "\n"),
    )
    if as_json:
        _write(1, json.dumps([r.to_json() for r in results], sort_keys=True) + "\n")
    save_last(verb, results)
    return exit_status(results)


# --------------------------------------------------------------------------- verbs
def fleet_options(
    func: Callable[..., Any] | None = None, *, jobs: bool = True
) -> Callable[..., Any]:
    """``-j/--jobs``, ``--fail-fast``, ``--retry-failed``: how a verb runs on several robots.
    ``jobs=False`` leaves out ``-j`` (a verb whose ``-j`` is its own, as snapshot's)."""
    import click

    if func is None:
        return lambda f: fleet_options(f, jobs=jobs)
    opts = [
        click.option(
            "--jobs",
            "-j",
            type=click.IntRange(1, MAX_JOBS),
            default=DEFAULT_JOBS,
            show_default=True,
            help="With several robots: how many at once.",
        ),
        click.option(
            "--fail-fast",
            is_flag=True,
            help="With several robots: start no more robots once one failed.",
        ),
        click.option(
            "--retry-failed",
            is_flag=True,
            help="Run again on the robots that failed in the last call on several robots.",
        ),
    ]
    for opt in reversed(opts if jobs else opts[1:]):
        func = opt(func)
    return func


def robots_for(verb: str, robot: str | None, *, retry_failed: bool) -> list[str] | None:
    """The robots a fleet ``verb`` runs on, or None for the single-robot verb."""
    if retry_failed:
        if robot:
            raise UsageError(
                "--retry-failed takes the robots that failed last time: give no --robot"
            )
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


def quiet() -> bool:
    import click

    ctx = click.get_current_context(silent=True)
    return bool(ctx is not None and ctx.find_root().meta.get("fetchsync.quiet"))
