#!/usr/bin/env python3
"""What durability costs a push: the robot's syncfs calls, as a share of the push.

    python3 bench/durability.py [--files 7000 --size-mb 150] [--quick] [--json out.json]

Per batch the robot-side endpoint writes the temporaries, calls ``syncfs`` on
the workspace's filesystem, renames them into place and calls ``syncfs``
again before it replies (``fetchsync/protocol/store.py``, ``_Batch.commit``).
This measures what those calls cost, two ways, on the built-in ``local``
robot (the real endpoint as a local subprocess: no SSH time in the push, so
the share is an upper bound of what a push over a network sees):

- **in syncfs**: the endpoint runs under ``strace -f -T --seccomp-bpf -e
  trace=syncfs,fsync,fdatasync,sync`` (only those calls stop the process, so
  the trace costs next to nothing); the time spent inside them is summed and
  divided by that push's wall time.
- **A/B**: the same push with ``syncfs`` made a no-op by an ``LD_PRELOAD``
  shim (compiled here with gcc); the difference of the medians is what a user
  waits for durability. It can be smaller than the time in syncfs: without
  it the kernel writes the data back anyway, later, and part of a flush
  overlaps other work.

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
from typing import Any, Iterator

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
for _p in (str(BENCH), str(REPO / "tests")):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from run import Edits, _workdir, differences, snapshot
from workspace import Workspace, generate

VARIANTS = ("syncfs", "traced", "no-op")
SHIM_C = "int syncfs(int fd) { (void)fd; return 0; }\n"
SYNC_CALLS = "syncfs,fsync,fdatasync,sync"
_DURATION = re.compile(r"^\d+\s+[\d.]+\s+(?:(syncfs|fsync|fdatasync|sync)\(.*|<\.\.\. (\w+) resumed>.*)"
                       r"= 0 <([\d.]+)>$")


@dataclasses.dataclass
class Sample:
    disk: str
    scenario: str
    variant: str
    rep: int
    wall: float
    in_sync: float | None = None  # seconds inside sync calls (traced variant)
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


@contextlib.contextmanager
def loop_disk(workdir: Path, size_mb: int) -> Iterator[Path]:
    """A fresh ext4 filesystem on a loop device, mounted; yields the mount point."""
    image, mnt = workdir / "robot-disk.img", workdir / "robot-disk"
    with open(image, "wb") as fh:
        fh.truncate(size_mb << 20)
    # every table written now, so no background initialisation writes during the runs
    subprocess.run(["mkfs.ext4", "-q", "-F", "-E", "lazy_itable_init=0,lazy_journal_init=0",
                    str(image)], check=True, capture_output=True)
    device = subprocess.run(["losetup", "-f", "--show", str(image)], check=True,
                            capture_output=True, text=True).stdout.strip()
    try:
        mnt.mkdir(exist_ok=True)
        subprocess.run(["mount", device, str(mnt)], check=True, capture_output=True)
        try:
            yield mnt
        finally:
            subprocess.run(["umount", str(mnt)], check=False, capture_output=True)
    finally:
        subprocess.run(["losetup", "-d", device], check=False, capture_output=True)
        image.unlink()


class Runner:
    def __init__(self, *, workdir: Path, ws: Workspace, shim: Path, log: Any) -> None:
        self.workdir = workdir
        self.ws = ws
        self.shim = shim
        self.log = log
        self.edits = Edits(ws)
        self.revision = 0
        self.samples: list[Sample] = []
        self.failures: list[str] = []

    def env(self, home: Path, variant: str, trace: Path) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items()
               if not k.startswith(("FETCHSYNC_", "FETCH_", "XDG_")) and k != "ROS_MASTER_URI"}
        env.update(FETCHSYNC_ROBOT="local", FETCHSYNC_LOCAL_ROBOT_HOME=str(home),
                   FETCHSYNC_WORKSPACE=str(self.ws.root), FETCHSYNC_REMOTE_WORKSPACE="~/robot_ws",
                   XDG_STATE_HOME=str(self.workdir / "state" / home.name),
                   PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
        if variant == "traced":
            strace = shutil.which("strace")
            env["FETCHSYNC_REMOTE_PYTHON"] = (f"{strace} -f -ttt -T --seccomp-bpf -e trace={SYNC_CALLS} "
                                              f"-o {trace} python3")
        elif variant == "no-op":
            env["FETCHSYNC_REMOTE_PYTHON"] = f"env LD_PRELOAD={self.shim} python3"
        return env

    def push(self, disk: str, home: Path, scenario: str, variant: str, rep: int) -> None:
        trace = self.workdir / "trace.txt"
        trace.unlink(missing_ok=True)
        env = self.env(home, variant, trace)
        syncfs_of(home)
        syncfs_of(self.ws.root)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "fetchsync", "push", "--json"], env=env,
                              capture_output=True, text=True, check=False, timeout=900)
        wall = time.perf_counter() - t0
        report = json.loads(proc.stdout.strip().splitlines()[-1]) if proc.stdout.strip() else {}
        if proc.returncode != 0 or not report.get("ok"):
            self.failures.append(f"{disk}/{scenario}/{variant}: push failed: {proc.stderr.strip()[-500:]}")
            return
        s = Sample(disk, scenario, variant, rep, wall, files=report.get("files", 0))
        if variant == "traced":
            s.in_sync, s.sync_calls = sync_time(trace)
        self.samples.append(s)
        diffs = differences(snapshot(self.ws.src), snapshot(home / "robot_ws" / "src"))
        if diffs:
            self.failures.append(f"{disk}/{scenario}/{variant}: {len(diffs)} differences, first: {diffs[0]}")
        self.log(f"  {disk} {scenario:8} {variant:7} rep {rep}: {wall:.3f} s"
                 + (f", {s.in_sync:.3f} s in {s.sync_calls} sync calls" if s.in_sync is not None else ""))

    def run(self, disk: str, home: Path, *, reps_initial: int, reps: int) -> None:
        for rep in range(reps_initial):
            for variant in VARIANTS[rep % 3:] + VARIANTS[:rep % 3]:
                shutil.rmtree(home / "robot_ws", ignore_errors=True)
                shutil.rmtree(self.workdir / "state" / home.name, ignore_errors=True)
                self.push(disk, home, "initial", variant, rep)
        for rep in range(reps):
            for variant in VARIANTS[rep % 3:] + VARIANTS[:rep % 3]:
                self.revision += 1
                self.edits.one_edit(self.revision)
                self.push(disk, home, "one edit", variant, rep)


def summarise(samples: list[Sample]) -> list[dict[str, Any]]:
    rows = []
    keys = list(dict.fromkeys((s.disk, s.scenario) for s in samples))  # in the order measured
    for disk, scenario in keys:
        real, traced, noop = ([s for s in samples if (s.disk, s.scenario, s.variant) == (disk, scenario, v)]
                              for v in VARIANTS)
        if not (real and traced and noop):
            continue
        wall = statistics.median(s.wall for s in real)
        wall_noop = statistics.median(s.wall for s in noop)
        in_sync = statistics.median(s.in_sync or 0.0 for s in traced)
        share = statistics.median((s.in_sync or 0.0) / s.wall for s in traced)
        rows.append({
            "disk": disk, "scenario": scenario, "runs": len(real), "files": real[0].files,
            "wall": wall, "wall_range": (min(s.wall for s in real), max(s.wall for s in real)),
            "wall_noop": wall_noop, "difference": wall - wall_noop,
            "in_sync": in_sync, "sync_calls": traced[0].sync_calls, "share": share,
            "wall_traced": statistics.median(s.wall for s in traced),
        })
    return rows


def render(rows: list[dict[str, Any]], info: dict[str, str]) -> str:
    out = [f"Machine: {info['machine']}", "", f"Workspace: {info['workspace']}", "",
           ("| robot disk | push | wall, syncfs as is | wall, syncfs a no-op | difference | "
            "in sync calls (strace -T) | calls | share of the push |"),
           "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        lo, hi = r["wall_range"]
        out.append(
            f"| {r['disk']} | {r['scenario']} ({r['files']} file{'s' if r['files'] != 1 else ''}) | {r['wall']:.3f} s ({lo:.2f}–{hi:.2f}) "
            f"| {r['wall_noop']:.3f} s | {r['difference'] * 1000:+.0f} ms ({r['difference'] / r['wall']:.1%}) "
            f"| {r['in_sync'] * 1000:.0f} ms | {r['sync_calls']} | {r['share']:.1%} |")
    out += ["", ("medians; wall = the whole `fetchsync push` process; share = time in sync calls / wall "
                 "time of the same (traced) push; difference = wall with syncfs minus wall with it a no-op.")]
    return "\n".join(out)


def machine_line() -> str:
    cpu = "?"
    with contextlib.suppress(OSError):
        m = re.search(r"^model name\s*:\s*(.+)$", Path("/proc/cpuinfo").read_text(), re.MULTILINE)
        cpu = m.group(1) if m else "?"
    commit = subprocess.run(["git", "-C", str(REPO), "describe", "--always", "--dirty"],
                            capture_output=True, text=True, check=False).stdout.strip() or "?"
    return (f"{len(os.sched_getaffinity(0))} CPUs ({cpu}), Linux {os.uname().release}, "
            f"Python {sys.version.split()[0]}, fetchsync at {commit}")


def fs_line(path: Path) -> str:
    res = subprocess.run(["findmnt", "-n", "-o", "SOURCE,FSTYPE,OPTIONS", "-T", str(path)],
                         capture_output=True, text=True, check=False)
    return res.stdout.strip() or "?"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="What the robot's syncfs costs a push.")
    ap.add_argument("--files", type=int, help="files in the workspace (default 7000; --quick 300)")
    ap.add_argument("--size-mb", type=float, help="workspace size in MiB (default 150; --quick 5)")
    ap.add_argument("--reps", type=int, help="one-edit pushes per variant (default 5; --quick 2)")
    ap.add_argument("--reps-initial", type=int, help="initial pushes per variant (default 3; --quick 1)")
    ap.add_argument("--disk", default="same,loop",
                    help="robot home: same (the work dir's disk), loop (an ext4 loop device; root), "
                         "comma-separated (default: same,loop; loop is skipped when not root)")
    ap.add_argument("--quick", action="store_true", help="a smoke run: 300 files, 5 MiB, few repetitions")
    ap.add_argument("--json", help="also write every sample here")
    ap.add_argument("--workdir", help="keep everything here (default: a temporary directory)")
    args = ap.parse_args(argv)
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
    for tool in ("strace", "gcc"):
        if shutil.which(tool) is None:
            print(f"durability: needs {tool} (apt install {tool})", file=sys.stderr)
            return 2

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    with _workdir(args.workdir, keep=bool(args.workdir)) as workdir:
        shim = workdir / "nosyncfs.so"
        (workdir / "nosyncfs.c").write_text(SHIM_C)
        subprocess.run(["gcc", "-shared", "-fPIC", "-O2", "-o", str(shim), str(workdir / "nosyncfs.c")],
                       check=True)
        log(f"generating {files} files, {size_mb} MiB ...")
        ws = generate(workdir / "laptop", files=files, size_mb=size_mb)
        runner = Runner(workdir=workdir, ws=ws, shim=shim, log=log)
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
        info = {"machine": machine_line(),
                "workspace": f"{ws.files} files + {ws.symlinks} symlink, {ws.bytes / 2**20:.1f} MiB "
                             f"(seed 1); initial push {reps_initial}x, one edit {reps}x per variant; "
                             f"robot disks: " + "; ".join(f"{d}: {fs[d]}" for d in disks)}
        print(render(rows, info))
        if runner.failures:
            print("\nFAILED:\n" + "\n".join(f"- {f}" for f in runner.failures))
        if args.json:
            Path(args.json).write_text(json.dumps({
                "info": info, "rows": rows, "failures": runner.failures,
                "samples": [dataclasses.asdict(s) for s in runner.samples]}, indent=1))
    return 1 if runner.failures else 0


if __name__ == "__main__":
    sys.exit(main())
