#!/usr/bin/env python3
"""A fleet push against the slowest single robot's push: ``fetchsync push --robot @fleet``.

    python3 bench/fleet.py [--robots 20] [--files 300 --size-mb 6] [--link wifi] [--json out.json]
    python3 bench/fleet.py --robots 3 --quick --no-loopback     # the smoke test's run

A lab pushes the same workspace to a class of twenty robots. Each robot here is a
separate OpenSSH ``sshd`` on 127.0.0.1 (``tests/sshd.py``), each behind its own
link (``bench/countproxy.py --serve``, a shaper the laptop reaches over TCP as it
would a robot: shaped as ``--link``, and counting that robot's bytes), each with
its own remote workspace; the laptop's
workspace is the bench's generated tree (``bench/workspace.py``). Every push is a
new ``fetchsync`` process without a connection master (``FETCHSYNC_PERSIST=0``:
a first push of the day); the robots' endpoint cache is warm (one warm-up push).

Scenarios, each timed as single pushes (one robot at a time, each robot once)
and as one fleet push (every robot, ``-j`` robots at once):

    initial   into empty remote workspaces, with no last-synced state
    edit      one line of one .cpp changed

It reports the fleet push's time against the slowest single robot's push (the
issue's target: at most 1.5x on the shaped link), the bytes each robot received
in the fleet push against its single push, then a fleet push with two robots
down (one robot's sshd stopped: refused; one link blackholed: a robot out of
range, given up after its ConnectTimeout) and the table fetchsync printed, and
the same fleet on unshaped loopback (reported, not targeted: there every robot's
endpoint and sshd share this machine's CPUs with the laptop).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import platform
import resource
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
for _p in (str(BENCH), str(REPO / "tests")):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from countproxy import LINKS, Counter, set_link_state
from robot import RobotSide, add_robot_user_option
from run import compile_checkout, robot_python
from sshd import SSHD, running_sshd
from workspace import generate

TARGET = 1.5  # fleet push time / the slowest single robot's, at most (shaped link)
CONNECT_TIMEOUT = 10  # the ssh config's ConnectTimeout: how long a blackholed robot is tried


class Fleet:
    """N robots (sshd + link each), one laptop HOME whose ssh config names them r01..rNN."""

    def __init__(
        self, *, workdir: Path, sshds: list[SSHD], link: str, ws_root: Path, side: RobotSide
    ) -> None:
        self.workdir = workdir
        self.side = side
        self.robot_dir = side.mkdir(side.root / "robots" / link)
        self.sshds = sshds
        self.link = link
        self.ws_root = ws_root
        self.names = [f"r{i + 1:02d}" for i in range(len(sshds))]
        self.home = workdir / "home"
        ssh = self.home / ".ssh"
        ssh.mkdir(parents=True, mode=0o700, exist_ok=True)
        identity = ssh / "id_ed25519"
        if not identity.exists():
            subprocess.run(
                ["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(identity)],
                check=True,
                stdin=subprocess.DEVNULL,
            )
        pub = identity.with_suffix(".pub").read_text()
        known = ssh / "known_hosts"
        config = ssh / "config"
        hosts, blocks = [], []
        # each robot's link: a shaper serving on a port of its own, reached over TCP as a
        # robot is (not a ProxyCommand: a proxy process started per connection cost ~40 ms
        # of CPU, twenty at once, where a lab's link costs the laptop nothing)
        self.links: list[subprocess.Popen[str]] = []
        for name, sshd in zip(self.names, sshds):
            with open(sshd.workdir / "authorized_keys", "a") as fh:
                fh.write(pub)
            served = subprocess.Popen(
                [
                    sys.executable,
                    "-S",
                    str(BENCH / "countproxy.py"),
                    "--serve",
                    sshd.host,
                    str(sshd.port),
                    str(self.wire(name)),
                    link,
                ],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                text=True,
            )
            self.links.append(served)
            assert served.stdout is not None
            port = int(served.stdout.readline())
            hosts.append(f"[127.0.0.1]:{port} {sshd.host_key_pub}\n")
            blocks.append(
                f"Host {name}\n    HostName 127.0.0.1\n    Port {port}\n"
                f"    User {sshd.user}\n    IdentityFile {identity}\n    IdentitiesOnly yes\n"
                f"    UserKnownHostsFile {known}\n    GlobalKnownHostsFile /dev/null\n"
                f"    StrictHostKeyChecking yes\n    UpdateHostKeys no\n"
                f"    ConnectTimeout {CONNECT_TIMEOUT}\n"
            )
        known.write_text("".join(hosts))
        config.write_text("\n".join(blocks))
        config.chmod(0o600)
        conf = self.home / ".config/fetchsync"
        conf.mkdir(parents=True, exist_ok=True)
        (conf / "robots.toml").write_text(
            f"fleet = {json.dumps(self.names)}\n\n"
            + "".join(
                f'[robots.{n}]\nremote_workspace = "{self.remote(n)}"\n\n' for n in self.names
            )
        )
        self.state = 0
        self.trace: Path | None = None  # --trace: the fleet pushes run under fleettrace.py
        self.wrap: list[str] = []  # an interpreter + profiler the fleet pushes run under

    def close(self) -> None:
        """Stop the links' shapers (ours, by their pids)."""
        for served in self.links:
            served.terminate()
        for served in self.links:
            try:
                served.wait(timeout=5)
            except subprocess.TimeoutExpired:
                served.kill()
                served.wait()

    def wire(self, name: str) -> Path:
        return self.workdir / "wire" / self.link / name

    def remote(self, name: str) -> Path:
        return self.robot_dir / name

    def counters(self) -> dict[str, Counter]:
        return {n: Counter(self.wire(n)) for n in self.names}

    def reset(self) -> None:
        """Empty every robot's workspace and forget every last-synced state."""
        for n in self.names:
            shutil.rmtree(self.remote(n), ignore_errors=True)
            self.side.mkdir(self.remote(n))
        self.state += 1

    def env(self) -> dict[str, str]:
        env = {
            k: v
            for k, v in os.environ.items()
            if not k.startswith(("FETCHSYNC_", "FETCH_", "XDG_"))
            and k not in ("SSH_AUTH_SOCK", "ROS_MASTER_URI")
        }
        env.update(
            HOME=str(self.home),
            PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")])),
            FETCHSYNC_WORKSPACE=str(self.ws_root),
            FETCHSYNC_PERSIST="0",
            XDG_STATE_HOME=str(self.workdir / f"state-{self.state}"),
            XDG_CACHE_HOME=str(self.workdir / "laptop-cache"),
            XDG_RUNTIME_DIR=str(self.workdir / "run"),
            FETCHSYNC_REMOTE_PYTHON=robot_python(self.robot_dir / "robot-cache"),
        )
        (self.workdir / "run").mkdir(mode=0o700, exist_ok=True)
        return env

    def push(self, robots: list[str], *, jobs: int) -> dict[str, Any]:
        """One ``fetchsync push`` of ``robots``: its time, exit status, table, reports, and
        the bytes each robot's link carried."""
        counters = self.counters()
        before = {n: counters[n].read() for n in robots}
        argv = [sys.executable, "-m", "fetchsync", "push", "--json", "--robot", ",".join(robots)]
        if len(robots) > 1:
            argv += ["-j", str(jobs)]
            if self.trace is not None:  # where the fleet push's time goes, per robot
                self.trace.mkdir(parents=True, exist_ok=True)
                out = (
                    self.trace
                    / f"{self.link}-{len(list(self.trace.glob(f'{self.link}-*.json')))}.json"
                )
                argv[1:1] = [str(BENCH / "fleettrace.py"), str(out)]
            if self.wrap:
                argv[:1] = self.wrap
        links0, robots0 = self.links_cpu(robots), self.robots_cpu(robots)
        proxies0 = self.proxies_cpu(robots)
        cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
            proc = subprocess.Popen(
                argv, env=self.env(), stdout=out, stderr=err, stdin=subprocess.DEVNULL
            )
            peak_fds = peak_threads = 0
            while proc.poll() is None:  # the laptop's descriptors and threads, at their peak
                fds, threads = _usage(proc.pid)
                peak_fds, peak_threads = max(peak_fds, fds), max(peak_threads, threads)
                time.sleep(0.05)
            seconds = time.perf_counter() - t0
            out.seek(0)
            err.seek(0)
            stdout, stderr = out.read().decode(), err.read().decode()
        wire = {}
        for n in robots:
            after = counters[n].settle(quiet=0.2, timeout=15)
            wire[n] = after.up + after.down - before[n].up - before[n].down
        keep = {p.pid for p in self.links} | {
            pid for pid in (_listener(sshd) for sshd in self.sshds) if pid
        }
        orphans = _reap_orphans(keep=keep, robot_uid=self.side.uid)  # robots' endpoints
        cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
        links = self.links_cpu(robots) - links0
        proxies = self.proxies_cpu(robots) - proxies0  # a ProxyCommand's: the push's children
        robots_cpu = self.robots_cpu(robots, settle=True) - robots0 + orphans
        reports: list[dict[str, Any]] = []
        for line in reversed(stdout.splitlines()):
            if line.startswith(("[", "{")):
                data = json.loads(line)
                reports = data if isinstance(data, list) else [data]
                break
        table = [ln for ln in stderr.splitlines() if not ln.startswith("[")]
        return {
            "seconds": seconds,
            "exit": proc.returncode,
            "bytes": wire,
            "reports": reports,
            "table": table,
            "stderr": stderr[-4000:],
            # the push process and what it ran, but the links and the robots' orphans
            "cpu": cpu - proxies - orphans,
            "cpu_links": links,
            "cpu_robots": robots_cpu,
            "fds": peak_fds,
            "threads": peak_threads,
        }

    def links_cpu(self, robots: list[str]) -> float:
        """CPU seconds the links (countproxy.py shapers) of ``robots`` have used, in all."""
        return self.proxies_cpu(robots) + sum(
            _cpu_with_reaped(self.links[self.names.index(n)].pid) for n in robots
        )

    def proxies_cpu(self, robots: list[str]) -> float:
        """CPU seconds of the stopped per-connection proxies of ``robots`` (none since the
        links serve: kept for a ProxyCommand in a user's ssh config)."""
        return sum(Counter(self.wire(n)).cpu() for n in robots)

    def robots_cpu(self, robots: list[str], *, settle: bool = False) -> float:
        """CPU seconds of the robots' sshds: each listener with the sessions it reaped (a
        session's sshd, the endpoint it ran). ``settle``: first wait (at most 5 s) until
        no session is left, so a push's have all been counted."""
        listeners = [_listener(self.sshds[self.names.index(n)]) for n in robots]
        deadline = time.monotonic() + 5
        while settle and time.monotonic() < deadline:
            if not any(_children(p) for p in listeners if p):
                break
            time.sleep(0.05)
        return sum(_cpu_with_reaped(p) for p in listeners if p)


