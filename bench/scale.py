#!/usr/bin/env python3
"""fetchsync at scale: a 100,000-file workspace, time and peak memory of each step.

    python3 bench/scale.py                          # 100,000 files, 400 MiB, over the real sshd
    python3 bench/scale.py --files 1000 --size-mb 6   # the CI smoke size (tests/test_scale_smoke.py)
    python3 bench/scale.py --robot local            # the endpoint as a local subprocess instead

One run generates a seeded ROS-like workspace (``bench/workspace.py``), starts
the test suite's real OpenSSH ``sshd`` on 127.0.0.1 (``tests/sshd.py``; the
robot is this machine; run as root, it logs in as the bench's ``fsrobot``
account, as the other benches do: ``--robot-user``, ``bench/robot.py``) and measures, each as a new process of this checkout's
fetchsync with ``FETCHSYNC_PERSIST=0`` (no connection master: every step pays
its own connection and endpoint start-up, and no process outlives its step):

1. ``fetchsync push`` into an empty remote workspace (the initial push);
2. ``fetchsync push`` again with nothing changed (the no-op push);
3. ``fetchsync watch`` on that unchanged workspace: the time from launch until
   the agent says it is live (its ``live:`` line, then confirmed by
   ``fetchsync status --json``), then one edit of a ``.cpp``, timed from the
   write until the robot's copy holds the new bytes;
4. ``fetchsync watch`` again, on an empty remote workspace with no
   last-synced state: its own first, full sync (``--no-watch-initial`` skips it).

Peak memory is the kernel's high-water mark of resident memory, ``VmHWM`` in
``/proc/PID/status``, polled every 20 ms for the fetchsync process and for the
robot-side endpoint (the ``python3`` process the robot's sshd runs for it, or
the client's child for ``--robot local``); for a push the client's figure is
also taken exactly from ``wait4()``'s ``ru_maxrss``. The agent's inotify
watches are counted from ``/proc/PID/fdinfo``.

After each step the robot's ``src/`` is compared with the local one (paths,
kinds, modes, link targets, sizes, SHA-256; ``bench/run.py``'s check).

The report (markdown) goes to stdout, progress to stderr; ``--json`` writes the
raw figures. Exit status 1 when a step failed or a tree did not verify; the
targets (watch start-up <= 10 s, peak memory <= 300 MB) are reported as
PASS/MISS and never fail the run.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
for _p in (str(BENCH), str(REPO / "tests")):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from robot import RobotSide, add_robot_user_option
from run import _workdir, differences, machine_info, snapshot, start_robot
from sshd import make_ssh_home
from workspace import Workspace, generate

STARTUP_TARGET = 10.0  # seconds, watch start-up on an unchanged workspace
MEMORY_TARGET = 300 * 10**6  # bytes of peak resident memory, each process
POLL = 0.02
STEP_TIMEOUT = 1800.0
MB = 10**6


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- /proc
def _status_kib(pid: int, field: str) -> int:
    """A ``kB`` field of /proc/PID/status (VmHWM, VmRSS), 0 if the process is gone."""
    with contextlib.suppress(OSError, ValueError, IndexError), open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return 0


def _children(pid: int) -> list[int]:
    """Direct children of ``pid`` (``/proc/PID/task/TID/children``: no walk over all of /proc)."""
    out: list[int] = []
    with contextlib.suppress(OSError):
        for tid in os.listdir(f"/proc/{pid}/task"):
            with contextlib.suppress(OSError), open(f"/proc/{pid}/task/{tid}/children") as fh:
                out += [int(x) for x in fh.read().split()]
    return out


def descendants(pid: int) -> list[int]:
    out: list[int] = []
    todo = _children(pid)
    while todo:
        p = todo.pop()
        out.append(p)
        todo += _children(p)
    return out


def _cmdline(pid: int) -> bytes:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return fh.read()
    except OSError:
        return b""


def inotify_watches(pid: int) -> int:
    """How many inotify watches ``pid`` holds (``inotify wd:`` lines of its fds' fdinfo)."""
    n = 0
    with contextlib.suppress(OSError):
        for fd in os.listdir(f"/proc/{pid}/fdinfo"):
            with contextlib.suppress(OSError), open(f"/proc/{pid}/fdinfo/{fd}") as fh:
                n += sum(1 for line in fh if line.startswith("inotify wd:"))
    return n


class Robot:
    """Where the endpoint runs and how to find its processes."""

    def __init__(self, kind: str, sshd: Any, side: RobotSide | None = None) -> None:
        self.kind = kind
        self.sshd = sshd
        self.side = side
        """The robot account's side (``--robot-user``: the sshd logs in as it), for ``ssh``."""
        self._listener: int | None = None

    def endpoint_pids(self, client: int) -> list[int]:
        """The robot-side endpoint processes serving ``client``: python under the robot's sshd
        (this benchmark runs one client at a time), or the client's python children."""
        if self.kind == "local":
            cands = descendants(client)
        else:
            cands = descendants(self._sshd_listener())
        return [p for p in cands if b"python" in _cmdline(p).split(b"\0", 1)[0]]

    def _sshd_listener(self) -> int:
        if self._listener is None:
            mark = str(self.sshd.workdir).encode()
            for p in os.listdir("/proc"):
                if p.isdigit():
                    cmd = _cmdline(int(p)).replace(b"\0", b" ")
                    if b"sshd" in cmd and b" -D " in cmd and mark in cmd:
                        self._listener = int(p)
                        break
            else:
                raise RuntimeError("cannot find the test sshd's listener process")
        return self._listener


class PeakSampler:
    """Polls VmHWM of a client process and of its robot-side endpoint(s) until stopped.

    VmHWM only grows, so the last value read before a process exits is its
    peak up to that moment (within one poll interval).
    """

    def __init__(self, client: int, robot: Robot) -> None:
        self.client = client
        self.robot = robot
        self.client_kib = 0
        self.endpoint_kib: dict[int, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        k = 0
        while not self._stop.is_set():
            self.sample(rescan=(k % 5 == 0))
            k += 1
            self._stop.wait(POLL)

    def sample(self, rescan: bool = True) -> None:
        self.client_kib = max(self.client_kib, _status_kib(self.client, "VmHWM"))
        if rescan:
            for p in self.robot.endpoint_pids(self.client):
                self.endpoint_kib.setdefault(p, 0)
        for p in list(self.endpoint_kib):
            self.endpoint_kib[p] = max(self.endpoint_kib[p], _status_kib(p, "VmHWM"))

    @property
    def endpoint_peak_kib(self) -> int:
        return max(self.endpoint_kib.values(), default=0)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


# --------------------------------------------------------------------------- the bench
class ScaleBench:
    def __init__(self, workdir: Path, ws: Workspace, robot: Robot) -> None:
        self.workdir = workdir
        self.ws = ws
        self.robot = robot
        # short, for the agent's control socket path
        self.runtime_dir = Path(tempfile.mkdtemp(prefix="fsscale-"))
        env = {
            k: v
            for k, v in os.environ.items()
            if not k.startswith(("FETCHSYNC_", "FETCH_", "XDG_"))
            and k not in ("SSH_AUTH_SOCK", "ROS_MASTER_URI")
        }
        env["XDG_RUNTIME_DIR"] = str(self.runtime_dir)
        env["XDG_STATE_HOME"] = str(workdir / "state")
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
        env["FETCHSYNC_PERSIST"] = "0"
        env["FETCHSYNC_WORKSPACE"] = str(ws.root)
        if robot.kind == "local":
            home = workdir / "robot-home"
            home.mkdir(exist_ok=True)
            env.update(
                FETCHSYNC_ROBOT="local",
                FETCHSYNC_LOCAL_ROBOT_HOME=str(home),
                FETCHSYNC_REMOTE_WORKSPACE="~/robot_ws",
            )
            self.remote_src = home / "robot_ws" / "src"
        else:
            ssh_home = make_ssh_home(workdir / "home", sshd=robot.sshd)
            assert robot.side is not None
            self.robot_dir = robot.side.mkdir(robot.side.root / "robot")  # the account's
            remote = self.robot_dir / "robot_ws"
            env.update(
                HOME=str(ssh_home.home),
                FETCHSYNC_ROBOT="robot",
                FETCHSYNC_REMOTE_WORKSPACE=str(remote),
            )
            self.remote_src = remote / "src"
        self.env = env
        self.verification: dict[str, list[str]] = {}
        self.failures: list[str] = []

    def close(self) -> None:
        shutil.rmtree(self.runtime_dir, ignore_errors=True)

    def fresh_target(self, tag: str) -> None:
        """From now on: a new, empty remote workspace and no last-synced state (a first sync)."""
        self.env["XDG_STATE_HOME"] = str(self.workdir / f"state-{tag}")
        if self.robot.kind == "local":
            self.env["FETCHSYNC_REMOTE_WORKSPACE"] = f"~/robot_ws_{tag}"
            self.remote_src = (
                Path(self.env["FETCHSYNC_LOCAL_ROBOT_HOME"]) / f"robot_ws_{tag}" / "src"
            )
        else:
            remote = self.robot_dir / f"robot_ws_{tag}"
            self.env["FETCHSYNC_REMOTE_WORKSPACE"] = str(remote)
            self.remote_src = remote / "src"

    def fetchsync(self, *args: str) -> list[str]:
        return [sys.executable, "-m", "fetchsync", *args]

    # ---------------------------------------------------------------------- push
    def push(self, label: str) -> dict[str, Any]:
        argv = self.fetchsync("push", "--json")
        out_path = self.workdir / f"{label}.out"
        os.sync()  # no writeback from the last step pending
        with open(out_path, "wb") as out:
            t0 = time.perf_counter()
            proc = subprocess.Popen(
                argv,
                env=self.env,
                cwd=self.workdir,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
            )
            sampler = PeakSampler(proc.pid, self.robot)
            try:
                # wait4 gives this child's exact ru_maxrss (KiB on Linux)
                _pid, status, usage = os.wait4(proc.pid, 0)
            finally:
                seconds = time.perf_counter() - t0
                sampler.sample()
                # the endpoint ends after the client's channel closes: its last VmHWM
                deadline = time.monotonic() + 5
                while (
                    any(_status_kib(p, "VmHWM") for p in sampler.endpoint_kib)
                    and time.monotonic() < deadline
                ):
                    sampler.sample(rescan=False)
                    time.sleep(POLL)
                sampler.stop()
        proc.returncode = os.waitstatus_to_exitcode(status)
        text = out_path.read_text(errors="replace")
        report: dict[str, Any] = {}
        for line in reversed(text.splitlines()):
            if line.startswith("{"):
                with contextlib.suppress(ValueError):
                    report = json.loads(line)
                break
        res: dict[str, Any] = {
            "seconds": seconds,
            "returncode": proc.returncode,
            # for the local robot the endpoint is a child: ru_maxrss is the larger of the two
            "client_peak_kib": usage.ru_maxrss
            if self.robot.kind != "local"
            else sampler.client_kib,
            "client_peak_polled_kib": sampler.client_kib,
            "endpoint_peak_kib": sampler.endpoint_peak_kib,
            "endpoints": len(sampler.endpoint_kib),
            "files": report.get("files"),
            "bytes_sent": report.get("bytes_sent"),
            "inner_seconds": report.get("seconds"),
        }
        log(
            f"{label}: exit {proc.returncode} in {seconds:.2f} s; client peak "
            f"{res['client_peak_kib'] * 1024 / MB:.0f} MB, endpoint peak "
            f"{res['endpoint_peak_kib'] * 1024 / MB:.0f} MB; {report.get('files')} files"
        )
        if proc.returncode != 0:
            self.failures.append(
                f"{label}: {shlex.join(argv)} exited {proc.returncode}: {text[-2000:]}"
            )
        return res

    # ---------------------------------------------------------------------- watch
    def watch(self, label: str = "watch") -> dict[str, Any]:
        logfile = self.workdir / f"{label.replace(' ', '-')}.log"
        argv = self.fetchsync("watch")
        res: dict[str, Any] = {}
        with open(logfile, "wb") as out:
            t0 = time.perf_counter()
            proc = subprocess.Popen(
                argv,
                env=self.env,
                cwd=self.workdir,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        sampler = PeakSampler(proc.pid, self.robot)
        try:
            live_at = self._wait_live(proc, logfile)
            res["startup_seconds"] = live_at - t0
            status = self.status()
            res["status_state"] = status.get("state")
            res["status_seconds"] = time.perf_counter() - t0
            sampler.sample()
            res["agent_peak_live_kib"] = sampler.client_kib
            res["agent_rss_live_kib"] = _status_kib(proc.pid, "VmRSS")
            res["endpoint_peak_live_kib"] = sampler.endpoint_peak_kib
            res["inotify_watches"] = inotify_watches(proc.pid)
            log(
                f"{label}: live after {res['startup_seconds']:.2f} s (status: {res['status_state']}); "
                f"agent peak {sampler.client_kib * 1024 / MB:.0f} MB, "
                f"{res['inotify_watches']} inotify watches"
            )
            res["edit_seconds"] = self._one_edit()
            time.sleep(0.5)  # anything the edit set off settles
            sampler.sample()
            res["agent_peak_edit_kib"] = sampler.client_kib
            res["agent_rss_edit_kib"] = _status_kib(proc.pid, "VmRSS")
            res["endpoint_peak_edit_kib"] = sampler.endpoint_peak_kib
            log(
                f"{label}: one edit on the robot after {_secs(res['edit_seconds'])}; agent peak "
                f"{sampler.client_kib * 1024 / MB:.0f} MB"
            )
            self.verify(f"{label}, after one edit")
        except Exception as exc:  # noqa: BLE001 - any failure of the step is reported, not raised
            self.failures.append(f"{label}: {exc}\n{logfile.read_text(errors='replace')[-3000:]}")
            log(f"{label} failed: {exc}")
        finally:
            sampler.stop()
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)  # our own child, by pid
                try:
                    proc.wait(15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(5)
        return res

    def _wait_live(self, proc: subprocess.Popen[bytes], logfile: Path) -> float:
        deadline = time.monotonic() + STEP_TIMEOUT
        while True:
            with open(logfile, "rb") as fh:
                if b" live: " in fh.read():
                    return time.perf_counter()
            if proc.poll() is not None:
                raise RuntimeError(f"fetchsync watch exited {proc.returncode} before it was live")
            if time.monotonic() > deadline:
                raise RuntimeError(f"fetchsync watch not live after {STEP_TIMEOUT:.0f} s")
            time.sleep(POLL)

    def status(self) -> dict[str, Any]:
        out = subprocess.run(
            self.fetchsync("status", "--json"),
            env=self.env,
            capture_output=True,
            text=True,
            check=False,
            stdin=subprocess.DEVNULL,
        )
        for line in reversed(out.stdout.splitlines()):
            if line.startswith("{"):
                return dict(json.loads(line))
        return {"state": f"? ({out.stderr.strip()[-200:]})"}

    def _one_edit(self) -> float | None:
        path = self.ws.edit_target
        data = path.read_bytes() + f"// scale bench edit {time.time_ns()}\n".encode()
        remote = self.remote_src / path.relative_to(self.ws.src)
        with open(path, "wb") as fh:
            fh.write(data)
        t0 = time.perf_counter()
        deadline = t0 + 60
        while time.perf_counter() < deadline:
            with contextlib.suppress(OSError):
                if remote.stat().st_size == len(data) and remote.read_bytes() == data:
                    return time.perf_counter() - t0
            time.sleep(0.001)
        self.failures.append(f"the edit of {path} did not reach the robot within 60 s")
        return None

    # ---------------------------------------------------------------------- verification
    def verify(self, step: str) -> None:
        t0 = time.perf_counter()
        diffs = differences(snapshot(self.ws.src), snapshot(self.remote_src))
        self.verification[step] = diffs
        log(
            f"verify after {step}: "
            + ("identical" if not diffs else f"{len(diffs)} difference(s): " + "; ".join(diffs[:3]))
            + f" ({time.perf_counter() - t0:.1f} s)"
        )


# --------------------------------------------------------------------------- report
def _mb(kib: int | None) -> str:
    return "—" if not kib else f"{kib * 1024 / MB:.0f} MB"


def _mem_verdict(*kibs: int | None) -> str:
    known = [k for k in kibs if k]
    if not known:
        return "—"
    return "**PASS**" if max(known) * 1024 <= MEMORY_TARGET else "**MISS**"


def _secs(x: float | None) -> str:
    return "—" if x is None else f"{x:.2f} s" if x >= 0.1 else f"{x * 1000:.0f} ms"


def render(res: dict[str, Any]) -> str:
    m, w = res["machine"], res["workspace"]
    ini, noop, wat = res["initial"], res["noop"], res.get("watch", {})
    start = wat.get("startup_seconds")
    start_ok = "—" if start is None else "**PASS**" if start <= STARTUP_TARGET else "**MISS**"
    out = [
        (
            f"Machine: {m['nproc']} CPUs ({m['cpu']}), Linux {m['kernel']}, Python {m['python']}, "
            f"{m['ssh']}, paramiko {m['paramiko']}, {m['fetchsync']}"
        ),
        "",
        (
            f"Workspace: {w['files']} files + {w['symlinks']} symlink in {w['dirs']} directories, "
            f"{w['bytes'] / 2**20:.0f} MiB (seed {res['params']['seed']}); robot: "
            + (
                f"the real sshd on 127.0.0.1, account {res['params'].get('robot_user', '?')}"
                if res["params"]["robot"] == "ssh"
                else "local"
            )
            + "; "
            f"each step a new process with FETCHSYNC_PERSIST=0; "
            f"fs.inotify.max_user_watches = {res['max_user_watches']}."
        ),
        "",
        "| step | time | fetchsync peak RSS | robot endpoint peak RSS | target | verdict |",
        "| --- | ---: | ---: | ---: | --- | --- |",
        (
            f"| initial push ({ini.get('files')} files) | {_secs(ini['seconds'])} | "
            f"{_mb(ini['client_peak_kib'])} | {_mb(ini['endpoint_peak_kib'])} | "
            f"memory ≤ 300 MB | {_mem_verdict(ini['client_peak_kib'], ini['endpoint_peak_kib'])} |"
        ),
        (
            f"| no-op push | {_secs(noop['seconds'])} | {_mb(noop['client_peak_kib'])} | "
            f"{_mb(noop['endpoint_peak_kib'])} | memory ≤ 300 MB | "
            f"{_mem_verdict(noop['client_peak_kib'], noop['endpoint_peak_kib'])} |"
        ),
        (
            f"| `fetchsync watch` start-up to live (unchanged workspace) | {_secs(start)} | "
            f"{_mb(wat.get('agent_peak_live_kib'))} | {_mb(wat.get('endpoint_peak_live_kib'))} | "
            f"≤ 10 s; memory ≤ 300 MB | {start_ok}; "
            f"{_mem_verdict(wat.get('agent_peak_live_kib'), wat.get('endpoint_peak_live_kib'))} |"
        ),
        (
            f"| watch: one edit, write → on the robot | {_secs(wat.get('edit_seconds'))} | "
            f"{_mb(wat.get('agent_peak_edit_kib'))} | {_mb(wat.get('endpoint_peak_edit_kib'))} | "
            f"memory ≤ 300 MB | "
            f"{_mem_verdict(wat.get('agent_peak_edit_kib'), wat.get('endpoint_peak_edit_kib'))} |"
        ),
    ]
    wi = res.get("watch_initial")
    if wi is not None:
        out.append(
            f"| `fetchsync watch` first start: empty robot, no state, initial sync to live | "
            f"{_secs(wi.get('startup_seconds'))} | {_mb(wi.get('agent_peak_live_kib'))} | "
            f"{_mb(wi.get('endpoint_peak_live_kib'))} | memory ≤ 300 MB | "
            f"{_mem_verdict(wi.get('agent_peak_live_kib'), wi.get('endpoint_peak_live_kib'))} |"
        )
    out += [
        "",
        (
            f"Peak RSS = VmHWM (MB = 10^6 bytes). The agent held {wat.get('inotify_watches', '?')} "
            f"inotify watches; its resident memory (VmRSS) was {_mb(wat.get('agent_rss_live_kib'))} "
            f"when live and {_mb(wat.get('agent_rss_edit_kib'))} after the edit. "
            f"`fetchsync status` said `{wat.get('status_state')}` "
            f"{_secs(wat.get('status_seconds'))} after launch. Inside the push processes: "
            f"initial {_secs(ini.get('inner_seconds'))}, no-op {_secs(noop.get('inner_seconds'))}."
            + (
                f" Started on an empty robot, the agent's VmRSS was {_mb(wi.get('agent_rss_live_kib'))}"
                f" when live and {_mb(wi.get('agent_rss_edit_kib'))} after an edit."
                if wi is not None
                else ""
            )
        ),
        "",
    ]
    bad = {k: v for k, v in res["verification"].items() if v}
    if bad or res["failures"]:
        out.append("verification: FAIL")
        for k, v in bad.items():
            out.append(f"- after {k}: {len(v)} difference(s), e.g. " + "; ".join(v[:3]))
        for f in res["failures"]:
            out.append(f"- {f.splitlines()[0] if f else f}")
    else:
        out.append(
            f"verification: PASS (after each of the {len(res['verification'])} steps the robot's "
            "src/ equals the local one: paths, kinds, modes, symlink targets, SHA-256)"
        )
    return "\n".join(out)


def count_dirs(root: Path) -> int:
    return sum(len(d) for _p, d, _f in os.walk(root)) + 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="fetchsync on a 100,000-file workspace: time, memory.")
    ap.add_argument("--files", type=int, default=100_000, help="workspace files (default 100000)")
    ap.add_argument("--size-mb", type=float, default=400, help="workspace MiB (default 400)")
    ap.add_argument(
        "--robot",
        choices=("ssh", "local"),
        default="ssh",
        help="the real sshd on 127.0.0.1 (default) or the local subprocess robot",
    )
    ap.add_argument(
        "--watch-initial",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also start the agent on an empty robot with no state: its first, full sync",
    )
    ap.add_argument("--seed", type=int, default=1)
    add_robot_user_option(ap)
    ap.add_argument("--json", dest="json_out", type=Path, help="write the raw figures here")
    ap.add_argument("--workdir", help="work here (kept) instead of in a temporary directory")
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory")
    a = ap.parse_args(argv)
    machine = machine_info()
    max_watches = 0
    with contextlib.suppress(OSError, ValueError):
        max_watches = int(Path("/proc/sys/fs/inotify/max_user_watches").read_text())
    res: dict[str, Any] = {
        "machine": machine,
        "params": {"files": a.files, "size_mb": a.size_mb, "robot": a.robot, "seed": a.seed},
        "max_user_watches": max_watches,
    }
    with _workdir(a.workdir, a.keep) as workdir:
        log(f"workdir: {workdir}")
        ws = generate(workdir / "ws", files=a.files, size_mb=a.size_mb, seed=a.seed)
        dirs = count_dirs(ws.src)
        res["workspace"] = {
            "files": ws.files,
            "bytes": ws.bytes,
            "symlinks": ws.symlinks,
            "dirs": dirs,
            "generate_seconds": round(ws.seconds, 2),
        }
        log(
            f"workspace: {ws.files} files in {dirs} directories, {ws.bytes / 2**20:.0f} MiB, "
            f"generated in {ws.seconds:.1f} s"
        )
        if max_watches and dirs > max_watches:
            log(
                f"warning: {dirs} directories but fs.inotify.max_user_watches = {max_watches}: "
                "the agent will run degraded (rescans)"
            )
        with contextlib.ExitStack() as stack:
            if a.robot == "ssh":
                side, sshd = start_robot(
                    stack, a.robot_user, workdir, keep=a.keep, log=log, fs=a.robot_fs
                )
                res["params"]["robot_user"] = side.user
                robot = Robot("ssh", sshd, side)
            else:
                robot = Robot("local", None)
            bench = ScaleBench(workdir, ws, robot)
            stack.callback(bench.close)
            log("initial push")
            res["initial"] = bench.push("initial")
            bench.verify("initial push")
            log("no-op push")
            res["noop"] = bench.push("noop")
            bench.verify("no-op push")
            log("fetchsync watch on the unchanged workspace")
            res["watch"] = bench.watch()
            if a.watch_initial:
                log("fetchsync watch, first start: an empty robot and no state")
                bench.fresh_target("first")
                res["watch_initial"] = bench.watch("watch from empty")
            res["verification"] = bench.verification
            res["failures"] = bench.failures
        report = render(res)
        print(report, flush=True)
        if a.json_out:
            a.json_out.write_text(json.dumps(res, indent=1, sort_keys=True, default=str) + "\n")
    ok = not res["failures"] and not any(res["verification"].values())
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
