#!/usr/bin/env python3
"""bench/run.py with each fetchsync's trace marks and CPU per push (edit track, issue 24).

    python3 bench/edittrace.py OUTDIR [run.py's options]

Runs ``bench/run.py`` as given, with two additions for every fetchsync of the run
(this checkout's and each ``--baseline-rev``'s):

- ``FETCHSYNC_TRACE`` = OUTDIR/NAME.trace in the push's environment (the resident
  inherits it: its marks land in the same file); afterwards, per one-shot push
  answered by a resident, each mark's time after the asking process's
  ``quick: asking the resident``;
- CPU seconds (schedstat's time on the CPU of every thread, /proc) per push of the asking process (reaped child),
  the resident (its environment's XDG_STATE_HOME) and the robot's endpoints (their
  environment's XDG_CACHE_HOME: the run's cache of that fetchsync): load-independent
  figures beside run.py's walls.

Writes OUTDIR/cpu.json and prints a summary per fetchsync and scenario.
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import sys
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))

import run  # noqa: E402


def _procs_with(env_entry: bytes, cmd: bytes = b"") -> dict[int, float]:
    """pid -> CPU seconds of the processes whose environment holds ``env_entry`` (and
    whose command line holds ``cmd``)."""
    out: dict[int, float] = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/environ", "rb") as f:
                environ = f.read().split(b"\0")
            if env_entry and env_entry not in environ:
                continue
            if cmd:
                with open(f"/proc/{name}/cmdline", "rb") as f:
                    if cmd not in f.read():
                        continue
            ns = 0
            for tid in os.listdir(f"/proc/{name}/task"):  # ns on the CPU, every thread
                with open(f"/proc/{name}/task/{tid}/schedstat", "rb") as f:
                    ns += int(f.read().split()[0])
        except OSError:
            continue
        out[int(name)] = ns / 1e9
    return out


def _runs_in(pid: int, runtime: Path) -> bool:
    """Whether process ``pid``'s --socket lies directly in ``runtime``'s fetchsync dir."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            argv = f.read().split(b"\0")
    except OSError:
        return False
    sock = argv[argv.index(b"--socket") + 1] if b"--socket" in argv else b""
    return os.path.dirname(os.path.dirname(sock)) == os.fsencode(runtime) or (
        os.path.dirname(sock) == os.fsencode(runtime)
    )


def _delta(before: dict[int, float], after: dict[int, float]) -> float:
    return sum(cpu - before.get(pid, 0.0) for pid, cpu in after.items())


def main(argv: list[str]) -> int:
    out = Path(argv[0]).resolve()
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    command = run.FetchsyncPush.command
    push = run.FetchsyncPush.push

    def traced_command(self: Any) -> tuple[list[str], dict[str, str]]:
        argv_, env = command(self)
        env["FETCHSYNC_TRACE"] = str(out / f"{self.name}.trace")
        return argv_, env

    def measured_push(self: Any, scenario: str, rep: int) -> Any:
        resident = f"XDG_STATE_HOME={self.state_home}".encode()
        robot = f"XDG_CACHE_HOME={self.bench.robot_dir / (self.name + '-cache')}".encode()
        r0, e0 = _procs_with(resident, b"resident"), _procs_with(robot)
        runtime = self.bench.runtime_dir / self.runtime if self.runtime else self.bench.runtime_dir
        master = b"fetchsync.link.mux\0--host\0"
        m0 = {p: c for p, c in _procs_with(b"", master).items() if _runs_in(p, runtime)}
        c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        sample = push(self, scenario, rep)
        c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        r1, e1 = _procs_with(resident, b"resident"), _procs_with(robot)
        m1 = {p: c for p, c in _procs_with(b"", master).items() if _runs_in(p, runtime)}
        rows.append(
            {
                "tool": self.name,
                "scenario": scenario,
                "rep": rep,
                "wall": sample.seconds,
                "asker_cpu": (c1.ru_utime + c1.ru_stime) - (c0.ru_utime + c0.ru_stime),
                "resident_cpu": _delta(r0, r1),
                "robot_cpu": _delta(e0, e1),
                "master_cpu": _delta(m0, m1),
            }
        )
        return sample

    robot_python = run.robot_python
    robot_traces = Path("/tmp/edittrace-robot")
    robot_traces.mkdir(exist_ok=True)
    os.chmod(robot_traces, 0o1777)

    def traced_robot_python(cache: Path) -> str:
        name = cache.name.removesuffix("-cache")
        trace = robot_traces / f"{out.name}-{name}.robot"
        return robot_python(cache).replace(" python3", f" FETCHSYNC_TRACE={trace} python3")

    run.robot_python = traced_robot_python
    run.FetchsyncPush.command = traced_command  # type: ignore[method-assign]
    run.FetchsyncPush.push = measured_push  # type: ignore[method-assign]
    try:
        return run.main(argv[1:])
    finally:
        (out / "cpu.json").write_text(json.dumps(rows, indent=1))
        summarize(out, rows)


