#!/usr/bin/env python3
"""The watch agent's burst, A/B: this checkout's agent against REV's, in alternating order.

    python3 bench/burstab.py --baseline-rev main --rounds 4 --link wifi [--burst 500]
        [--settle 240] [--robot-fs ext4|home] [--laptop-fs ext4|tmp] [--files 2000 --size-mb 40] [--json OUT]

Why a script of its own: bench/watch.py's A/B always runs this checkout's agent first
and the baseline's second, each burst right after its agent's start, with nothing
between them and the robot disk's state. On this VM the robot's trees are on ext4
WITHOUT a journal, whose inode allocator skips every inode freed in the last minute
(six while its inode table block is dirty: fs/ext4/ialloc.c recently_deleted): after
a run's (or another session's) trees are deleted near the robot's directory, a 500-file
burst's creates cost 4-10x the kernel CPU for a minute or more (bench/createcost.py),
and the first tool of a run meets more of it than the second. Here:

- the order alternates each round (A B, B A, ...), each tool into a fresh remote tree;
- before each burst the robot disk is waited for until creating files runs at its usual
  speed (bench/run.py settle_allocator, against tmpfs; ``--settle 0``: no wait), nothing
  is deleted on the robot until the end (the probes' files go to a graveyard), and the
  cost of 200 bare creates next to the burst's directory is measured and reported
  (kernel CPU ms: ``create_sys_ms``), so a round met by a slow disk shows as one;
- load-independent figures beside the wall times: the robot's CPU seconds for the burst
  (the sshd's session tree: the endpoint), the agent's, and the pushes the agent made
  for it (its log's "pushed" lines);
- the robot's side (``--robot-fs``, bench/robot.py) and the laptop's workspace
  (``--laptop-fs``) each on a journaled ext4 of the run's own by default, as a robot's and
  a laptop's disks are: nobody else's deletions nearby, no skipped inodes.

Prints one line per burst and a summary (medians per tool, and per round A - B).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import re
import signal
import statistics
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
from createcost import probe  # noqa: E402
from robot import add_robot_user_option, loop_disk  # noqa: E402
from run import (  # noqa: E402
    _terminated,
    _workdir,
    baseline_checkout,
    check_source,
    load_average,
    settle_allocator,
    start_robot,
)
from watch import (  # noqa: E402
    FetchsyncWatch,
    WatchBench,
    WatchTool,
    baseline_watch,
    cpu_seconds,
    log,
    measure_burst,
    measure_latency,
    pick_targets,
    tree_pids,
    verify,
)
from workspace import generate  # noqa: E402


def one_burst(
    tool: WatchTool,
    bench: WatchBench,
    n: int,
    tag: str,
    settle: float,
    targets: list[Path],
) -> dict[str, Any]:
    """Start ``tool`` into a fresh tree, a few saves, settle, the burst; its figures."""
    tool.start()
    try:
        tool.wait_live()
        measure_latency(tool, targets, 3, 0.2, tag)  # the connection warm, as a user's
        allocator = settle_allocator(
            bench.robot_dir, bench.robot_dir / "graveyard", log, wait=settle
        )
        probes = bench.robot_dir / "probes"
        probes.mkdir(exist_ok=True)
        create = probe(probes, 200, tag)
        time.sleep(0.5)  # the probe's writeback and the settle's out of the way
        assert tool.proc is not None
        agent_pids = tree_pids(tool.proc.pid)
        robot_pids = bench.robot_pids()
        cpu_a0, cpu_r0 = cpu_seconds(agent_pids), cpu_seconds(robot_pids)
        log_at = tool.logfile.stat().st_size
        t_call = time.perf_counter()  # = the first write's time, within microseconds
        c_call = time.process_time()
        b = measure_burst(tool, n, tag)  # watch.py's wait: one stat a millisecond
        bench_cpu = time.process_time() - c_call
        time.sleep(0.3)  # the last answer's bookkeeping
        cpu_a1, cpu_r1 = cpu_seconds(agent_pids), cpu_seconds(robot_pids)
        with open(tool.logfile, "rb") as fh:
            fh.seek(log_at)
            text = fh.read().decode(errors="replace")
        pushes = [int(m) for m in re.findall(r"pushed (\d+) files", text)]
        diffs = verify(tool)
    finally:
        tool.stop()
    return {
        **b,
        "create_sys_ms": round(create["sys_ms"], 1),
        "create_us_settle": allocator["create_us"],
        "create_vs_tmpfs": allocator["create_vs_tmpfs"],
        "settle_waited_s": allocator["waited_s"],
        "agent_cpu_s": round(cpu_a1 - cpu_a0, 2),
        "robot_cpu_s": round(cpu_r1 - cpu_r0, 2),
        "bench_cpu_s": round(bench_cpu, 3),
        "pushes": len(pushes),
        "pushed_files": pushes,
        "verified": not diffs,
        "load": load_average(),
        "timeline": timeline(tool, t_call, b),
    }


def timeline(tool: WatchTool, t0: float, b: dict[str, Any]) -> list[tuple[int, str]]:
    """The agent's trace marks (``--trace``) during the burst: (ms after the first write,
    what), the bench's last write and arrival among them."""
    path = tool.env().get("FETCHSYNC_TRACE")
    out: list[tuple[int, str]] = [(round(b["write_seconds"] * 1e3), "bench: last write")]
    if b["after_first"] is not None:
        out.append((round(b["after_first"] * 1e3), "bench: all on the robot"))
    if path:
        end = t0 + (b["after_first"] or 60) + 0.2
        with contextlib.suppress(OSError), open(path) as fh:
            for line in fh:
                at, _pid, what = line.rstrip("\n").split(" ", 2)
                if t0 - 0.01 <= float(at) <= end:
                    out.append((round((float(at) - t0) * 1e3), what))
    return sorted(out)


