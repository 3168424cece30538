#!/usr/bin/env python3
"""fetchsync push vs rsync on real history: ros2/rclcpp's commits and releases, replayed.

    python3 bench/history.py [--link wifi] [--commits 30] [--switches 4] [--json out.json]
    python3 bench/history.py --quick      # smoke: 2 commits, 1 switch, 1 no-op

Generated workspaces (``bench/run.py``) measure scale; this measures what a
developer's day sends: the changes real commits make. One run:

1. clones the git bundle of ros2/rclcpp (``--bundle``, default
   ``/work/shared/data/rclcpp.bundle``) into a private git dir, and checks out
   the commit ``--commits`` first-parent steps before its tip into the
   workspace's ``src/rclcpp`` (the git dir stays outside ``src/``: a robot
   wants no ``.git``, fetchsync skips it and fetch_tools' rsync would send it);
2. **initial**: pushes that tree with each tool into an empty remote dir;
3. **no-op**: ``--noops`` pushes with nothing changed, to know what each tool
   pays for a push that sends nothing (its handshake, its listing);
4. **commit**: checks out each next first-parent commit (``git checkout -f``:
   only the files the commit changed are rewritten, as a ``git pull`` does) and
   pushes after each;
5. **switch**: checks out a few releases in turn (the latest release of the
   previous major version, back to the tip's, two majors back, back to the
   tip's), pushing after each.

Every push is a new process (as run.py); the tools alternate which goes first
at each step; after each step both robot trees are compared with the local one
(paths, kinds, modes, link targets, SHA-256) and a difference fails the run.
The report gives, per kind of step and tool, the wall time and the bytes on the
wire beyond that tool's median no-op push, their medians and totals, and the
ratios fetchsync/rsync: of the medians, of the totals, and the median of each
step's own ratio. ``--link`` and ``--baseline-rev`` are run.py's.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
if str(BENCH) not in sys.path:
    sys.path.insert(0, str(BENCH))

from countproxy import LINKS
from robot import add_robot_user_option
from run import (
    Bench,
    FetchsyncPush,
    Params,
    ResultRow,
    _human,
    _ratio,
    _verdict,
    _workdir,
    baseline_checkout,
    compile_checkout,
    link_line,
    load_average,
    machine_info,
    results_section,
    start_robot,
)
from workspace import Workspace

BUNDLE = Path("/work/shared/data/rclcpp.bundle")
RELEASE = re.compile(r"^(\d+)\.(\d+)\.(\d+)$")
KINDS = (("commit", "one commit"), ("switch", "a release switch"))
# Targets on wifi, issue 24: (bytes beyond no-op, wall time), fetchsync/rsync at most.
TARGETS_BY_LINK: dict[str, dict[str, tuple[float | None, float | None]]] = {
    "wifi": {"commit": (0.8, None), "switch": (1.0, 1.0)},
}


class Repo:
    """A private clone of the bundle whose work tree is the workspace's package dir."""

    def __init__(self, bundle: Path, gitdir: Path, worktree: Path) -> None:
        self.gitdir, self.worktree = gitdir, worktree
        if not gitdir.exists():
            subprocess.run(
                ["git", "clone", "--quiet", "--bare", str(bundle), str(gitdir)], check=True
            )
        worktree.mkdir(parents=True, exist_ok=True)

    def git(self, *args: str) -> str:
        out = subprocess.run(
            ["git", f"--git-dir={self.gitdir}", f"--work-tree={self.worktree}", *args],
            capture_output=True,
            text=True,
            check=True,
        )
        return out.stdout

    def checkout(self, rev: str) -> None:
        self.git("checkout", "--quiet", "--force", rev)

    def first_parent(self, n: int) -> list[str]:
        """The tip and the ``n`` first-parent commits before it, oldest first."""
        return self.git("rev-list", "--first-parent", "-n", str(n + 1), "HEAD").split()[::-1]

    def releases(self) -> list[tuple[tuple[int, int, int], str]]:
        """(version, commit) of the first-parent commits titled like ``29.3.0``, newest first."""
        out = []
        for line in self.git("log", "--first-parent", "--format=%H %s", "HEAD").splitlines():
            sha, _, subject = line.partition(" ")
            m = RELEASE.match(subject.strip())
            if m:
                out.append(((int(m[1]), int(m[2]), int(m[3])), sha))
        return out


