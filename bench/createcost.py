#!/usr/bin/env python3
"""The robot disk's cost of creating a burst's files, and what the bench's deletions do to it.

    python3 bench/createcost.py probe DIR [--files 500]         # one burst of bare creates
    python3 bench/createcost.py settle DIR [--delete 4000] [--at 0,5,15,30,60,90,150,240,400]
    python3 bench/createcost.py every DIR --files 200 --period 2 --seconds 120  # beside a bench

Why: the watch bench's 500-file burst ends on the robot's creates (bench/watch.py
measure_burst), and its figure swung 289-556 ms between quiet runs of the same code.
This VM's root file system is ext4 WITHOUT a journal (and mounted ``discard``). In that
mode ext4's inode allocator (fs/ext4/ialloc.c find_inode_bit) skips every free inode
that was deleted less than 60 s ago -- 360 s while its inode-table block is still dirty
(``recently_deleted``: RECENTCY_MIN 60 + RECENTCY_DIRTY 300) -- so that a crash cannot
hand a just-deleted inode's stale on-disk copy to a new file. Each skipped bit is a
buffer-cache lookup; after thousands of deletions in a block group, every create in that
group walks past all of them: kernel CPU per create grows with the recent deletions
nearby and falls back after 1-6 minutes. The bench deletes trees between runs and
scenarios (the robot's workspace of the last run, each tool's remote directory), and
the burst's directory is made right next to them.

``probe`` creates FILES 1-4 KB files (open O_CREAT|O_EXCL, write, close: what the
robot's Store does for a new file's temporary, without the fsync) in a new directory
under DIR and prints this process's kernel CPU seconds for them (getrusage: does not
depend on the machine's load the way wall time does), and the wall time. ``settle``
makes a tree of DELETE files under DIR, deletes it as the bench's rmtree does, then
probes at the given seconds after the deletion (each probe in its own new directory,
kept until the end so the probes add no deletions of their own), and prints one line
per probe. Run it as the robot's account (``runuser -u fsrobot --``) under its home to
see what the bench's robot sees.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import time
from pathlib import Path


def probe(parent: Path, files: int, tag: str) -> dict[str, float]:
    """Create ``files`` new files in a new directory under ``parent``: kernel/user CPU, wall."""
    d = parent / f"probe-{tag}-{os.getpid()}-{time.monotonic_ns()}"
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    os.mkdir(d)
    for i in range(files):
        data = b"x" * (1024 + (i * 37) % 3072)
        fd = os.open(d / f"gen_{i:04d}.cpp", os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        try:
            os.write(fd, data)
        finally:
            os.close(fd)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    return {
        "sys_ms": (r1.ru_stime - r0.ru_stime) * 1e3,
        "user_ms": (r1.ru_utime - r0.ru_utime) * 1e3,
        "wall_ms": wall * 1e3,
    }


def make_tree(root: Path, files: int) -> None:
    """A workspace-like tree: 40 files a directory, 1-4 KB each."""
    for i in range(files):
        d = root / f"pkg{i // 40:03d}"
        if i % 40 == 0:
            d.mkdir(parents=True)
        (d / f"f{i:05d}.cpp").write_bytes(b"y" * (1024 + (i * 53) % 3072))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("mode", choices=("probe", "settle", "every"))
    ap.add_argument("dir", type=Path, help="where the probe's directories are made")
    ap.add_argument("--files", type=int, default=500, help="files per probe (default 500)")
    ap.add_argument("--delete", type=int, default=4000, help="settle: files deleted first")
    ap.add_argument(
        "--at",
        default="0,5,15,30,60,90,150,240,400",
        help="settle: seconds after the deletion to probe at",
    )
    ap.add_argument("--period", type=float, default=2.0, help="every: seconds between probes")
    ap.add_argument("--seconds", type=float, default=120.0, help="every: for how long")
    ap.add_argument("--keep", action="store_true", help="keep the probes' directories")
    a = ap.parse_args(argv)
    work = a.dir / f"createcost-{os.getpid()}"
    work.mkdir(parents=True)
    try:
        if a.mode == "probe":
            r = probe(work, a.files, "p")
            print(json.dumps({"t": 0.0, **{k: round(v, 1) for k, v in r.items()}}), flush=True)
            return 0
        if a.mode == "every":
            t0 = time.monotonic()
            while time.monotonic() - t0 < a.seconds:
                r = probe(work, a.files, "e")
                line = {k: round(v, 1) for k, v in r.items()}
                print(json.dumps({"at": time.strftime("%H:%M:%S"), **line}), flush=True)
                time.sleep(max(0.0, a.period - r["wall_ms"] / 1e3))
            return 0
        tree = work / "tree"
        make_tree(tree, a.delete)
        os.sync()
        before = probe(work, a.files, "before")
        print(json.dumps({"t": "before", **{k: round(v, 1) for k, v in before.items()}}))
        t_del = time.monotonic()
        r0 = resource.getrusage(resource.RUSAGE_SELF)
        shutil.rmtree(tree)
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        print(
            json.dumps(
                {
                    "deleted": a.delete,
                    "rm_sys_ms": round((r1.ru_stime - r0.ru_stime) * 1e3, 1),
                    "rm_wall_ms": round((time.monotonic() - t_del) * 1e3, 1),
                }
            ),
            flush=True,
        )
        for at in (float(x) for x in a.at.split(",")):
            wait = t_del + at - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            r = probe(work, a.files, f"{at:g}")
            t = time.monotonic() - t_del
            print(json.dumps({"t": round(t, 1), **{k: round(v, 1) for k, v in r.items()}}))
            sys.stdout.flush()
        return 0
    finally:
        if not a.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