def _listener(sshd: SSHD) -> int | None:
    try:
        return int((sshd.workdir / "sshd.pid").read_text())
    except (OSError, ValueError):
        return None


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(x) for x in text.split()]


CLK_TCK = os.sysconf("SC_CLK_TCK")


def _cpu_with_reaped(pid: int) -> float:
    """utime + stime of ``pid`` and of the children it has reaped (cutime + cstime)."""
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return sum(int(x) for x in f[11:15]) / CLK_TCK


def _become_subreaper() -> None:
    """Orphans of our children (a robot's endpoint that outlived its sshd session) become
    ours, so their CPU time is ours to collect (:func:`_reap_orphans`) and counted, not
    init's."""
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER


def _reap_orphans(*, keep: set[int], robot_uid: int, wait: float = 3.0) -> float:
    """Reap the processes handed to us (we are a subreaper), and the CPU they used.

    A robot's endpoint can outlive its sshd session by a moment (the session's sshd ends
    when the link closes and does not wait for it): it is then ours, and its CPU is not
    in its sshd's count. Exited ones are reaped at once; the robot account's that still
    run (not ``keep``: our sshds and links) are waited for, ``wait`` seconds at most."""
    total = 0.0
    deadline = time.monotonic() + wait
    while True:
        running = []
        for pid in _children(os.getpid()):
            if pid in keep:
                continue
            try:
                status = Path(f"/proc/{pid}/status").read_text()
            except OSError:
                continue
            zombie = "\nState:\tZ" in status
            uid = int(status.split("\nUid:")[1].split()[0])
            if zombie:
                try:
                    _pid, _status, usage = os.wait4(pid, os.WNOHANG)
                except ChildProcessError:
                    continue
                if _pid:
                    total += usage.ru_utime + usage.ru_stime
            elif uid == robot_uid:
                running.append(pid)
        if not running or time.monotonic() > deadline:
            return total
        time.sleep(0.02)


