#!/usr/bin/env python3
"""The laptop's CPU per further robot of a fleet push, two revisions interleaved.

    python3 bench/fleetab.py --rev HEAD --baseline-rev main [--rounds 3] [--robot-root /dev/shm]
    python3 bench/fleetab.py --rev HEAD --rounds 1 --profile /tmp/prof   # cProfile of each fleet push

The figure issue 27 needs from a lab's laptop: what each robot beyond the first costs
the laptop's process (its CPU seconds, however loaded this machine is), i.e. (CPU of a
fleet push of N robots - CPU of a single push) / (N - 1). The robots are bench/fleet.py's
(each its own sshd behind its own link shaper); both revisions push to the same robots,
alternating within each round, each as a ``git archive`` of it (bench/run.py's
baseline_checkout) or ``.`` for this checkout. Issue 27, link track: nothing here is in
fetchsync itself.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import shutil
import signal
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
for _p in (str(BENCH), str(REPO / "tests")):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from fleet import Fleet, _become_subreaper, _check  # noqa: E402
from robot import RobotSide, add_robot_user_option  # noqa: E402
from run import baseline_checkout, compile_checkout  # noqa: E402
from sshd import running_sshd  # noqa: E402
from workspace import generate  # noqa: E402


class RevFleet(Fleet):
    """A Fleet whose pushes import fetchsync from ``tree``."""

    tree: Path = REPO
    profile: Path | None = None

    def env(self) -> dict[str, str]:
        env = super().env()
        env["PYTHONPATH"] = str(self.tree)
        return env


def checkout(rev: str, workdir: Path) -> tuple[str, Path]:
    if rev == ".":
        compile_checkout(REPO)
        return "worktree", REPO
    return baseline_checkout(rev, workdir)


def one(fleet: RevFleet, scenario: str, edit: Path, robots: list[str]) -> dict[str, Any]:
    if scenario == "initial":
        fleet.reset()
    else:
        with open(edit, "a") as fh:
            fh.write(f"// {len(robots)} {os.urandom(4).hex()}\n")
    r = fleet.push(robots, jobs=len(robots))
    _check(r, f"{scenario} push to {len(robots)}")
    return r


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--rev", default=".", help="a git revision, or . for this checkout")
    ap.add_argument("--baseline-rev", help="the revision to interleave with (optional)")
    ap.add_argument("--robots", type=int, default=20)
    ap.add_argument("--files", type=int, default=300)
    ap.add_argument("--size-mb", type=float, default=6.0)
    ap.add_argument("--link", default="wifi")
    ap.add_argument("--scenario", choices=["initial", "edit"], default="initial")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--robot-root", type=Path)
    ap.add_argument(
        "--profile",
        type=Path,
        metavar="DIR",
        help="profile each fleet push into DIR (bench/threadprof.py: every thread's CPU)",
    )
    add_robot_user_option(ap)
    args = ap.parse_args()
    _become_subreaper()
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    workdir = Path(tempfile.mkdtemp(prefix="fsbench-fleetab-"))
    revs = [args.rev] + ([args.baseline_rev] if args.baseline_rev else [])
    trees = [checkout(rev, workdir) for rev in revs]
    ws = generate(workdir / "ws", files=args.files, size_mb=args.size_mb)
    results: dict[str, list[dict[str, float]]] = {name: [] for name, _ in trees}
    try:
        with contextlib.ExitStack() as stack:
            side = RobotSide.make(args.robot_user, workdir, parent=args.robot_root)
            stack.callback(side.close)
            sshds = []
            for i in range(args.robots):
                sshd = stack.enter_context(running_sshd(side.sshd_dir(f"sshd-{i:02d}")))
                side.opened(sshd.workdir)
                sshds.append(dataclasses.replace(sshd, user=side.user))
            fleet = RevFleet(
                workdir=workdir / args.link, sshds=sshds, link=args.link, ws_root=ws.root, side=side
            )
            stack.callback(fleet.close)
            fleet.reset()
            # every robot once, as bench/fleet.py's singles do before its fleet push: the
            # endpoint's cache on the robots, each robot's login name noted on the laptop
            _check(fleet.push(fleet.names, jobs=len(fleet.names)), "warm-up push")
            for rnd in range(args.rounds):
                order = trees if rnd % 2 == 0 else trees[::-1]
                for name, tree in order:
                    fleet.tree = tree
                    load = os.getloadavg()[0]
                    single = one(fleet, args.scenario, ws.edit_target, fleet.names[:1])
                    if args.profile:
                        args.profile.mkdir(parents=True, exist_ok=True)
                        out = args.profile / f"{name}-{rnd}.prof"
                        fleet.wrap = [sys.executable, str(BENCH / "threadprof.py"), str(out)]
                    many = one(fleet, args.scenario, ws.edit_target, fleet.names)
                    fleet.wrap = []
                    per = (many["cpu"] - single["cpu"]) / (args.robots - 1)
                    results[name].append(
                        {
                            "single_cpu": single["cpu"],
                            "fleet_cpu": many["cpu"],
                            "per_robot_ms": per * 1000,
                            "fleet_s": many["seconds"],
                            "single_s": single["seconds"],
                            "load": load,
                        }
                    )
                    print(
                        f"round {rnd} {name:10} load {load:4.1f}: single {single['cpu']:.3f} CPU-s "
                        f"({single['seconds']:.2f} s), fleet {many['cpu']:.3f} CPU-s "
                        f"({many['seconds']:.2f} s): {per * 1000:.1f} ms per further robot",
                        flush=True,
                    )
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    for name, rows in results.items():
        if rows:
            med = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
            print(
                f"{name:10} median of {len(rows)}: {med['per_robot_ms']:.1f} ms per further robot "
                f"(single {med['single_cpu']:.3f}, fleet {med['fleet_cpu']:.3f} CPU-s; fleet "
                f"{med['fleet_s']:.2f} s, single {med['single_s']:.2f} s)"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
