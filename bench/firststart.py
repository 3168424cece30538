#!/usr/bin/env python3
"""The timeline of a first push (no connection master): where its start and its end go.

``python3 bench/firststart.py --link wifi --files 300 --size-mb 2 --rounds 5
[--rev REV] [--baseline-rev REV]``: a workspace pushed into an empty robot tree by
rsync and by each fetchsync (this checkout's or ``--rev``'s, and ``--baseline-rev``'s),
in alternating order, each fetchsync with no master (stopped before its push) and
``FETCHSYNC_TRACE`` on. Per push: the wall time, the CPU seconds of the push process
and its reaped children (``wait4``'s rusage) and
each trace mark's time from the exec. The medians of each mark per tool close the
report: load-independent where they are CPU, a timeline where they are marks.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))

import run  # noqa: E402
from run import Bench, FetchsyncPush, Params, RsyncPush  # noqa: E402
from workspace import generate  # noqa: E402

# (from, to, what): spans of one push, each from its own marks (first occurrence)
SPANS = [
    (
        "session: the master is not there",
        "ssh: key exchange done",
        "no master -> key exchange done",
    ),
    ("ssh: socket made", "ssh: key exchange done", "socket -> key exchange done"),
    ("ssh: key exchange done", "ssh: authenticated", "key exchange -> authenticated"),
    (
        "ssh: authenticated",
        "connection: the endpoint's command sent",
        "authenticated -> command sent",
    ),
    (
        "connection: the endpoint's command sent",
        "connection: the endpoint's hello in",
        "command -> hello",
    ),
    (
        "main: the interpreter is up",
        "push: the first batch sent",
        "interpreter -> first batch sent",
    ),
    ("connection: the endpoint's hello in", "push: connected", "hello -> connected"),
    ("connection: the local work meanwhile done", "push: connected", "meanwhile -> connected"),
    ("push: connected", "push: the robot's listing in", "connected -> listing in"),
    ("push: the robot's listing in", "push: the first batch sent", "listing -> first batch sent"),
    ("main: the interpreter is up", "session: the master is not there", "interpreter -> no master"),
    ("push: done", "exit: output flushed", "done -> exit"),
]


def push(
    tool: run.Tool, trace: Path, extra: dict[str, str], keep_stderr: Path | None
) -> tuple[float, float, list[tuple[float, str]]]:
    """One push of ``tool``: (wall s, CPU s of the push process and its reaped children,
    [(s from exec, mark)])."""
    argv, env = tool.command()
    if isinstance(tool, FetchsyncPush):
        env["FETCHSYNC_TRACE"] = str(trace)
        env.update(extra)
    os.sync()
    run.wait_quiet(tool.bench.marks())
    with contextlib.suppress(FileNotFoundError):
        trace.unlink()
    t0 = time.monotonic()
    proc = subprocess.Popen(
        argv,
        env=env,
        cwd=tool.bench.workdir,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.monotonic() - t0
    err = proc.stderr.read() if proc.stderr else b""
    if keep_stderr is not None:
        keep_stderr.write_bytes(err)
    if status != 0:
        raise SystemExit(f"{tool.name} failed ({status}): {err.decode(errors='replace')[-2000:]}")
    marks: list[tuple[float, str]] = []
    if trace.exists():
        for line in trace.read_text().splitlines():
            stamp, pid, what = line.split(" ", 2)
            if int(pid) == proc.pid:
                marks.append((float(stamp) - t0, what))
    run.wait_quiet(tool.bench.marks())
    tool.bench.counter.settle()
    return wall, usage.ru_utime + usage.ru_stime, marks


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=300)
    ap.add_argument("--size-mb", type=float, default=2.0)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--link", default="wifi")
    ap.add_argument("--rev")
    ap.add_argument("--baseline-rev", action="append")
    ap.add_argument("--no-rsync", action="store_true")
    ap.add_argument(
        "--rclcpp",
        type=Path,
        nargs="?",
        const=Path("/work/shared/data/rclcpp.bundle"),
        help="push rclcpp's tip (a git bundle) instead of a generated workspace",
    )
    ap.add_argument("--env", action="append", default=[], help="NAME=VALUE for fetchsync")
    ap.add_argument("--stderr-dir", type=Path, help="keep each push's stderr here")
    ap.add_argument(
        "--hold",
        type=Path,
        help="set up, write a shell file of the push's environment here, wait until it is gone",
    )
    a = ap.parse_args()

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    run.compile_checkout()
    params = Params(
        files=a.files,
        size_mb=a.size_mb,
        reps_small=1,
        reps_initial=a.rounds,
        seed=1,
        cold=False,
        settle=0.0,
        link=a.link,
        scenarios=("initial",),
    )
    with tempfile.TemporaryDirectory(prefix="firststart-") as tmp, contextlib.ExitStack() as stack:
        workdir = Path(tmp)
        if a.rclcpp:
            import history

            repo = history.Repo(a.rclcpp, workdir / "rclcpp.git", workdir / "ws" / "src" / "rclcpp")
            repo.checkout(repo.first_parent(0)[-1])
            files, size = history.tree_size(workdir / "ws" / "src")
            src = workdir / "ws" / "src"
            ws = run.Workspace(
                root=workdir / "ws",
                src=src,
                files=files,
                bytes=size,
                symlinks=0,
                big_text=src,
                edit_target=src,
                seconds=0.0,
            )
            log(f"rclcpp: {files} files, {size / 1024:.0f} KiB")
        else:
            ws = generate(workdir / "ws", files=a.files, size_mb=a.size_mb, seed=1)
        side, sshd = run.start_robot(stack, None, workdir, log=log)
        baseline = [run.baseline_checkout(rev, workdir) for rev in a.baseline_rev or []]
        measured = run.baseline_checkout(a.rev, workdir) if a.rev else None
        bench = Bench(
            workdir=workdir,
            ws=ws,
            sshd=sshd,
            params=params,
            log=log,
            baseline=baseline,
            measured=measured,
            side=side,
        )
        stack.callback(bench.close)
        tools = [t for t in bench.tools if not (a.no_rsync and isinstance(t, RsyncPush))]
        rows: dict[str, list[tuple[float, float, list[tuple[float, str]]]]] = {}
        if a.hold:
            fs = next(t for t in bench.tools if isinstance(t, FetchsyncPush))
            argv, env = fs.command()
            lines = [f"export {k}={shlex.quote(v)}" for k, v in sorted(env.items())]
            lines.append(f"FS_ARGV={shlex.quote(shlex.join(argv))}")
            lines.append(f"FS_SSH_CONFIG={shlex.quote(str(bench.ssh_config))}")
            lines.append(f"FS_REMOTE={shlex.quote(str(fs.remote))}")
            lines.append(f"FS_RSYNC={shlex.quote(shlex.join(bench.tools[-1].command()[0]))}")
            a.hold.write_text("\n".join(lines) + "\n")
            log(f"holding: source {a.hold}; remove it to end")
            while a.hold.exists():
                time.sleep(0.5)
            return 0
        log(f"load {run.load_average()}")
        for r in range(a.rounds):
            order = tools if r % 2 == 0 else list(reversed(tools))
            for tool in order:
                tool.reset()
                keep = a.stderr_dir / f"{tool.name}-{r}.err" if a.stderr_dir else None
                extra = dict(kv.split("=", 1) for kv in a.env)
                wall, cpu, marks = push(tool, workdir / "trace", extra, keep)
                rows.setdefault(tool.name, []).append((wall, cpu, marks))
                log(f"round {r} {tool.name}: {wall:.3f} s wall, {cpu:.3f} CPU-s")
        log(f"load {run.load_average()}")
        for cache in sorted(workdir.glob("*-cache/fetchsync")):
            log(f"{cache}: {sorted(p.name for p in cache.iterdir())}")
        for name, samples in rows.items():
            print(
                f"\n== {name}: wall median {statistics.median(s[0] for s in samples):.3f} s "
                f"({', '.join(f'{s[0]:.3f}' for s in samples)}); push process CPU median "
                f"{statistics.median(s[1] for s in samples):.3f} s"
            )
            names: list[str] = []
            for s in samples:
                for _, what in s[2]:
                    if what not in names:
                        names.append(what)
            for what in names:
                at = [t for s in samples for t, w in s[2] if w == what]
                print(
                    f"  {statistics.median(at) * 1000:8.1f} ms  (min {min(at) * 1000:7.1f})  {what}"
                )
            for a_mark, b_mark, label in SPANS:
                spans = []
                for s in samples:
                    first = {w: t for t, w in reversed(s[2])}
                    if a_mark in first and b_mark in first:
                        spans.append(first[b_mark] - first[a_mark])
                if spans:
                    print(
                        f"  span {label}: median {statistics.median(spans) * 1000:.1f} ms "
                        f"({', '.join(f'{x * 1000:.0f}' for x in spans)})"
                    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