def _usage(pid: int) -> tuple[int, int]:
    """Open descriptors and threads of process ``pid`` (0, 0 once it is gone)."""
    try:
        fds = len(os.listdir(f"/proc/{pid}/fd"))
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0, 0
    threads = next(
        (int(ln.split()[1]) for ln in status.splitlines() if ln.startswith("Threads:")), 0
    )
    return fds, threads


def _check(result: dict[str, Any], what: str) -> None:
    if result["exit"] != 0:
        raise SystemExit(f"{what} failed (exit {result['exit']}):\n{result['stderr']}")


def scenario(
    fleet: Fleet, name: str, *, jobs: int, edit: Path, log: Any, singles: int
) -> dict[str, Any]:
    """Single pushes of the first ``singles`` robots (every one by default), then one
    fleet push, from the same starting point."""
    out: dict[str, Any] = {"scenario": name}
    for label in ("single", "fleet"):
        if name == "initial":
            fleet.reset()
        else:
            with open(edit, "a") as fh:  # one line more, on every robot
                fh.write(f"// {label} {time.monotonic_ns()}\n")
        if label == "single":
            times, wire, cpu, fds, threads = {}, {}, {}, {}, {}
            links, robots = {}, {}
            for n in fleet.names[:singles]:
                r = fleet.push([n], jobs=1)
                _check(r, f"{name}: push to {n}")
                times[n], wire[n], cpu[n] = r["seconds"], r["bytes"][n], r["cpu"]
                fds[n], threads[n] = r["fds"], r["threads"]
                links[n], robots[n] = r["cpu_links"], r["cpu_robots"]
            out["single"] = {
                "seconds": times,
                "bytes": wire,
                "cpu": cpu,
                "cpu_links": links,
                "cpu_robots": robots,
                "fds": max(fds.values()),
                "threads": max(threads.values()),
            }
            slowest = max(times, key=lambda k: times[k])
            log(
                f"{name:8} single: slowest {slowest} {times[slowest]:.2f}s, median "
                f"{statistics.median(times.values()):.2f}s, sum {sum(times.values()):.1f}s"
            )
        else:
            r = fleet.push(fleet.names, jobs=jobs)
            _check(r, f"{name}: fleet push")
            out["fleet"] = {
                k: r[k]
                for k in (
                    "seconds",
                    "bytes",
                    "table",
                    "cpu",
                    "cpu_links",
                    "cpu_robots",
                    "fds",
                    "threads",
                )
            }
            log(f"{name:8} fleet:  {r['seconds']:.2f}s for {len(fleet.names)} robots")
    single = out["single"]
    out["ratio"] = out["fleet"]["seconds"] / max(single["seconds"].values())
    out["bytes_ratio"] = {
        n: out["fleet"]["bytes"][n] / single["bytes"][n]
        for n in single["bytes"]
        if single["bytes"][n]
    }
    return out