def summarize(out: Path, rows: list[dict[str, Any]]) -> None:
    print("\n## CPU per push (medians; ms)")
    keys = sorted({(r["tool"], r["scenario"]) for r in rows})
    for tool, scenario in keys:
        rs = [r for r in rows if (r["tool"], r["scenario"]) == (tool, scenario)]
        if scenario == "initial":
            continue
        med = {
            k: statistics.median(r[k] for r in rs) * 1000
            for k in ("wall", "asker_cpu", "resident_cpu", "master_cpu", "robot_cpu")
        }
        print(
            f"{tool:<28} {scenario:<8} n={len(rs):<2} wall {med['wall']:.0f}  asker "
            f"{med['asker_cpu']:.0f}  resident {med['resident_cpu']:.0f}  master "
            f"{med['master_cpu']:.0f}  robot "
            f"{med['robot_cpu']:.0f}"
        )
    for trace in sorted(out.glob("*.trace")):
        for kind, pushes in marks_after_ask(trace).items():
            print(f"\n## {trace.name}, {kind} ({len(pushes)} pushes): marks after the ask (ms)")
            found: dict[str, list[float]] = {}
            for push_marks in pushes:
                for what, value in push_marks:
                    found.setdefault(what, []).append(value)
            for what, values in sorted(found.items(), key=lambda kv: statistics.median(kv[1])):
                values.sort()
                print(
                    f"  {what:<45} n={len(values):<3} {statistics.median(values):7.1f}  "
                    f"[{values[0]:.1f} .. {values[-1]:.1f}]"
                )


def marks_after_ask(trace: Path) -> dict[str, list[list[tuple[str, float]]]]:
    """Per kind of push (one that planned writes, one that did not), each push's marks
    as (what, ms after its ask)."""
    lines = []
    robot = Path("/tmp/edittrace-robot") / f"{trace.parent.name}-{trace.stem}.robot"
    text = trace.read_text() + (robot.read_text() if robot.exists() else "")
    for line in text.splitlines():
        t, pid, what = line.split(" ", 2)
        lines.append((float(t), int(pid), what))
    lines.sort()
    out: dict[str, list[list[tuple[str, float]]]] = {}
    for i, (t, pid, what) in enumerate(lines):
        if what != "quick: asking the resident":
            continue
        start = next((t0 for t0, p0, w0 in lines if p0 == pid), t)
        push_marks = [("(asker) interpreter up -> asking", (start - t) * 1000)]
        for t2, _pid2, what2 in lines[i + 1 :]:
            push_marks.append((what2, (t2 - t) * 1000))
            if what2 == "quick: answered":
                break
        kind = "writes" if any(w == "push: planned" for w, _ in push_marks) else "no writes"
        out.setdefault(kind, []).append(push_marks)
    return out


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
