#!/usr/bin/env python3
"""What durability costs a push: the robot's syncfs calls, as a share of the push.

    python3 bench/durability.py [--files 7000 --size-mb 150] [--quick] [--strace] [--json out.json]

Per batch the robot-side endpoint writes the temporaries, calls ``syncfs`` on
the workspace's filesystem, renames them into place and calls ``syncfs``
again before it replies (``fetchsync/protocol/store.py``, ``_Batch.commit``).
This measures what those calls cost on the built-in ``local`` robot (the real
endpoint as a local subprocess: no SSH time in the push, so the share is an
upper bound of what a push over a network sees). Two LD_PRELOAD shims,
compiled here with gcc, stand in for libc's ``syncfs`` in the endpoint
(which calls it through ctypes):

- **timed**: calls the real ``syncfs`` and appends how long it took to a log
  (``CLOCK_MONOTONIC`` around the call; no ptrace, so the rest of the push
  runs at full speed). The sum over a push, divided by that push's wall
  time, is the share.
- **no-op**: returns 0 at once. The difference of the medians (timed minus
  no-op) is what a user waits for durability, all effects included; it is
  noisy on a shared machine, and can be smaller than the time in syncfs
  (without it the kernel writes the data back anyway, later, partly
  overlapping other work).
- ``--strace`` adds a cross-check at the syscall level: the endpoint under
  ``strace -f -T --seccomp-bpf -e trace=syncfs,fsync,fdatasync,sync``, the
  time inside those calls summed. Its wall times are not used: the endpoint's
  writer threads run many times slower under strace -f here (a 4-thread
  Python loop of stat() calls: 1.6 s alone, 67 s traced).

Scenarios: an **initial** push of the generated workspace
(``bench/workspace.py``, 7,000 files / 150 MiB by default) into an empty
robot workspace, and a **one-file edit** push (one line of a ~10 KB .cpp).
Before every push the dirty data of the filesystems involved is flushed
(``syncfs``), so each push's syncfs pays only for what that push wrote. The
variants are interleaved, their order rotated every repetition; medians.

``--disk`` says where the robot's home is: ``same`` (a directory of the work
dir: this machine's disk, shared with everyone's dirty data) and/or ``loop``
(root only: a fresh ext4 filesystem on a loop device backed by a file of the
work dir, so a syncfs flushes only the robot's writes; each flush still ends
in an fsync of the backing file on the real disk).

Every push's tree is verified against the laptop's (as ``bench/run.py``
does). The report (markdown) goes to stdout, progress to stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import dataclasses
import json
import os
import re
import shutil
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

from robot import loop_disk
from run import Edits, _workdir, differences, snapshot
from workspace import Workspace, generate

VARIANTS = ("timed", "no-op")
NOOP_C = "int syncfs(int fd) { (void)fd; return 0; }\n"
TIMED_C = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include <unistd.h>

/* the real syncfs, timed; each duration (seconds) appended to $FETCHSYNC_SYNCFS_LOG */
int syncfs(int fd)
{
    static int (*real)(int);
    struct timespec a, b;
    if (!real)
        real = (int (*)(int))dlsym(RTLD_NEXT, "syncfs");
    clock_gettime(CLOCK_MONOTONIC, &a);
    int r = real(fd);
    clock_gettime(CLOCK_MONOTONIC, &b);
    const char *log = getenv("FETCHSYNC_SYNCFS_LOG");
    if (log) {
        char line[64];
        int n = snprintf(line, sizeof line, "%.6f\n",
                         (double)(b.tv_sec - a.tv_sec) + (double)(b.tv_nsec - a.tv_nsec) / 1e9);
        int out = open(log, O_WRONLY | O_APPEND | O_CREAT, 0644);
        if (out >= 0) {
            if (write(out, line, (size_t)n) < 0) {
                /* a lost sample, not a failed syncfs */
            }
            close(out);
        }
    }
    return r;
}
"""
SYNC_CALLS = "syncfs,fsync,fdatasync,sync"
_DURATION = re.compile(
    r"^\d+\s+[\d.]+\s+(?:(syncfs|fsync|fdatasync|sync)\(.*|<\.\.\. (\w+) resumed>.*)"
    r"= 0 <([\d.]+)>$"
)


@dataclasses.dataclass
class Sample:
    disk: str
    scenario: str
    variant: str
    rep: int
    wall: float
    in_sync: float | None = None  # seconds inside sync calls (timed and traced variants)
    sync_calls: int | None = None
    files: int = 0