def two_down(fleet: Fleet, sshds: list[SSHD], *, jobs: int, edit: Path) -> dict[str, Any]:
    """A fleet push (after an edit) with robot 1's sshd stopped and robot 2's link blackholed."""
    stopped, dark = fleet.names[0], fleet.names[1]
    pid = int((sshds[0].workdir / "sshd.pid").read_text())
    os.kill(pid, signal.SIGTERM)  # our own sshd, by its pid
    set_link_state(fleet.wire(dark), "blackhole")
    try:
        with open(edit, "a") as fh:
            fh.write(f"// two down {time.monotonic_ns()}\n")
        r = fleet.push(fleet.names, jobs=jobs)
    finally:
        set_link_state(fleet.wire(dark), "up")
    ok = [rep["robot"] for rep in r["reports"] if rep.get("ok")]
    failed = {rep["robot"]: rep.get("error", "") for rep in r["reports"] if not rep.get("ok")}
    return {
        "seconds": r["seconds"],
        "exit": r["exit"],
        "ok": ok,
        "failed": failed,
        "down": {stopped: "sshd stopped", dark: "link blackholed"},
        "table": r["table"],
    }


def machine() -> dict[str, Any]:
    return {
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "kernel": platform.release(),
        "load": os.getloadavg()[0],
    }