def traced(cls: type[FetchsyncWatch], path: Path) -> type[FetchsyncWatch]:
    """``cls`` with its trace marks written to ``path`` (fetchsync/trace.py)."""

    class Traced(cls):  # type: ignore[valid-type,misc]
        name = cls.name

        def env(self) -> dict[str, str]:
            return {**super().env(), "FETCHSYNC_TRACE": str(path)}

    return Traced


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--baseline-rev", required=True, metavar="REV")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--burst", type=int, default=500)
    ap.add_argument("--files", type=int, default=2000)
    ap.add_argument("--size-mb", type=float, default=40)
    ap.add_argument("--link", choices=sorted(LINKS), default="wifi")
    ap.add_argument("--settle", type=float, default=240.0, help="seconds at most (0: none)")
    ap.add_argument(
        "--laptop-fs",
        choices=("ext4", "tmp"),
        default="ext4",
        help="the laptop's workspace on a journaled ext4 of its own (default) or in the work dir",
    )
    add_robot_user_option(ap)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--trace", action="store_true", help="print the agents' trace marks")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--workdir")
    a = ap.parse_args(argv)
    signal.signal(signal.SIGTERM, _terminated)  # unwinds: the sshd and agents stopped
    rows: list[dict[str, Any]] = []
    with _workdir(a.workdir, False) as workdir, contextlib.ExitStack() as disk:
        wsdir = workdir / "ws"
        if a.laptop_fs == "ext4":
            # the laptop's disk: a journaled ext4 of its own too (the bench's writer creates
            # the burst's files: on this machine's root they meet others' deletions as well)
            (workdir / "laptop").mkdir()
            wsdir = disk.enter_context(loop_disk(workdir / "laptop", 2048)) / "ws"
        ws = generate(wsdir, files=a.files, size_mb=a.size_mb, seed=a.seed)
        targets = pick_targets(ws)
        rev, checkout = baseline_checkout(a.baseline_rev, workdir)
        classes: dict[str, type[FetchsyncWatch]] = {
            "fetchsync": FetchsyncWatch,
            f"fetchsync@{rev}": baseline_watch(rev, checkout),
        }
        names = list(classes)
        if a.trace:
            classes = {
                n: traced(c, workdir / f"trace-{i}") for i, (n, c) in enumerate(classes.items())
            }
        with contextlib.ExitStack() as stack:
            side, sshd = start_robot(stack, a.robot_user, workdir, log=log, fs=a.robot_fs)
            bench = WatchBench(workdir, sshd, LINKS[a.link], side)
            stack.callback(bench.close)
            for name, cls in classes.items():
                t = cls(bench, ws, bench.robot_dir / f"{name}-check")
                check_source(name, t.env(), checkout if "@" in name else REPO, workdir)
            for r in range(a.rounds):
                order = names if r % 2 == 0 else names[::-1]
                for name in order:
                    tool = classes[name](bench, ws, bench.robot_dir / f"{name}-r{r}")
                    row = one_burst(
                        tool,
                        bench,
                        a.burst,
                        f"r{r}{name[-7:]}",
                        a.settle,
                        targets,
                    )
                    row.update(tool=name, round=r)
                    rows.append(row)
                    print(
                        f"round {r} {name:22} first->all {row['after_first'] * 1e3:6.0f} ms"
                        f"  last->all {row['after_last'] * 1e3:6.0f}  write {row['write_seconds'] * 1e3:4.0f}"
                        f"  pushes {row['pushes']} {row['pushed_files']}  robot CPU {row['robot_cpu_s']:.2f} s"
                        f"  agent CPU {row['agent_cpu_s']:.2f} s  bench CPU {row['bench_cpu_s']:.2f} s  200 creates {row['create_sys_ms']:.0f} ms sys"
                        f"  ({row['create_vs_tmpfs']}x tmpfs, waited {row['settle_waited_s']:.0f} s)"
                        f"  ok={row['verified']}  load {row['load']}",
                        flush=True,
                    )
                    if a.trace:
                        print("    " + "; ".join(f"{ms} {what}" for ms, what in row["timeline"]))
    for name in names:
        mine = [x for x in rows if x["tool"] == name and x["after_first"] is not None]
        if mine:
            print(
                f"{name:22} median first->all {statistics.median(x['after_first'] for x in mine) * 1e3:.0f} ms"
                f", last->all {statistics.median(x['after_last'] for x in mine) * 1e3:.0f}"
                f", robot CPU {statistics.median(x['robot_cpu_s'] for x in mine):.2f} s"
                f", agent CPU {statistics.median(x['agent_cpu_s'] for x in mine):.2f} s"
                f", pushes {statistics.median(x['pushes'] for x in mine)}"
            )
    diffs = []
    for r in range(a.rounds):
        pair = {x["tool"]: x for x in rows if x["round"] == r}
        if len(pair) == 2 and all(x["after_first"] is not None for x in pair.values()):
            diffs.append((pair[names[0]]["after_first"] - pair[names[1]]["after_first"]) * 1e3)
    if diffs:
        print(f"A - B per round (first->all, ms): {[round(d) for d in diffs]}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0 if all(x["verified"] and not x["missing"] for x in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