def syncfs_of(path: Path) -> None:
    """Flush the filesystem holding ``path`` (not every filesystem, as sync(1) would)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        if ctypes.CDLL(None, use_errno=True).syncfs(fd) != 0:
            os.sync()
    finally:
        os.close(fd)


def sync_time(trace: Path) -> tuple[float, int]:
    """Seconds spent in sync calls in an ``strace -T`` output, and how many."""
    total, n = 0.0, 0
    for line in trace.read_text().splitlines():
        m = _DURATION.match(line)
        if m:
            total += float(m.group(3))
            n += 1
    return total, n


class Runner:
    def __init__(
        self, *, workdir: Path, ws: Workspace, shims: dict[str, Path], strace: bool, log: Any
    ) -> None:
        self.workdir = workdir
        self.ws = ws
        self.shims = shims
        self.variants = VARIANTS + (("traced",) if strace else ())
        self.log = log
        self.edits = Edits(ws)
        self.revision = 0
        self.samples: list[Sample] = []
        self.failures: list[str] = []

    def env(self, home: Path, variant: str, trace: Path) -> dict[str, str]:
        env = {
            k: v
            for k, v in os.environ.items()
            if not k.startswith(("FETCHSYNC_", "FETCH_", "XDG_")) and k != "ROS_MASTER_URI"
        }
        env.update(
            FETCHSYNC_ROBOT="local",
            FETCHSYNC_LOCAL_ROBOT_HOME=str(home),
            FETCHSYNC_WORKSPACE=str(self.ws.root),
            FETCHSYNC_REMOTE_WORKSPACE="~/robot_ws",
            XDG_STATE_HOME=str(self.workdir / "state" / home.name),
            PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
        )
        if variant == "traced":
            strace = shutil.which("strace")
            env["FETCHSYNC_REMOTE_PYTHON"] = (
                f"{strace} -f -ttt -T --seccomp-bpf -e trace={SYNC_CALLS} -o {trace} python3"
            )
        else:
            env["FETCHSYNC_REMOTE_PYTHON"] = f"env LD_PRELOAD={self.shims[variant]} python3"
            env["FETCHSYNC_SYNCFS_LOG"] = str(trace)
        return env

    def push(self, disk: str, home: Path, scenario: str, variant: str, rep: int) -> None:
        trace = self.workdir / "trace.txt"
        trace.unlink(missing_ok=True)
        env = self.env(home, variant, trace)
        syncfs_of(home)
        syncfs_of(self.ws.root)
        t0 = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-m", "fetchsync", "push", "--json"],
            env=env,
            capture_output=True,
            text=True,
            check=False,
            timeout=900,
        )
        wall = time.perf_counter() - t0
        report = json.loads(proc.stdout.strip().splitlines()[-1]) if proc.stdout.strip() else {}
        if proc.returncode != 0 or not report.get("ok"):
            self.failures.append(
                f"{disk}/{scenario}/{variant}: push failed: {proc.stderr.strip()[-500:]}"
            )
            return
        s = Sample(disk, scenario, variant, rep, wall, files=report.get("files", 0))
        if variant == "traced":
            s.in_sync, s.sync_calls = sync_time(trace)
        elif variant == "timed":
            times = [float(x) for x in trace.read_text().split()] if trace.exists() else []
            s.in_sync, s.sync_calls = sum(times), len(times)
        self.samples.append(s)
        diffs = differences(snapshot(self.ws.src), snapshot(home / "robot_ws" / "src"))
        if diffs:
            self.failures.append(
                f"{disk}/{scenario}/{variant}: {len(diffs)} differences, first: {diffs[0]}"
            )
        self.log(
            f"  {disk} {scenario:8} {variant:7} rep {rep}: {wall:.3f} s"
            + (f", {s.in_sync:.3f} s in {s.sync_calls} sync calls" if s.in_sync is not None else "")
        )

    def order(self, rep: int) -> tuple[str, ...]:
        k = rep % len(self.variants)
        return self.variants[k:] + self.variants[:k]

    def run(self, disk: str, home: Path, *, reps_initial: int, reps: int) -> None:
        for rep in range(reps_initial):
            for variant in self.order(rep):
                shutil.rmtree(home / "robot_ws", ignore_errors=True)
                shutil.rmtree(self.workdir / "state" / home.name, ignore_errors=True)
                self.push(disk, home, "initial", variant, rep)
        for rep in range(reps):
            for variant in self.order(rep):
                self.revision += 1
                self.edits.one_edit(self.revision)
                self.push(disk, home, "one edit", variant, rep)


def _med(xs: list[float]) -> tuple[float, float, float]:
    return statistics.median(xs), min(xs), max(xs)


def summarise(samples: list[Sample]) -> list[dict[str, Any]]:
    rows = []
    keys = list(dict.fromkeys((s.disk, s.scenario) for s in samples))  # in the order measured
    for disk, scenario in keys:

        def pick(variant: str, disk: str = disk, scenario: str = scenario) -> list[Sample]:
            return [
                s for s in samples if (s.disk, s.scenario, s.variant) == (disk, scenario, variant)
            ]

        timed, noop, traced = pick("timed"), pick("no-op"), pick("traced")
        if not (timed and noop):
            continue
        wall, noop_wall = _med([s.wall for s in timed]), _med([s.wall for s in noop])
        row: dict[str, Any] = {
            "disk": disk,
            "scenario": scenario,
            "runs": len(timed),
            "files": timed[0].files,
            "wall": wall,
            "wall_noop": noop_wall,
            "difference": wall[0] - noop_wall[0],
            "in_sync": _med([s.in_sync or 0.0 for s in timed]),
            "sync_calls": timed[0].sync_calls,
            # each push's own share, then the median over the pushes
            "share": _med([(s.in_sync or 0.0) / s.wall for s in timed]),
        }
        if traced:
            row["in_sync_strace"] = _med([s.in_sync or 0.0 for s in traced])
        rows.append(row)
    return rows


def _ms(x: tuple[float, float, float]) -> str:
    return f"{x[0] * 1000:.0f} ms ({x[1] * 1000:.0f}–{x[2] * 1000:.0f})"


def _s(x: tuple[float, float, float]) -> str:
    return f"{x[0]:.2f} s ({x[1]:.2f}–{x[2]:.2f})"


def render(rows: list[dict[str, Any]], info: dict[str, str]) -> str:
    strace = any("in_sync_strace" in r for r in rows)
    out = [
        f"Machine: {info['machine']}",
        "",
        f"Workspace: {info['workspace']}",
        "",
        "| robot disk | push | wall | in syncfs | calls | share of the push | wall, syncfs a no-op "
        "| difference |" + (" in syncfs, strace -T |" if strace else ""),
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |" + (" ---: |" if strace else ""),
    ]
    for r in rows:
        share = r["share"]
        line = (
            f"| {r['disk']} | {r['scenario']} ({r['files']} file{'s' if r['files'] != 1 else ''}) "
            f"| {_s(r['wall'])} | {_ms(r['in_sync'])} | {r['sync_calls']} "
            f"| {share[0]:.1%} ({share[1]:.1%}–{share[2]:.1%}) | {_s(r['wall_noop'])} "
            f"| {r['difference'] * 1000:+.0f} ms |"
        )
        if strace:
            line += f" {_ms(r['in_sync_strace'])} |" if "in_sync_strace" in r else " — |"
        out.append(line)
    out += [
        "",
        (
            "Medians (min–max) over the pushes. wall: the whole `fetchsync push` process, "
            "the endpoint's syncfs timed by the LD_PRELOAD shim; in syncfs: the time inside its "
            "calls in that push; share: in syncfs / wall of the same push; wall, syncfs a no-op: "
            "the same push with the no-op shim; difference: the two medians' difference."
        ),
    ]
    return "\n".join(out)


def machine_line() -> str:
    cpu = "?"
    with contextlib.suppress(OSError):
        m = re.search(r"^model name\s*:\s*(.+)$", Path("/proc/cpuinfo").read_text(), re.MULTILINE)
        cpu = m.group(1) if m else "?"
    commit = (
        subprocess.run(
            ["git", "-C", str(REPO), "describe", "--always", "--dirty"],
            capture_output=True,
            text=True,
            check=False,
        ).stdout.strip()
        or "?"
    )
    return (
        f"{len(os.sched_getaffinity(0))} CPUs ({cpu}), Linux {os.uname().release}, "
        f"Python {sys.version.split()[0]}, fetchsync at {commit}"
    )


def fs_line(path: Path) -> str:
    try:
        res = subprocess.run(
            ["findmnt", "-n", "-o", "SOURCE,FSTYPE,OPTIONS", "-T", str(path)],
            capture_output=True,
            text=True,
            check=False,
        )
    except OSError:
        return "?"
    return res.stdout.strip() or "?"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="What the robot's syncfs costs a push.")
    ap.add_argument("--files", type=int, help="files in the workspace (default 7000; --quick 300)")
    ap.add_argument("--size-mb", type=float, help="workspace size in MiB (default 150; --quick 5)")
    ap.add_argument("--reps", type=int, help="one-edit pushes per variant (default 5; --quick 2)")
    ap.add_argument(
        "--reps-initial", type=int, help="initial pushes per variant (default 3; --quick 1)"
    )
    ap.add_argument(
        "--disk",
        default="same,loop",
        help="robot home: same (the work dir's disk), loop (an ext4 loop device; root), "
        "comma-separated (default: same,loop; loop is skipped when not root)",
    )
    ap.add_argument(
        "--strace",
        action="store_true",
        help="also time the syncfs calls with strace -T (a cross-check; slow)",
    )
    ap.add_argument(
        "--quick", action="store_true", help="a smoke run: 300 files, 5 MiB, few repetitions"
    )
    ap.add_argument("--json", help="also write every sample here")
    ap.add_argument("--workdir", help="keep everything here (default: a temporary directory)")
    ap.add_argument(
        "--report", metavar="JSON", help="print the tables of an earlier --json run and exit"
    )
    args = ap.parse_args(argv)
    if args.report:
        saved = json.loads(Path(args.report).read_text())
        print(render(summarise([Sample(**s) for s in saved["samples"]]), saved["info"]))
        return 0
    files = args.files or (300 if args.quick else 7000)
    size_mb = args.size_mb or (5 if args.quick else 150)
    reps = args.reps or (2 if args.quick else 5)
    reps_initial = args.reps_initial or (1 if args.quick else 3)
    disks = [d.strip() for d in args.disk.split(",") if d.strip()]
    if any(d not in ("same", "loop") for d in disks):
        ap.error("--disk takes same and/or loop")
    if "loop" in disks and os.geteuid() != 0:
        print("durability: not root, so no loop device: --disk loop skipped", file=sys.stderr)
        disks.remove("loop")
    for tool in ("gcc",) + (("strace",) if args.strace else ()):
        if shutil.which(tool) is None:
            print(f"durability: needs {tool} (apt install {tool})", file=sys.stderr)
            return 2

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    with _workdir(args.workdir, keep=bool(args.workdir)) as workdir:
        shims = {}
        for variant, code in (("timed", TIMED_C), ("no-op", NOOP_C)):
            c_file = workdir / f"syncfs-{variant}.c"
            c_file.write_text(code)
            shims[variant] = c_file.with_suffix(".so")
            subprocess.run(
                [
                    "gcc",
                    "-shared",
                    "-fPIC",
                    "-O2",
                    "-Wall",
                    "-o",
                    str(shims[variant]),
                    str(c_file),
                    "-ldl",
                ],
                check=True,
            )
        log(f"generating {files} files, {size_mb} MiB ...")
        ws = generate(workdir / "laptop", files=files, size_mb=size_mb)
        runner = Runner(workdir=workdir, ws=ws, shims=shims, strace=args.strace, log=log)
        fs = {}
        for disk in disks:
            if disk == "same":
                home = workdir / "robot-same"
                home.mkdir(exist_ok=True)
                fs[disk] = fs_line(home)
                runner.run(disk, home, reps_initial=reps_initial, reps=reps)
            else:
                with loop_disk(workdir, max(512, int(size_mb * 4) + 256)) as mnt:
                    home = mnt / "robot-loop"
                    home.mkdir()
                    fs[disk] = fs_line(home)
                    runner.run(disk, home, reps_initial=reps_initial, reps=reps)
        rows = summarise(runner.samples)
        info = {
            "machine": machine_line(),
            "workspace": f"{ws.files} files + {ws.symlinks} symlink, {ws.bytes / 2**20:.1f} MiB "
            f"(seed 1); initial push {reps_initial}x, one edit {reps}x per variant; "
            f"robot disks: " + "; ".join(f"{d}: {fs[d]}" for d in disks),
        }
        print(render(rows, info))
        if runner.failures:
            print("\nFAILED:\n" + "\n".join(f"- {f}" for f in runner.failures))
        if args.json:
            Path(args.json).write_text(
                json.dumps(
                    {
                        "info": info,
                        "rows": rows,
                        "failures": runner.failures,
                        "samples": [dataclasses.asdict(s) for s in runner.samples],
                    },
                    indent=1,
                )
            )
    return 1 if runner.failures else 0


if __name__ == "__main__":
    sys.exit(main())
