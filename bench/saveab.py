#!/usr/bin/env python3
"""The watch agent's save -> same bytes on the robot, A/B, interleaved save by save.

    python3 bench/saveab.py [--rev A] --baseline-rev main --saves 30 --link wifi [--strace DIR]
        [--files 2000 --size-mb 40] [--json OUT]

Why a script of its own: bench/watch.py's A/B runs one agent's saves, then the other's,
minutes apart, so the machine's load (2 shared CPUs) differs between them. Here both
agents run at once, each on its own copy of the same workspace (same seed) into its own
remote tree, and the saves alternate between them (A B, B A, ...), ``--gap`` apart, so
each pair meets the same load. Per save, beside the wall time (close -> the robot's
copy holds the bytes, polled every 0.5 ms as watch.py does):

- the agent's trace marks (fetchsync/trace.py: the batch, the push, the first batch
  sent, pushed) as ms after the save, so the laptop's part is separated from the
  link's and the robot's;
- CPU ms of the agent (all its threads, /proc/PID/task/*/schedstat: ns, not ticks) and
  of its robot endpoint (the python3 under the test sshd whose XDG_CACHE_HOME is the
  tool's) during the save: load-independent figures;
- ``--strace DIR``: the robot endpoints traced (strace -f -ttt -T, file system and
  pipe calls): per save, the time from the request's first read to the rename that
  puts the bytes in place, and the syncfs calls before and after it (strace slows
  every syscall: its figures are for where the time goes, not for the wall time).

Prints one line per save and the medians per tool, and A - B per pair.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
for _p in (str(BENCH), str(REPO / "tests")):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from countproxy import LINKS  # noqa: E402
from robot import add_robot_user_option, loop_disk  # noqa: E402
from run import (  # noqa: E402
    _terminated,
    _workdir,
    baseline_checkout,
    check_source,
    load_average,
    robot_python,  # noqa: E402
    start_robot,
)
from watch import (  # noqa: E402
    FetchsyncWatch,
    WatchBench,
    WatchTool,
    log,
    pick_targets,
    verify,
    wait_arrival,
)
from workspace import generate  # noqa: E402


def rev_watch(rev: str, checkout: Path, slot: str) -> type[FetchsyncWatch]:
    """``fetchsync watch`` of git revision ``rev`` (bench/watch.py baseline_watch, with
    the runtime directory and robot cache of its ``slot``, so A and B can both be revs)."""

    class Rev(FetchsyncWatch):
        name = f"fetchsync@{rev}"

        def env(self) -> dict[str, str]:
            env = super().env()
            runtime = self.bench.runtime_dir / slot
            runtime.mkdir(mode=0o700, exist_ok=True)
            env.update(
                PYTHONPATH=str(checkout),
                XDG_RUNTIME_DIR=str(runtime),
                FETCHSYNC_REMOTE_PYTHON=robot_python(self.bench.robot_dir / f"robot-cache-{slot}"),
            )
            return env

    return Rev


def cpu_ns(pid: int) -> int:
    """CPU time of all of ``pid``'s threads, in ns (schedstat's first field)."""
    total = 0
    with contextlib.suppress(OSError):
        for task in Path(f"/proc/{pid}/task").iterdir():
            with contextlib.suppress(OSError, ValueError):
                total += int((task / "schedstat").read_text().split()[0])
    return total


def endpoint_pids(bench: WatchBench, cache: Path) -> list[int]:
    """The robot endpoints (python3 under the test sshd) of the tool whose robot cache
    is ``cache`` (bench/run.py robot_python: ``env XDG_CACHE_HOME=CACHE python3``)."""
    mark = f"XDG_CACHE_HOME={cache}".encode()
    out = []
    for pid in bench.robot_pids():
        with contextlib.suppress(OSError):
            if mark in Path(f"/proc/{pid}/environ").read_bytes().split(b"\0"):
                if b"python" in Path(f"/proc/{pid}/comm").read_bytes():
                    out.append(pid)
    return out


def traced(cls: type[FetchsyncWatch], path: Path, cache: str) -> type[FetchsyncWatch]:
    """``cls`` with its trace marks written to ``path`` (fetchsync/trace.py)."""

    class Traced(cls):  # type: ignore[valid-type,misc]
        name = cls.name
        cache_name = cache

        def env(self) -> dict[str, str]:
            return {**super().env(), "FETCHSYNC_TRACE": str(path)}

    return Traced


def marks(path: Path, t0: float, t1: float) -> list[tuple[float, str]]:
    """The trace marks in ``path`` within [t0, t1]: (ms after t0, what)."""
    out = []
    with contextlib.suppress(OSError), open(path) as fh:
        for line in fh:
            at, _pid, what = line.rstrip("\n").split(" ", 2)
            if t0 - 0.005 <= float(at) <= t1:
                out.append((round((float(at) - t0) * 1e3, 2), what))
    return out


def one_save(tool: WatchTool, target: Path, i: int, tag: str) -> tuple[bytes, float, float | None]:
    """watch.py's save: new unique bytes written in place; (data, saved, arrived), timed
    from just before the close."""
    rel = target.relative_to(tool.ws.src)
    body = target.read_bytes()
    marker = b"\n// fetchsync-bench "
    if marker in body:
        body = body[: body.rindex(marker)]
    data = body + marker + f"{tag} save {i} {time.time_ns()}\n".encode()
    fd = os.open(target, os.O_WRONLY | os.O_TRUNC)
    try:
        os.write(fd, data)  # (a few KB: one write)
        # timed before the close, whose IN_CLOSE_WRITE the agent acts on: on 2 busy CPUs
        # the agent's threads, woken by it, often ran before this process read the clock
        # after close() (watch.py's way: its trace marks came up to ~2 ms "before" the save)
        t_saved = time.perf_counter()
    finally:
        os.close(fd)
    return data, t_saved, wait_arrival(tool.remote_src / rel, data)


# --------------------------------------------------------------------------- strace
def start_strace(pids: list[int], out: Path) -> subprocess.Popen[bytes]:
    argv = ["strace", "-f", "-ttt", "-T", "-o", str(out)]
    argv += ["-e", "trace=read,write,openat,renameat2,rename,syncfs,fsync,fdatasync,unlinkat"]
    for p in pids:
        argv += ["-p", str(p)]
    proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(0.5)  # attached
    return proc


def strace_lines(path: Path) -> list[tuple[float, float, str]]:
    """(start, duration, call) of each finished syscall (wall clock seconds)."""
    out = []
    with contextlib.suppress(OSError), open(path, errors="replace") as fh:
        for line in fh:
            parts = line.split(None, 2)
            if len(parts) < 3 or "<unfinished" in line or "resumed>" in line:
                continue
            try:
                start = float(parts[1])
            except ValueError:
                continue
            dur = 0.0
            if line.rstrip().endswith(">") and "<" in line:
                with contextlib.suppress(ValueError):
                    dur = float(line.rstrip()[line.rstrip().rindex("<") + 1 : -1])
            out.append((start, dur, parts[2].strip()))
    return out


def robot_split(
    calls: list[tuple[float, float, str]], t0: float, t1: float, name: str
) -> dict[str, Any]:
    """What the endpoint did between wall times t0 and t1 for the save of ``name``: ms
    from t0 to its first read, to its rename of the file, the syncfs calls (start, ms)."""
    mine = [c for c in calls if t0 <= c[0] <= t1]
    first_read = next((c[0] for c in mine if c[2].startswith("read(")), None)
    rename = next(
        (c[0] + c[1] for c in mine if c[2].startswith(("renameat2(", "rename(")) and name in c[2]),
        None,
    )
    syncs = [(round((c[0] - t0) * 1e3, 2), round(c[1] * 1e3, 2)) for c in mine if "syncfs(" in c[2]]
    syscalls = len(mine)

    def ms(x: float | None) -> float | None:
        return None if x is None else round((x - t0) * 1e3, 2)

    return {"first_read": ms(first_read), "renamed": ms(rename), "syncfs": syncs, "calls": syscalls}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--rev", metavar="REV", help="A (default: this checkout)")
    ap.add_argument("--baseline-rev", metavar="REV", help="B (none: A alone)")
    ap.add_argument("--saves", type=int, default=30, help="saves per tool")
    ap.add_argument("--gap", type=float, default=0.3, help="seconds between two saves")
    ap.add_argument("--files", type=int, default=2000)
    ap.add_argument("--size-mb", type=float, default=40)
    ap.add_argument("--link", choices=sorted(LINKS), default="wifi")
    ap.add_argument("--strace", type=Path, metavar="DIR", help="trace the robot endpoints")
    add_robot_user_option(ap)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--workdir")
    a = ap.parse_args(argv)
    signal.signal(signal.SIGTERM, _terminated)  # unwinds: the sshd and agents stopped
    rows: list[dict[str, Any]] = []
    straces: list[subprocess.Popen[bytes]] = []
    with _workdir(a.workdir, False) as workdir, contextlib.ExitStack() as disk:
        (workdir / "laptop").mkdir()
        laptop = disk.enter_context(loop_disk(workdir / "laptop", 2048))
        classes: dict[str, type[FetchsyncWatch]] = {}
        checkouts: dict[str, Path] = {}
        caches: dict[str, str] = {}
        for slot, rev in (("a", a.rev), ("b", a.baseline_rev)):
            if rev is None and slot == "a":
                classes["fetchsync"], checkouts["fetchsync"] = FetchsyncWatch, REPO
                caches["fetchsync"] = "robot-cache"
            elif rev is not None:
                short, checkout = baseline_checkout(rev, workdir)
                name = f"fetchsync@{short}" + ("" if slot == "b" else " (A)")
                classes[name], checkouts[name] = rev_watch(short, checkout, slot), checkout
                caches[name] = f"robot-cache-{slot}"
        names = list(classes)
        classes = {
            n: traced(c, workdir / f"trace-{i}", caches[n])
            for i, (n, c) in enumerate(classes.items())
        }
        wss = {
            n: generate(laptop / f"ws{i}", files=a.files, size_mb=a.size_mb, seed=a.seed)
            for i, n in enumerate(names)
        }
        with contextlib.ExitStack() as stack:
            side, sshd = start_robot(stack, a.robot_user, workdir, log=log, fs=a.robot_fs)
            bench = WatchBench(workdir, sshd, LINKS[a.link], side)
            stack.callback(bench.close)
            tools: dict[str, WatchTool] = {}
            for i, (name, cls) in enumerate(classes.items()):
                t = cls(bench, wss[name], bench.robot_dir / f"ws{i}")
                check_source(name, t.env(), checkouts[name], workdir)
                tools[name] = t
            for t in tools.values():
                t.start()
                stack.callback(t.stop)
            for t in tools.values():
                t.wait_live()
            targets = {n: pick_targets(wss[n]) for n in names}
            for n, t in tools.items():  # the connections warm, as a user's
                for k in range(3):
                    one_save(t, targets[n][k], k, "warm")
                    time.sleep(0.2)
            eps = {n: endpoint_pids(bench, bench.robot_dir / caches[n]) for n in names}
            log(f"endpoints: {eps}; load {load_average()}")
            if a.strace:
                a.strace.mkdir(parents=True, exist_ok=True)
                for n in names:
                    straces.append(start_strace(eps[n], a.strace / f"{caches[n]}.strace"))
            wall_off = time.time() - time.perf_counter()
            for i in range(a.saves):
                order = names if i % 2 == 0 else names[::-1]
                for n in order:
                    t = tools[n]
                    assert t.proc is not None
                    target = targets[n][i % len(targets[n])]
                    c_agent, c_robot = cpu_ns(t.proc.pid), sum(cpu_ns(p) for p in eps[n])
                    data, t_saved, t_arrived = one_save(t, target, i, n[-7:])
                    time.sleep(0.05)  # the answer and its bookkeeping
                    row = {
                        "tool": n,
                        "i": i,
                        "file": str(target.relative_to(t.ws.src)),
                        "bytes": len(data),
                        "ms": None if t_arrived is None else round((t_arrived - t_saved) * 1e3, 2),
                        "agent_cpu_ms": round((cpu_ns(t.proc.pid) - c_agent) / 1e6, 2),
                        "robot_cpu_ms": round((sum(cpu_ns(p) for p in eps[n]) - c_robot) / 1e6, 2),
                        "marks": marks(Path(t.env()["FETCHSYNC_TRACE"]), t_saved, t_saved + 0.05),
                        "saved_wall": t_saved + wall_off,
                        "load": load_average(),
                    }
                    rows.append(row)
                    print(
                        f"{i:3} {n:22} {row['ms']} ms  agent {row['agent_cpu_ms']} ms CPU"
                        f"  robot {row['robot_cpu_ms']} ms CPU  "
                        + "; ".join(f"{ms} {w}" for ms, w in row["marks"]),
                        flush=True,
                    )
                    time.sleep(a.gap)
            for p in straces:
                p.terminate()  # our own, by pid
                p.wait(10)
            for n, t in tools.items():
                diffs = verify(t)
                log(f"{n}: {'identical' if not diffs else diffs[:3]}")
                if diffs:
                    rows.append({"tool": n, "verify": diffs[:20]})
    if a.strace:
        for n in names:
            calls = strace_lines(a.strace / f"{caches[n]}.strace")
            for row in rows:
                if row.get("tool") == n and "saved_wall" in row:
                    row["robot"] = robot_split(
                        calls,
                        row["saved_wall"],
                        row["saved_wall"] + 0.06,
                        Path(row["file"]).name,
                    )
                    print(f"{row['i']:3} {n:22} {row['ms']} ms  robot: {row['robot']}")
    for n in names:
        mine = [r for r in rows if r.get("tool") == n and r.get("ms") is not None]
        if not mine:
            continue
        ms = sorted(r["ms"] for r in mine)
        p90 = ms[min(len(ms) - 1, round(0.9 * (len(ms) - 1)))]
        print(
            f"{n:22} p50 {statistics.median(ms):.1f} ms p90 {p90:.1f} (n {len(ms)}), "
            f"agent CPU {statistics.median(r['agent_cpu_ms'] for r in mine):.1f} ms, "
            f"robot CPU {statistics.median(r['robot_cpu_ms'] for r in mine):.1f} ms"
        )
        by_mark: dict[str, list[float]] = {}
        for r in mine:
            for at, what in r["marks"]:
                key = what.split(" of ")[0].split(" pushed")[0] if "batch" in what else what
                by_mark.setdefault(key, []).append(at)
        print(
            "    marks (median ms after the save): "
            + "; ".join(f"{statistics.median(v):.2f} {k} (n {len(v)})" for k, v in by_mark.items())
        )
    if len(names) == 2:
        pairs = []
        for i in range(a.saves):
            got = {r["tool"]: r["ms"] for r in rows if r.get("i") == i and "ms" in r}
            if all(got.get(n) is not None for n in names):
                pairs.append(got[names[0]] - got[names[1]])
        if pairs:
            print(
                f"A - B per pair (ms): median {statistics.median(pairs):+.1f}; "
                + " ".join(f"{d:+.1f}" for d in pairs)
            )
    print(f"load at the end {load_average()}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0 if all("verify" not in r for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