def switch_plan(releases: list[tuple[tuple[int, int, int], str]], n: int) -> list[tuple[str, str]]:
    """``n`` release switches: the latest release of the previous major, back to the
    newest, two majors back, back to the newest, ... as (version, commit)."""
    latest: dict[int, tuple[tuple[int, int, int], str]] = {}
    for version, sha in releases:
        latest.setdefault(version[0], (version, sha))
    majors = sorted(latest, reverse=True)
    if len(majors) < 2:
        raise SystemExit("the bundle has fewer than two major releases to switch between")
    tip = latest[majors[0]]
    plan = []
    k = 1
    while len(plan) < n:
        old = latest[majors[min(k, len(majors) - 1)]]
        plan.append(old)
        if len(plan) < n:
            plan.append(tip)
        k += 1
    return [(".".join(map(str, v)), sha) for v, sha in plan]


def tree_size(root: Path) -> tuple[int, int]:
    files = total = 0
    for p in root.rglob("*"):
        if p.is_file() and not p.is_symlink():
            files += 1
            total += p.stat().st_size
    return files, total


class History:
    def __init__(self, bench: Bench, repo: Repo, log: Any) -> None:
        self.bench, self.repo, self.log = bench, repo, log
        self.steps: list[dict[str, Any]] = []

    def push_all(self, kind: str, index: int, label: str) -> None:
        for tool in self.bench.order(index):
            s = self.bench.push_sample(tool, kind, index)
            if s is None:
                continue
            self.log(
                f"  {kind:7} {index:2} {label:24} {tool.name:18} {s.seconds:6.3f} s "
                f"{_human(s.bytes):>10}"
            )
        name = f"{kind} {index} {label}"
        self.bench.verify(name)
        self.steps.append(
            {"kind": kind, "index": index, "label": label, "verified": self.bench.verified[name]}
        )

    def run(self, commits: list[str], switches: list[tuple[str, str]], noops: int) -> None:
        self.repo.checkout(commits[0])
        self.bench.probe_robot()
        for tool in self.bench.tools:
            tool.reset()
        self.push_all("initial", 0, commits[0][:10])
        for k in range(noops):
            self.push_all("noop", k, "nothing changed")
        for i, sha in enumerate(commits[1:]):
            self.repo.checkout(sha)
            title = self.repo.git("log", "-1", "--format=%s", sha).strip()[:40]
            self.log(f"commit {i + 1}/{len(commits) - 1}: {sha[:10]} {title}")
            self.push_all("commit", i, sha[:10])
        for j, (version, sha) in enumerate(switches):
            self.repo.checkout(sha)
            self.log(f"switch {j + 1}/{len(switches)}: to {version}")
            self.push_all("switch", j, f"to {version}")

    def verified_ok(self) -> bool:
        return (
            not self.bench.failures
            and bool(self.steps)
            and all(not d for st in self.steps for d in st["verified"].values())
        )

    # ---------------------------------------------------------------------- results
    def summary(self, ours: str, theirs: str, *, targets: bool = True) -> dict[str, Any]:
        samples = self.bench.samples

        def noop_median(tool: str, key: str) -> float:
            xs = [getattr(s, key) for s in samples if s.tool == tool and s.scenario == "noop"]
            return statistics.median(xs) if xs else 0.0

        noop = {
            t: {"seconds": noop_median(t, "seconds"), "bytes": noop_median(t, "bytes")}
            for t in (ours, theirs)
        }
        rows: dict[str, Any] = {"noop": noop}
        link_targets = TARGETS_BY_LINK.get(self.bench.params.link, {}) if targets else {}
        for kind, title in (("initial", "initial push"), *KINDS):
            per: dict[str, dict[int, tuple[float, float]]] = {}
            for t in (ours, theirs):
                base = noop[t] if kind != "initial" else {"seconds": 0.0, "bytes": 0}
                per[t] = {
                    s.rep: (s.seconds, s.bytes - base["bytes"])
                    for s in samples
                    if s.tool == t and s.scenario == kind
                }
            if not per[ours] or not per[theirs]:
                continue  # every push of one of them failed (see the failures)
            row: dict[str, Any] = {"title": title, "n": len(per[ours])}
            for t in (ours, theirs):
                secs = [v[0] for v in per[t].values()]
                byts = [v[1] for v in per[t].values()]
                row[t] = {
                    "seconds": statistics.median(secs),
                    "seconds_total": sum(secs),
                    "bytes": statistics.median(byts),
                    "bytes_total": sum(byts),
                }
            f, r = row[ours], row[theirs]

            def ratio(a: float, b: float) -> float | None:
                return a / b if b > 0 else None

            row["time_ratio"] = ratio(f["seconds"], r["seconds"])
            row["time_total_ratio"] = ratio(f["seconds_total"], r["seconds_total"])
            steps = [per[ours][k][0] / per[theirs][k][0] for k in per[ours] if k in per[theirs]]
            row["time_step_ratio"] = statistics.median(steps) if steps else None
            row["bytes_ratio"] = ratio(f["bytes"], r["bytes"])
            row["bytes_total_ratio"] = ratio(f["bytes_total"], r["bytes_total"])
            bytes_target, time_target = link_targets.get(kind, (None, None))
            if bytes_target is not None:
                row["bytes_target"] = bytes_target
                row["bytes_pass"] = all(
                    x is not None and x <= bytes_target
                    for x in (row["bytes_ratio"], row["bytes_total_ratio"])
                )
            if time_target is not None:
                row["time_target"] = time_target
                row["time_pass"] = all(
                    x is not None and x <= time_target
                    for x in (row["time_ratio"], row["time_step_ratio"])
                )
            rows[kind] = row
        return rows


