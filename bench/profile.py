#!/usr/bin/env python3
"""One command per link profile for the final runs: run.py, watch.py and history.py in turn.

    python3 bench/profile.py wifi   [--out DIR]      # ~15 min quiet
    python3 bench/profile.py loopback [--out DIR]    # loopback + weak: ~20 min together
    python3 bench/profile.py weak   [--out DIR]
    python3 bench/profile.py wifi --dry-run          # the commands only
    python3 bench/profile.py wifi --robot-user root  # other arguments go to every script

Each script runs with the arguments of :data:`PROFILES` (the ones bench/README.md's
"Running it" gives), one after the other, never at the same time; each one's full
report and JSON go to ``--out`` (default ``bench-PROFILE-<time>`` in the current
directory), its progress to stderr. At the end it prints, for pasting into
bench/README.md's "Latest results", one table of every script's rows (figure,
target, fetchsync, rsync / lsyncd, ratio, verdict) with the load average before
and after each script, and ``--json`` writes them. The exit status is the first
non-zero one of the scripts (a tree that failed verification), else 0.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
if str(BENCH) not in sys.path:
    sys.path.insert(0, str(BENCH))

from run import RESULTS_HEADER, ResultRow, load_average, machine_info

PROFILES: dict[str, list[tuple[str, list[str]]]] = {
    "wifi": [
        (
            "run.py",
            "--link wifi --files 2000 --size-mb 40 --reps 3 --reps-initial 3 --no-cold "
            "--settle 120".split(),
        ),
        ("watch.py", "--link wifi --saves 30 --idle-files 0".split()),
        ("history.py", "--link wifi --commits 30 --switches 4".split()),
    ],
    "loopback": [
        (
            "run.py",
            "--link loopback --files 2000 --size-mb 40 --reps 3 --reps-initial 3 --no-cold "
            "--settle 120".split(),
        ),
        ("watch.py", "--link loopback --saves 30 --recovery 0".split()),
        ("history.py", "--link loopback --commits 20 --switches 2".split()),
    ],
    "weak": [
        (
            "run.py",
            "--link weak --files 1000 --size-mb 20 --reps 3 --reps-initial 3 --no-cold "
            "--settle 0".split(),
        ),
        ("history.py", "--link weak --commits 20 --switches 2".split()),
        (
            "watch.py",
            "--link weak --saves 20 --idle-files 0 --recovery 0 --tools fetchsync".split(),
        ),
    ],
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("profile", nargs="+", choices=sorted(PROFILES), help="one or more, in turn")
    ap.add_argument("--out", type=Path, help="where the reports go (default bench-PROFILE-TIME)")
    ap.add_argument("--json", dest="json_out", type=Path, help="write the rows here")
    ap.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    # any other argument goes to every script (e.g. --robot-user root)
    a, extra = ap.parse_known_args(argv)
    name = "+".join(a.profile)
    out = a.out or Path(f"bench-{name}-{time.strftime('%Y%m%d-%H%M%S')}")
    steps = []
    for profile, script, args in ((p, s, x) for p in a.profile for s, x in PROFILES[p]):
        stem = f"{profile}-{script.removesuffix('.py')}"
        argv_ = [
            sys.executable,
            str(BENCH / script),
            *args,
            *extra,
            "--json",
            str(out / f"{stem}.json"),
        ]
        steps.append((profile, script, stem, argv_))
    if a.dry_run:
        for _p, _s, _stem, argv_ in steps:
            print(" ".join(argv_))
        return 0
    out.mkdir(parents=True, exist_ok=True)
    commit = machine_info().get("commit", "?")
    rows: list[tuple[str, ResultRow]] = []
    loads: list[tuple[str, str]] = []
    status = 0
    for profile, script, stem, argv_ in steps:
        before, t0 = load_average(), time.monotonic()
        print(f"[{time.strftime('%H:%M:%S')}] {' '.join(argv_[1:])}", file=sys.stderr, flush=True)
        with open(out / f"{stem}.md", "w") as report:
            rc = subprocess.run(argv_, stdout=report, check=False, cwd=os.getcwd()).returncode
        minutes = (time.monotonic() - t0) / 60
        loads.append(
            (
                profile,
                f"{script}: load {before} → {load_average()}, {minutes:.1f} min, exit status {rc}",
            )
        )
        print(f"  {loads[-1][1]}", file=sys.stderr, flush=True)
        status = status or rc
        try:
            raw = json.loads((out / f"{stem}.json").read_text())
        except (OSError, ValueError):
            continue
        rows += [(profile, ResultRow(**r)) for r in raw.get("results_rows", [])]
    for profile in a.profile:
        print(f"### `{profile}` (main at {commit}; reports in {out}/)")
        print()
        for p, line in loads:
            if p == profile:
                print(f"- {line}")
        print()
        print(RESULTS_HEADER[0].format(commit=commit))
        print(RESULTS_HEADER[1])
        for p, row in rows:
            if p == profile:
                print(row.markdown())
        print()
    if a.json_out:
        a.json_out.write_text(
            json.dumps(
                {
                    "profiles": a.profile,
                    "commit": commit,
                    "loads": [{"profile": p, "line": x} for p, x in loads],
                    "rows": [{"script": s, **r.__dict__} for s, r in rows],
                },
                indent=1,
            )
            + "\n"
        )
    return status


if __name__ == "__main__":
    sys.exit(main())