def report(data: dict[str, Any]) -> str:
    p = data["params"]
    lines = [
        f"Fleet push: {p['robots']} robots (one sshd and one {p['link']} link each), "
        f"-j {p['jobs']}, a workspace of {data['workspace']['files']} files, "
        f"{data['workspace']['bytes'] / 2**20:.1f} MiB; {data['machine']['cpus']} CPUs, "
        f"load {data['machine']['load']:.1f} at the start; the robots log in as "
        f"{data.get('robot_user', '?')}, their trees on "
        f"{p.get('robot_root', 'home')}.",
        "",
        "| scenario | link | slowest single push | median single | sum of singles | fleet push "
        "| fleet / slowest | target | bytes per robot, fleet / single (min-max) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for s in data["scenarios"]:
        times = s["single"]["seconds"].values()
        br = s["bytes_ratio"].values()
        shaped = s["link"] != "loopback"
        verdict = ("PASS" if s["ratio"] <= TARGET else "MISS") if shaped else "(reported)"
        lines.append(
            f"| {s['scenario']} | {s['link']} | {max(times):.2f} s | "
            f"{statistics.median(times):.2f} s | {sum(times):.1f} s | {s['fleet']['seconds']:.2f} s "
            f"| {s['ratio']:.2f}x | {'<= ' + str(TARGET) + 'x ' if shaped else ''}{verdict} | "
            f"{min(br):.2f}-{max(br):.2f} |"
        )
    lines += [
        "",
        (
            "Who used the CPUs (user+sys seconds; the laptop: the push process and what it ran, "
            "the links apart; the links: the bench's shapers, `countproxy.py --serve`, one per "
            "robot, their CPU in /proc; the robots: each robot's sshd with the sessions and "
            "endpoints it ran, which a lab runs on the robots, not here), and the push's wall "
            "time times the CPUs: what this machine had. Peak descriptors and threads of the "
            "push process:"
        ),
        "",
        "| scenario | link | push | wall x CPUs | laptop | links (bench) | robots | fds | threads |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    cpus = data["machine"]["cpus"] or 1
    for s in data["scenarios"]:
        single, fl = s["single"], s["fleet"]
        k = statistics.median_low(single["seconds"].values())
        one = next(n for n, v in single["seconds"].items() if v == k)  # the median single push
        for label, wall, lap, lnk, rob, fds, thr in (
            (
                f"single ({one}, the median)",
                single["seconds"][one],
                single["cpu"][one],
                single.get("cpu_links", {}).get(one),
                single.get("cpu_robots", {}).get(one),
                single["fds"],
                single["threads"],
            ),
            (
                f"fleet of {len(fl['bytes'])}",
                fl["seconds"],
                fl["cpu"],
                fl.get("cpu_links"),
                fl.get("cpu_robots"),
                fl["fds"],
                fl["threads"],
            ),
        ):
            avail = wall * cpus

            def share(x: float | None, avail: float = avail) -> str:
                return "—" if x is None else f"{x:.2f} s ({100 * x / avail:.0f}%)"

            lines.append(
                f"| {s['scenario']} | {s['link']} | {label} | {avail:.1f} s | {share(lap)} | "
                f"{share(lnk)} | {share(rob)} | {fds} | {thr} |"
            )
    lines += [
        "",
        "The CPU floor: what the fleet push's processes used over the CPUs, the least wall "
        "time this machine allows before any waiting, against the slowest single push; and "
        "the laptop's share alone (in a lab the links and the robots' side are elsewhere):",
        "",
        "| scenario | link | CPU-s (laptop + links + robots) | floor on "
        f"{cpus} CPUs | floor / slowest single | laptop alone / slowest single "
        "| laptop CPU per further robot |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for s in data["scenarios"]:
        fl, single = s["fleet"], s["single"]
        total = fl["cpu"] + fl.get("cpu_links", 0.0) + fl.get("cpu_robots", 0.0)
        slowest = max(single["seconds"].values())
        one = statistics.median(single["cpu"].values())
        extra = (fl["cpu"] - one) / max(1, len(fl["bytes"]) - 1)
        lines.append(
            f"| {s['scenario']} | {s['link']} | {total:.2f} s | {total / cpus:.2f} s | "
            f"{total / cpus / slowest:.2f}x | {fl['cpu'] / slowest:.2f}x | {extra * 1000:.0f} ms |"
        )
    d = data.get("two_down")
    if d:
        lines += [
            "",
            f"Two robots down ({', '.join(f'{k}: {v}' for k, v in d['down'].items())}): "
            f"{len(d['ok'])} of {len(d['ok']) + len(d['failed'])} succeeded in "
            f"{d['seconds']:.1f} s, exit status {d['exit']}; the table's failed rows:",
            "",
            "```",
            *[ln for ln in d["table"] if ln.startswith(("robot ", *d["failed"], "push:"))],
            "```",
        ]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--robots", type=int, default=20)
    ap.add_argument("--jobs", type=int, help="robots at once in the fleet push (default: all)")
    ap.add_argument("--files", type=int, default=300)
    ap.add_argument("--size-mb", type=float, default=6.0)
    ap.add_argument("--link", choices=[k for k in LINKS if k != "loopback"], default="wifi")
    ap.add_argument("--no-loopback", action="store_true", help="skip the unshaped fleet figure")
    ap.add_argument("--no-down", action="store_true", help="skip the two-robots-down push")
    ap.add_argument("--quick", action="store_true", help="the initial push only (a smoke test)")
    ap.add_argument(
        "--scenarios",
        default="initial,edit",
        help="comma-separated, of initial and edit (default both; --quick: initial)",
    )
    ap.add_argument(
        "--singles",
        type=int,
        help="robots pushed one at a time for the single figures (default: all; the "
        "robots are alike, so a few give the slowest single push within noise)",
    )
    add_robot_user_option(ap)
    ap.add_argument(
        "--robot-root",
        type=Path,
        help="where the robots' side (trees, sshd dirs) goes, e.g. /dev/shm: a tmpfs, whose "
        "syncfs waits for nothing; on the default (the robot account's home, this VM's one "
        "disk) every robot's batch ends in a syncfs of the same file system, which waits for "
        "the other robots' writes too, where a lab's robots each have a disk (12 robots on "
        "wifi: fleet push ~6 s on the shared disk vs ~5 s on /dev/shm, singles alike)",
    )
    ap.add_argument(
        "--trace",
        type=Path,
        metavar="DIR",
        help="run each fleet push under bench/fleettrace.py (timing wrappers, each "
        "function's CPU per thread, the phases per robot) and keep its LINK-N.json and "
        "LINK-N.txt summary in DIR; the tracing costs the push some CPU",
    )
    ap.add_argument("--json", dest="json_out", type=Path, help="write the raw numbers here")
    ap.add_argument("--workdir", help="work here (kept) instead of in a temporary directory")
    args = ap.parse_args()
    compile_checkout()  # as pip install does: each push's start pays no compiling
    if args.robots < 3:
        ap.error("--robots: at least 3 (two are taken down)")
    jobs = args.jobs or args.robots
    scenarios = ["initial"] if args.quick else [x for x in args.scenarios.split(",") if x]
    if not scenarios or set(scenarios) - {"initial", "edit"}:
        ap.error("--scenarios: initial and/or edit")
    singles = min(args.singles or args.robots, args.robots)
    _become_subreaper()
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="fsbench-fleet-")).resolve()
    workdir.mkdir(parents=True, exist_ok=True)

    def log(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    ws = generate(workdir / "ws", files=args.files, size_mb=args.size_mb)
    data: dict[str, Any] = {
        "params": {
            "robots": args.robots,
            "jobs": jobs,
            "link": args.link,
            "files": args.files,
            "size_mb": args.size_mb,
            "scenarios": scenarios,
            "singles": singles,
            "robot_root": str(args.robot_root or "home"),
        },
        "workspace": {"files": ws.files, "bytes": ws.bytes},
        "machine": machine(),
        "scenarios": [],
    }
    # a SIGTERM unwinds like Ctrl-C: the 20 sshds (in sessions of their own) are stopped
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    with contextlib.ExitStack() as stack:
        side = RobotSide.make(args.robot_user, workdir, parent=args.robot_root)
        stack.callback(side.close)
        log(f"robots: account {side.user}, their side in {side.root}")
        sshds = []
        for i in range(args.robots):
            sshd = stack.enter_context(running_sshd(side.sshd_dir(f"sshd-{i:02d}")))
            side.opened(sshd.workdir)
            sshds.append(dataclasses.replace(sshd, user=side.user))
        data["robot_user"] = side.user
        log(f"{len(sshds)} sshds up; workspace {ws.files} files, {ws.bytes / 2**20:.1f} MiB")
        links = [args.link] + ([] if args.no_loopback else ["loopback"])
        fleets = {}
        for link in links:
            fleet = fleets[link] = Fleet(
                workdir=workdir / link, sshds=sshds, link=link, ws_root=ws.root, side=side
            )
            stack.callback(fleet.close)
            fleet.trace = args.trace.resolve() if args.trace else None
            fleet.reset()
            _check(fleet.push(fleet.names[:1], jobs=1), "warm-up push")  # the endpoint cache
            for name in scenarios:
                s = scenario(fleet, name, jobs=jobs, edit=ws.edit_target, log=log, singles=singles)
                s["link"] = link
                data["scenarios"].append(s)
        if not args.no_down:  # last: it stops a robot's sshd
            d = data["two_down"] = two_down(
                fleets[args.link], sshds, jobs=jobs, edit=ws.edit_target
            )
            log(f"two down: {len(d['ok'])} ok, failed {d['failed']}")
    text = report(data)
    print(text)
    if args.json_out:
        args.json_out.write_text(json.dumps(data, indent=1, sort_keys=True))
    if not args.workdir:
        shutil.rmtree(workdir, ignore_errors=True)
    d = data.get("two_down")
    if d and (len(d["failed"]) != 2 or len(d["ok"]) != args.robots - 2):
        log("two robots down: expected exactly those two to fail")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