def _tables(rows: dict[str, Any], ours: str, theirs: str) -> list[str]:
    n = rows["noop"]
    out = [
        (
            f"No-op push (median): {ours} {n[ours]['seconds']:.3f} s, {_human(n[ours]['bytes'])}; "
            f"{theirs} {n[theirs]['seconds']:.3f} s, {_human(n[theirs]['bytes'])}."
        ),
        "",
        (
            f"| step | n | {ours}: time, median (total) | {theirs}: time, median (total) | "
            "time ratio: of the medians, median of the steps' | "
            f"{ours}: bytes beyond no-op, median (total) | {theirs}: same | "
            "bytes ratio: of the medians (of the totals) | target |"
        ),
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    for kind in ("initial", "commit", "switch"):
        if kind not in rows:
            continue
        row = rows[kind]
        f, r = row[ours], row[theirs]
        targets = []
        if "bytes_target" in row:
            targets.append(f"bytes ≤ {row['bytes_target']:g}x {_verdict(row['bytes_pass'])}")
        if "time_target" in row:
            targets.append(f"time ≤ {row['time_target']:g}x {_verdict(row['time_pass'])}")
        out.append(
            f"| {row['title']} | {row['n']} | {f['seconds']:.3f} s ({f['seconds_total']:.1f} s) | "
            f"{r['seconds']:.3f} s ({r['seconds_total']:.1f} s) | "
            f"{_ratio(row['time_ratio'])}, {_ratio(row['time_step_ratio'])} | "
            f"{_human(f['bytes'])} ({_human(f['bytes_total'])}) | "
            f"{_human(r['bytes'])} ({_human(r['bytes_total'])}) | "
            f"{_ratio(row['bytes_ratio'])} ({_ratio(row['bytes_total_ratio'])}) | "
            f"{'; '.join(targets) or '—'} |"
        )
    return out


def result_rows(hist: History) -> list[ResultRow]:
    """bench/README.md's "Latest results" rows for this run (see run.result_rows)."""
    rows = hist.summary("fetchsync", "rsync")
    out: list[ResultRow] = []

    def verdict(row: dict[str, Any], key: str) -> str:
        return _verdict(row[key]) if key in row else ""

    for kind, what in (("commit", "real history, per commit"), ("switch", "release switches")):
        if kind not in rows:
            continue
        r = rows[kind]
        f, t = r["fetchsync"], r["rsync"]
        out.append(
            ResultRow(
                f"{what}: bytes beyond no-op",
                f"≤ {r['bytes_target']:g}x" if "bytes_target" in r else "—",
                f"{_human(f['bytes'])} ({_human(f['bytes_total'])} in all)",
                f"{_human(t['bytes'])} ({_human(t['bytes_total'])})",
                f"{_ratio(r['bytes_ratio'])} (totals {_ratio(r['bytes_total_ratio'])})",
                verdict(r, "bytes_pass"),
            )
        )
        out.append(
            ResultRow(
                f"{what}: time",
                f"≤ {r['time_target']:g}x" if "time_target" in r else "—",
                f"{f['seconds']:.3f} s",
                f"{t['seconds']:.3f} s",
                f"{_ratio(r['time_ratio'])} ({_ratio(r['time_step_ratio'])})",
                verdict(r, "time_pass"),
            )
        )
    if "initial" in rows:
        r = rows["initial"]
        f, t = r["fetchsync"], r["rsync"]
        out.append(
            ResultRow(
                "rclcpp's first push, time / bytes",
                "figure",
                f"{f['seconds']:.3f} s / {_human(f['bytes'])}",
                f"{t['seconds']:.3f} s / {_human(t['bytes'])}",
                f"{_ratio(r['time_ratio'])} / {_ratio(r['bytes_ratio'])}",
                "",
            )
        )
    return out


def render(hist: History, machine: dict[str, str], info: dict[str, Any]) -> str:
    bench = hist.bench
    out = [
        (
            f"Machine: {machine['nproc']} CPUs ({machine['cpu']}), Python {machine['python']}, "
            f"{machine['rsync']}, {machine['ssh']}, paramiko {machine['paramiko']}, {machine['fetchsync']}"
        ),
        "",
        (
            f"Repository: ros2/rclcpp from {info['bundle']}: {info['files']} files, "
            f"{info['bytes'] / 2**20:.1f} MiB at {info['start'][:10]}; {info['commits']} first-parent "
            f"commits to {info['tip'][:10]}, then switches to {', '.join(v for v, _ in info['switches'])}. "
            "Each push a new process, the tools alternating who goes first; rsync -phErtzl --delete."
        ),
        "",
        link_line(bench.link),
        "",
        bench.side.describe(bench.robot) if bench.robot else "Robot: not probed.",
        "",
        f"Load average: {machine.get('load', '?')} at the start, {load_average()} at the end.",
        "",
    ]
    out += _tables(hist.summary("fetchsync", "rsync"), "fetchsync", "rsync")
    for base in bench.tools:
        if isinstance(base, FetchsyncPush) and base.name.startswith("fetchsync@"):
            out += ["", f"A/B: this checkout against {base.name}", ""]
            out += _tables(
                hist.summary("fetchsync", base.name, targets=False), "fetchsync", base.name
            )
            out += ["", f"{base.name} against rsync", ""]
            out += _tables(hist.summary(base.name, "rsync"), base.name, "rsync")
    title = f"{bench.params.link}, history.py, {info['commits']} commits, {len(info['switches'])} switches"
    out += ["", *results_section(title, machine.get("commit", "?"), result_rows(hist))]
    out.append("")
    if hist.verified_ok():
        out.append(
            f"verification: PASS (after each of the {len(hist.steps)} steps every remote tree "
            "equals the local src/: paths, kinds, modes, symlink targets, SHA-256)"
        )
    else:
        out.append("verification: FAIL")
        for f in bench.failures:
            out.append(
                f"- {f['tool']}'s {f['scenario']} push #{f['rep']} failed: "
                + " ".join(f["error"].split())[-400:]
            )
        for st in hist.steps:
            for tool, diffs in st["verified"].items():
                if diffs:
                    out.append(
                        f"- after {st['kind']} {st['index']} ({st['label']}), {tool}: "
                        f"{len(diffs)} difference(s), e.g. " + "; ".join(diffs[:3])
                    )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="fetchsync push vs rsync on ros2/rclcpp's history.")
    ap.add_argument("--bundle", type=Path, default=BUNDLE, help=f"git bundle (default {BUNDLE})")
    ap.add_argument(
        "--commits", type=int, help="first-parent commits replayed (default 30; --quick 2)"
    )
    ap.add_argument("--switches", type=int, help="release switches (default 4; --quick 1)")
    ap.add_argument("--noops", type=int, help="no-op pushes per tool (default 3; --quick 1)")
    ap.add_argument(
        "--quick", action="store_true", help="a smoke run: 2 commits, 1 switch, 1 no-op"
    )
    ap.add_argument("--link", choices=sorted(LINKS), default="loopback", help="as run.py's")
    ap.add_argument("--baseline-rev", metavar="REV", help="as run.py's: an A/B of two fetchsyncs")
    add_robot_user_option(ap)
    ap.add_argument("--json", dest="json_out", type=Path, help="write the raw numbers here")
    ap.add_argument("--workdir", help="work here (kept) instead of in a temporary directory")
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory")
    a = ap.parse_args(argv)
    n_commits = a.commits if a.commits is not None else (2 if a.quick else 30)
    n_switches = a.switches if a.switches is not None else (1 if a.quick else 4)
    noops = a.noops or (1 if a.quick else 3)
    if not a.bundle.is_file():
        raise SystemExit(f"{a.bundle}: no such git bundle (--bundle)")

    def log(msg: str) -> None:
        print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)

    machine = machine_info()
    compile_checkout()
    with _workdir(a.workdir, a.keep) as workdir:
        ws_root = workdir / "ws"
        repo = Repo(a.bundle, workdir / "rclcpp.git", ws_root / "src" / "rclcpp")
        commits = repo.first_parent(n_commits)
        switches = switch_plan(repo.releases(), n_switches)
        repo.checkout(commits[0])
        files, size = tree_size(ws_root / "src")
        info = {
            "bundle": str(a.bundle),
            "start": commits[0],
            "tip": commits[-1],
            "commits": len(commits) - 1,
            "switches": switches,
            "files": files,
            "bytes": size,
        }
        ws = Workspace(
            root=ws_root,
            src=ws_root / "src",
            files=files,
            bytes=size,
            symlinks=0,
            big_text=ws_root / "src",  # run.py's edits are not made here
            edit_target=ws_root / "src",
            seconds=0.0,
        )
        params = Params(
            files=files,
            size_mb=size / 2**20,
            reps_small=noops,
            reps_initial=1,
            seed=0,
            cold=False,
            settle=0.0,
            link=a.link,
        )
        with contextlib.ExitStack() as stack:
            side, sshd = start_robot(
                stack, a.robot_user, workdir, keep=a.keep, log=log, fs=a.robot_fs
            )
            baseline = baseline_checkout(a.baseline_rev, workdir) if a.baseline_rev else None
            bench = Bench(
                workdir=workdir,
                ws=ws,
                sshd=sshd,
                params=params,
                log=log,
                baseline=baseline,
                side=side,
            )
            hist = History(bench, repo, log)
            try:
                hist.run(commits, switches, noops)
                report = render(hist, machine, info)
            finally:
                bench.close()
        print(report, flush=True)
        if a.json_out:
            names = [t.name for t in bench.tools if t.name != "rsync"]
            a.json_out.write_text(
                json.dumps(
                    {
                        "machine": machine,
                        "load_end": load_average(),
                        "params": dataclasses.asdict(params),
                        "repository": info,
                        "samples": [
                            dataclasses.asdict(s) | {"bytes": s.bytes} for s in bench.samples
                        ],
                        "steps": hist.steps,
                        "summary": {t: hist.summary(t, "rsync") for t in names},
                        "ab": {
                            t: hist.summary("fetchsync", t, targets=False)
                            for t in names
                            if t != "fetchsync"
                        },
                        "failures": bench.failures,
                        "robot": bench.robot,
                        "results_rows": [dataclasses.asdict(r) for r in result_rows(hist)],
                        "verified": hist.verified_ok(),
                    },
                    indent=1,
                    sort_keys=True,
                )
                + "\n"
            )
    return 0 if hist.verified_ok() else 1


if __name__ == "__main__":
    sys.exit(main())
