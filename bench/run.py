#!/usr/bin/env python3
"""fetchsync push vs rsync, side by side over the same sshd, as ratios.

    python3 bench/run.py [--files 7000 --size-mb 150] [--quick] [--json out.json]

One run generates a seeded ROS-like workspace (``bench/workspace.py``), starts
the test suite's real OpenSSH ``sshd`` on 127.0.0.1 (``tests/sshd.py``; the
robot is this machine) and runs every scenario for both tools, each push a new
process, interleaved and repeated:

    initial   push into an empty remote directory
    no-op     nothing changed
    one edit  one line of one .cpp changed
    insert    one line inserted at the top of a 2 MiB text file
    rename    that 2 MiB file renamed

Both tools reach the robot through the same ``ProxyCommand``
(``bench/countproxy.py``), which counts the bytes on the wire. rsync runs with
fetch_tools' flags plus ``-l`` (``-phErtzl --delete``) into its own remote
directory. After each scenario both remote trees are compared with the local
one (paths, kinds, permission bits, link targets, SHA-256 of contents); a
difference fails the run.

The report is markdown: machine info, then time and bytes tables with the
ratio fetchsync/rsync and each target marked PASS or MISS. ``--json`` writes
the raw samples. ``--profile`` adds where a no-op ``fetchsync push`` spends
its time (``-X importtime`` and cProfile).

lsyncd belongs to the watch agent's comparison (``fetchsync watch``):
``bench/watch.py``, which reuses this module's verification.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import hashlib
import json
import os
import platform
import pstats
import re
import shlex
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Iterator

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
for _p in (str(BENCH), str(REPO / "tests")):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from countproxy import LINKS, Counter, Link, proxy_command
from robot import (
    RobotSide,
    add_robot_user_option,
    default_robot_user,
    ensure_account,
    loop_disk,
)
from sshd import SSHD, make_ssh_home, running_sshd
from workspace import Workspace, generate

ALIAS = "robot-counted"
RSYNC_FLAGS = "-phErtzl"  # fetch_tools' -phErtz plus -l: symlinks as symlinks
KiB = 1024


def fetchsync_python() -> str:
    """The interpreter the bench runs fetchsync with: by default a venv of this one that
    holds nothing but a path line to this one's site-packages (fetchsync's dependencies),
    as ``pip install fetchsync`` in a venv gives a user; ``FETCHSYNC_BENCH_PYTHON=base``
    runs this interpreter itself, any other value names an interpreter.

    Why not this one: this machine's base interpreter runs four ``.pth`` files at every
    start that a user's laptop does not have (the sandbox's CA injection importing
    certifi, a coverage hook, setuptools' distutils shim, the editable install's
    finder): ``python3 -c pass`` takes 0.06-0.07 s here against 0.01-0.02 s in the venv,
    and a one-shot push pays it once per call (the figures before 27 Nov 2026 include
    it). A path line in a ``.pth`` only extends ``sys.path``: the ``.pth`` files in that
    directory are not run. fetchsync itself comes from ``PYTHONPATH`` as before."""
    choice = os.environ.get("FETCHSYNC_BENCH_PYTHON", "venv")
    if choice == "base":
        return sys.executable
    if choice != "venv":
        return choice
    import sysconfig

    purelib = sysconfig.get_paths()["purelib"]
    platlib = sysconfig.get_paths()["platlib"]
    import zlib

    key = f"{sys.version_info[0]}.{sys.version_info[1]}-{zlib.crc32(sys.executable.encode()):08x}"
    root = Path(tempfile.gettempdir()) / f"fetchsync-bench-python-{os.getuid()}" / key
    exe = root / "bin" / "python3"
    if exe.exists():
        return str(exe)
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=root.parent))
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", "--clear", str(tmp)], check=True)
    site = subprocess.run(
        [
            str(tmp / "bin" / "python3"),
            "-c",
            "import sysconfig; print(sysconfig.get_paths()['purelib'])",
        ],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    lines = dict.fromkeys([purelib, platlib])
    (Path(site) / "_fetchsync_bench_deps.pth").write_text("".join(f"{p}\n" for p in lines))
    try:
        tmp.rename(root)
    except OSError:  # another bench made it meanwhile
        shutil.rmtree(tmp, ignore_errors=True)
    return str(exe)


# (scenario, title) in the order they run; each leaves the tree the next starts from.
SCENARIOS = (
    ("initial", "initial push (empty remote)"),
    ("noop", "no-op push"),
    ("edit", "one small edit (.cpp)"),
    ("insert", "insert a line at the top of a 2 MiB file"),
    ("rename", "rename the 2 MiB file"),
)
# Creating a file costs ext4 without a journal (as on the machine these numbers are from)
# a scan past every inode of its block group freed in the last minute, or the last
# six while that inode table is dirty (ialloc.c, recently_deleted): after a run's
# trees are deleted, creating files near them measured 10-25x slower for minutes,
# for both tools alike, and rounds then swung between 1.2 s and 3.5 s a push.
CREATE_PROBE = (300, 30)  # directories, files in each: spread over block groups as a push's tree is
CREATE_SLOW = 4.0  # times tmpfs's time an inode: too slow to measure in (healthy: 1.8-2.5x)
CREATE_WAIT = 420.0  # seconds at most to wait for it to pass
CREATE_POLL = 30.0

# Time targets: fetchsync/rsync wall-time ratio at most this.
TIME_TARGETS_BY_LINK: dict[str, dict[str, float]] = {
    "loopback": {"initial": 1.0, "noop": 0.5, "edit": 0.5},
    "wifi": {"initial": 0.8, "edit": 0.25, "insert": 0.5},  # issue 24's targets where robots live
    "weak": {},  # figures only
}
TIME_TARGETS = TIME_TARGETS_BY_LINK["loopback"]
# Bytes on the wire, fetchsync/rsync, at most this (wifi: the initial push sends no more than rsync).
BYTES_RATIO_TARGETS_BY_LINK: dict[str, dict[str, float]] = {"wifi": {"initial": 1.0}}
# Byte targets: fetchsync's bytes on the wire beyond a no-op push, at most this.
BYTE_TARGETS = {"insert": 2 * KiB, "rename": 4 * KiB}

# The watch agent (``fetchsync watch``) is compared with lsyncd (rsync over ssh
# on inotify events) in bench/watch.py: latency from a save to the file on the
# robot, a burst of new files, CPU and memory while idle. The tools it runs:
WATCH_TOOLS: tuple[str, ...] = ("fetchsync watch", "lsyncd")


# --------------------------------------------------------------------------- samples
@dataclasses.dataclass
class Sample:
    tool: str
    scenario: str
    rep: int
    seconds: float
    up: int
    down: int
    connections: int
    report: dict[str, Any] | None = None
    """fetchsync's own ``--json`` report (files, deltas, reused, bytes_sent, seconds, ...)."""

    @property
    def bytes(self) -> int:
        return self.up + self.down


class PushFailed(RuntimeError):
    pass


def _cpu_ticks(pids: list[int]) -> int:
    """utime+stime (and waited-for children's) of these processes, in clock ticks."""
    total = 0
    for pid in pids:
        with contextlib.suppress(OSError, IndexError, ValueError):
            f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += int(f[11]) + int(f[12]) + int(f[13]) + int(f[14])
    return total


def own_processes(marks: list[bytes]) -> list[int]:
    """Processes whose command line holds one of ``marks`` (this run's directories), and
    their descendants: the connection masters, the byte counters, the robot's sshd and
    what it runs for each connection (the endpoints)."""
    kids: dict[int, list[int]] = {}
    roots = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        with contextlib.suppress(OSError, IndexError, ValueError):
            ppid = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
            kids.setdefault(ppid, []).append(int(proc.name))
            cmdline = (proc / "cmdline").read_bytes()
            if any(m in cmdline for m in marks):
                roots.append(int(proc.name))
    out, todo = set(), roots
    while todo:
        pid = todo.pop()
        if pid not in out:
            out.add(pid)
            todo += kids.get(pid, [])
    return sorted(out)


def wait_quiet(
    marks: list[bytes], *, busy: float = 0.05, window: float = 0.3, timeout: float = 5.0
) -> None:
    """Wait until this run's own processes (see :func:`own_processes`) used at most
    ``busy`` of one CPU over ``window`` seconds.

    A tool's background work after it returned (a connection master's spare
    endpoints preparing the next call, the robot finishing its writes) must not
    be timed as the next tool's. The machine as a whole is not waited for: it is
    shared, and rarely quiet; its load average is in the report instead.
    """
    tck = os.sysconf("SC_CLK_TCK")
    deadline = time.monotonic() + timeout
    pids = own_processes(marks)
    before = _cpu_ticks(pids)
    while time.monotonic() < deadline:
        time.sleep(window)
        after_pids = own_processes(marks)
        after = _cpu_ticks([p for p in after_pids if p in pids])
        if after_pids == pids and (after - before) / tck <= busy * window:
            return
        pids, before = after_pids, _cpu_ticks(after_pids)


def robot_python(cache: Path) -> str:
    """The robot's Python for a fetchsync of this run, with a cache of its own there.

    The robot's account is shared by every run (and, for root, with every test
    suite running here, some of which damage its cache on purpose) and, in an A/B
    run, by the other version: its own cache makes each run's first push ship the
    endpoint as to a new robot. ``env`` costs the robot one exec a connection."""
    return shlex.join(["env", f"XDG_CACHE_HOME={cache}", "python3"])


# --------------------------------------------------------------------------- the tools
class Tool:
    """One push tool: a command run as a new process per push, and its remote tree."""

    name = ""

    def __init__(self, *, bench: Bench, remote: Path) -> None:
        self.bench = bench
        self.remote = remote

    @property
    def remote_src(self) -> Path:
        raise NotImplementedError

    def reset(self) -> None:
        """Empty the remote directory (and any local memory of it).

        The old tree is moved aside and deleted when the run ends: ext4 makes
        creating files slow for a while after thousands were deleted (its inode
        allocator skips recently freed inodes), which would slow the next push
        down for a reason no user's initial push meets.
        """
        if self.remote.exists():
            self.bench.graveyard.mkdir(exist_ok=True)
            self.remote.rename(self.bench.graveyard / f"{self.name}-{time.monotonic_ns()}")
        self.bench.side.mkdir(self.remote)  # the robot account's, as on a robot

    def command(self) -> tuple[list[str], dict[str, str]]:
        raise NotImplementedError

    def parse(self, stdout: str) -> dict[str, Any] | None:
        return None

    def push(self, scenario: str, rep: int) -> Sample:
        argv, env = self.command()
        counter = self.bench.counter
        os.sync()  # start each push with no writeback pending from the last one
        # nor CPU still taken by the last one's background work (a master's spares)
        wait_quiet(self.bench.marks())
        before = counter.read()
        t0 = time.perf_counter()
        proc = subprocess.run(
            argv,
            env=env,
            cwd=self.bench.workdir,
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            check=False,
        )
        seconds = time.perf_counter() - t0
        if proc.returncode != 0:
            raise PushFailed(
                f"{self.name} {scenario} #{rep} exited {proc.returncode}:\n"
                f"{shlex.join(argv)}\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
            )
        # bytes a push causes after it returns (a connection master's handshake,
        # its next warm endpoint, channel closes) are counted to it too: once this
        # run's processes are idle (a master spawned as the push closes takes longer
        # to start and connect than the counters' quiet window) and the counters quiet
        wait_quiet(self.bench.marks())
        after = counter.settle()
        return Sample(
            self.name,
            scenario,
            rep,
            seconds,
            after.up - before.up,
            after.down - before.down,
            len(after.per_conn) - len(before.per_conn),
            self.parse(proc.stdout),
        )


class FetchsyncPush(Tool):
    """``fetchsync push``; with ``persist`` (its default) a connection master outlives each call.

    ``checkout``: the source tree of the fetchsync that runs (``PYTHONPATH``),
    this one by default; the baseline of an A/B run is another (``--baseline-rev``).
    Each has its own runtime directory (so its own connection master), state and
    cache.
    """

    def __init__(
        self,
        *,
        bench: Bench,
        remote: Path,
        persist: bool = True,
        checkout: Path = REPO,
        name: str | None = None,
        runtime: str | None = None,
    ) -> None:
        super().__init__(bench=bench, remote=remote)
        self.persist = persist
        self.checkout = checkout
        self.runtime = runtime  # a subdirectory of the run's: its own connection master
        self.name = name or ("fetchsync" if persist else "fetchsync-cold")
        self.resets = 0

    @property
    def remote_src(self) -> Path:
        return self.remote / "src"

    @property
    def state_home(self) -> Path:
        return self.bench.workdir / f"{self.name}-state-{self.resets}"

    def reset(self) -> None:
        super().reset()
        self.resets += 1  # a fresh XDG_STATE_HOME: no memory of the last sync
        if self.persist:
            # and no connection left open: a first push (only its own master: another
            # fetchsync's, made by its initial push this round, must live on)
            self.bench.stop_masters(self.runtime)

    def command(self) -> tuple[list[str], dict[str, str]]:
        env = self.bench.base_env()
        env.update(
            FETCHSYNC_ROBOT=ALIAS,
            FETCHSYNC_WORKSPACE=str(self.bench.ws.root),
            FETCHSYNC_REMOTE_WORKSPACE=str(self.remote),
            XDG_STATE_HOME=str(self.state_home),
            XDG_CACHE_HOME=str(self.bench.workdir / f"{self.name}-cache"),
            PYTHONPATH=str(self.checkout),
            FETCHSYNC_REMOTE_PYTHON=robot_python(self.bench.robot_dir / f"{self.name}-cache"),
        )
        if self.runtime:
            # it must exist: fetchsync makes only its own fetchsync/ in it, and without a
            # private place for the master's socket every push goes direct (no master)
            runtime = self.bench.runtime_dir / self.runtime
            runtime.mkdir(mode=0o700, exist_ok=True)
            env["XDG_RUNTIME_DIR"] = str(runtime)
        if not self.persist:
            env["FETCHSYNC_PERSIST"] = "0"
        return [fetchsync_python(), "-m", "fetchsync", "push", "--json"], env

    def parse(self, stdout: str) -> dict[str, Any] | None:
        for line in reversed(stdout.splitlines()):
            if line.startswith("{"):
                return dict(json.loads(line))
        return None


class RsyncPush(Tool):
    name = "rsync"

    @property
    def remote_src(self) -> Path:
        return self.remote / "src"

    def command(self) -> tuple[list[str], dict[str, str]]:
        ssh = f"ssh -F {shlex.quote(str(self.bench.ssh_config))} -o BatchMode=yes"
        argv = [
            "rsync",
            RSYNC_FLAGS,
            "--delete",
            "-e",
            ssh,
            str(self.bench.ws.src),
            f"{ALIAS}:{self.remote}/",
        ]
        return argv, self.bench.base_env()


# --------------------------------------------------------------------------- verification
def snapshot(root: Path) -> dict[str, tuple[Any, ...]]:
    """Every path under ``root``: kind, permission bits, link target or size and SHA-256."""
    out: dict[str, tuple[Any, ...]] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            full = os.path.join(dirpath, name)
            rel = os.path.relpath(full, root)
            st = os.lstat(full)
            mode = st.st_mode & 0o7777
            if os.path.islink(full):
                out[rel] = ("l", os.readlink(full))
            elif os.path.isdir(full):
                out[rel] = ("d", mode)
            else:
                h = hashlib.sha256()
                with open(full, "rb") as fh:
                    while chunk := fh.read(1 << 20):
                        h.update(chunk)
                digest = h.hexdigest()
                out[rel] = ("f", mode, st.st_size, digest)
    return out


def differences(local: dict[str, tuple[Any, ...]], remote: dict[str, tuple[Any, ...]]) -> list[str]:
    diffs = [f"missing on the robot: {p}" for p in sorted(local.keys() - remote.keys())]
    diffs += [f"extra on the robot: {p}" for p in sorted(remote.keys() - local.keys())]
    for p in sorted(local.keys() & remote.keys()):
        a, b = local[p], remote[p]
        if a != b:
            if a[0] == b[0] == "d":
                diffs.append(f"mode of {p}/: {a[1]:o} here, {b[1]:o} on the robot")
            elif a[0] == b[0] == "f" and a[2:] == b[2:]:
                diffs.append(f"mode of {p}: {a[1]:o} here, {b[1]:o} on the robot")
            else:
                diffs.append(f"differs: {p}: {a} here, {b} on the robot")
    return diffs


# --------------------------------------------------------------------------- edits
class Edits:
    """The changes the scenarios make to the local tree, distinct on every repetition."""

    def __init__(self, ws: Workspace) -> None:
        self.ws = ws
        self.big = ws.big_text
        lines = ws.edit_target.read_bytes().splitlines(keepends=True)
        # a line of code in the middle of the file, not the license or includes
        self.edit_line = next(i for i in range(len(lines) // 2, len(lines)) if b";" in lines[i])
        self.edit_original = lines[self.edit_line]

    def one_edit(self, rep: int) -> None:
        path = self.ws.edit_target
        lines = path.read_bytes().splitlines(keepends=True)
        lines[self.edit_line] = (
            self.edit_original.rstrip(b"\n") + f"  // tuned, rev {rep}\n".encode()
        )
        path.write_bytes(b"".join(lines))

    def insert_top(self, rep: int) -> None:
        data = self.big.read_bytes()
        self.big.write_bytes(f"// generated by table_gen, revision {rep}\n".encode() + data)

    def rename(self, rep: int) -> None:
        new = self.big.with_name(f"generated_lookup_tables_r{rep}.cpp")
        os.rename(self.big, new)
        self.big = new


# --------------------------------------------------------------------------- the run
@dataclasses.dataclass
class Params:
    files: int
    size_mb: float
    reps_small: int
    reps_initial: int
    seed: int
    cold: bool
    """Also run fetchsync without its connection master (FETCHSYNC_PERSIST=0)."""
    settle: float = CREATE_WAIT
    """Seconds at most to wait for file creation to run at its usual speed (see settle_allocator)."""
    link: str = "loopback"
    """The link profile of bench/countproxy.py both tools reach the robot through."""
    scenarios: tuple[str, ...] = tuple(sc for sc, _ in SCENARIOS)
    """The scenarios run (the initial push always: the others start from its tree)."""


class Bench:
    def __init__(
        self,
        *,
        workdir: Path,
        ws: Workspace,
        sshd: SSHD,
        params: Params,
        log: Callable[[str], None],
        baseline: tuple[str, Path] | list[tuple[str, Path]] | None = None,
        measured: tuple[str, Path] | None = None,
        side: RobotSide | None = None,
    ) -> None:
        """``baseline``: (a short name of its revision, its source tree), or a list of
        them: other fetchsyncs pushed side by side with this one (an A/B run; several
        measure a series of commits in the same rounds). ``measured``: the same for the
        fetchsync measured, when it is not this checkout (``--rev``). ``side``: the
        robot's account and where its trees go (default: the current user, in
        ``workdir``)."""
        self.side = side or RobotSide.make(sshd.user, workdir)
        self.workdir = workdir
        self.ws = ws
        self.sshd = sshd
        self.params = params
        self.log = log
        self.home = make_ssh_home(workdir / "home", sshd=sshd)
        self.counter = Counter(workdir / "wire")
        # fetchsync's connection masters listen here: a directory of this run only
        # (short, for the unix socket path limit), so they are ours to stop
        self.runtime_dir = Path(tempfile.mkdtemp(prefix="fsbench-run-"))
        # trees replaced by a reset, deleted at the end (beside them: a rename)
        self.graveyard = self.side.root / "graveyard"
        self.robot_dir = self.side.mkdir(self.side.root / "robot")
        self.ssh_config = self.home.config
        self.link: Link | None = LINKS[params.link]
        proxy = proxy_command(sshd.host, sshd.port, self.counter.dir, self.link)
        with open(self.ssh_config, "a") as fh:
            fh.write(
                f"\nHost {ALIAS}\n"
                f"    HostName {sshd.host}\n"
                f"    Port {sshd.port}\n"
                f"    User {self.side.user}\n"
                f"    IdentityFile {self.home.identity}\n"
                f"    IdentitiesOnly yes\n"
                f"    UserKnownHostsFile {self.home.known_hosts}\n"
                f"    GlobalKnownHostsFile /dev/null\n"
                f"    StrictHostKeyChecking yes\n"
                f"    UpdateHostKeys no\n"
                f"    ProxyCommand {proxy}\n"
            )
        robot = self.robot_dir
        self.measured_rev = measured[0] if measured else None
        self.tools: list[Tool] = [
            FetchsyncPush(
                bench=self,
                remote=robot / "fetchsync-ws",
                checkout=measured[1] if measured else REPO,
                runtime="m",  # each fetchsync its own runtime dir, so its own master
            )
        ]
        if params.cold:
            self.tools.append(
                FetchsyncPush(
                    bench=self, remote=robot / "fetchsync-cold-ws", persist=False, runtime="c"
                )
            )
        baselines = [baseline] if isinstance(baseline, tuple) else list(baseline or [])
        for i, (rev, checkout) in enumerate(baselines):
            self.tools.append(
                FetchsyncPush(
                    bench=self,
                    remote=robot / ("baseline-ws" if i == 0 else f"baseline-{i}-ws"),
                    checkout=checkout,
                    name=f"fetchsync@{rev}",
                    runtime=f"b{i}" if i else "b",
                )
            )
        # the revisions in the order given, the one measured last: a series of commits
        self.series = [f"fetchsync@{rev}" for rev, _ in baselines] + ["fetchsync"]
        self.sources = {
            t.name: check_source(t.name, t.command()[1], t.checkout, workdir)
            for t in self.tools
            if isinstance(t, FetchsyncPush)
        }
        self.tools.append(RsyncPush(bench=self, remote=robot / "rsync-ws"))
        self.samples: list[Sample] = []
        self.failures: list[dict[str, Any]] = []
        self.startup: dict[str, float] = {}  # see measure_startup
        self.allocator: dict[str, float] | None = None  # see settle_allocator
        self.robot: dict[str, object] = {}  # see RobotSide.probe
        self.owners: dict[str, list[str]] = {}  # who owns each tool's robot tree at the end
        self.verified: dict[str, dict[str, list[str]]] = {}
        self.repairs: dict[str, dict[str, dict[str, Any]]] = {}

    @functools.cached_property
    def edits(self) -> Edits:
        return Edits(self.ws)

    def marks(self) -> list[bytes]:
        """What the command lines of this run's background processes hold."""
        return [str(self.runtime_dir).encode(), str(self.workdir).encode()]

    def base_env(self) -> dict[str, str]:
        env = {
            k: v
            for k, v in os.environ.items()
            if not k.startswith(("FETCHSYNC_", "FETCH_", "XDG_"))
            and k not in ("SSH_AUTH_SOCK", "ROS_MASTER_URI")
        }
        env["HOME"] = str(self.home.home)
        env["XDG_RUNTIME_DIR"] = str(self.runtime_dir)
        # benchmark this checkout's fetchsync, whatever is installed or the current directory
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
        return env

    # ---------------------------------------------------------------------- masters
    def _master_pids(self, runtime: str | None = None) -> list[int]:
        """Connection masters of this run (of one fetchsync's ``runtime`` subdirectory):
        their --socket is under our runtime dir.

        Matched by that directory and the name fetchsync, not by module path, so
        the bench still finds them in a version that moved its modules."""
        base = self.runtime_dir / runtime if runtime else self.runtime_dir
        mark = (str(base) + "/").encode()
        pids = []
        for proc in Path("/proc").iterdir():
            if not proc.name.isdigit():
                continue
            try:
                cmdline = (proc / "cmdline").read_bytes()
            except OSError:
                continue
            if b"fetchsync" in cmdline and mark in cmdline and int(proc.name) != os.getpid():
                pids.append(int(proc.name))
        return pids

    def stop_masters(self, runtime: str | None = None) -> None:
        """End fetchsync's connection masters of this run (or of one fetchsync's ``runtime``
        subdirectory), as a new login session would find none.

        A master exits within a second of its socket being taken away; one that
        does not is sent SIGTERM by pid.
        """
        base = self.runtime_dir / runtime if runtime else self.runtime_dir
        for sock in base.rglob("*.sock"):
            sock.unlink(missing_ok=True)
        deadline = time.monotonic() + 5
        while self._master_pids(runtime) and time.monotonic() < deadline:
            time.sleep(0.05)
        for pid in self._master_pids(runtime):
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGTERM)
        if runtime is None:
            self.counter.settle(live=0, timeout=10)
        else:  # the other fetchsyncs' masters stay connected
            self.counter.settle(timeout=10)

    def close(self) -> None:
        self.stop_masters()
        shutil.rmtree(self.runtime_dir, ignore_errors=True)
        shutil.rmtree(self.graveyard, ignore_errors=True)

    # ---------------------------------------------------------------------- scenarios
    def order(self, rep: int) -> list[Tool]:
        # rotate which tool goes first, so none always meets a warm or a cold cache
        k = rep % len(self.tools)
        return self.tools[k:] + self.tools[:k]

    def push_sample(self, tool: Tool, scenario: str, rep: int) -> Sample | None:
        """One timed push, kept with the samples. A push that fails is logged and kept in
        ``failures`` (the run then fails; the verification after the scenario shows and
        repairs its tree), and the run goes on: one tool's error must not lose the others'."""
        try:
            s = tool.push(scenario, rep)
        except PushFailed as exc:
            self.failures.append(
                {"tool": tool.name, "scenario": scenario, "rep": rep, "error": str(exc)[-4000:]}
            )
            first = next((ln for ln in str(exc).splitlines() if "error" in ln), str(exc)[:200])
            self.log(f"  {scenario:8} #{rep} {tool.name:14} FAILED: {first[:300]}")
            return None
        self.samples.append(s)
        return s

    def run_scenario(
        self,
        scenario: str,
        reps: int,
        before: Callable[[int], None] | None = None,
        each: Callable[[Tool], None] | None = None,
    ) -> None:
        for rep in range(reps):
            if before is not None:
                before(rep)
            for tool in self.order(rep):
                if each is not None:
                    each(tool)
                s = self.push_sample(tool, scenario, rep)
                if s is None:
                    continue
                inner = f" (in-process {s.report['seconds']:.3f} s)" if s.report else ""
                self.log(
                    f"  {scenario:8} #{rep} {tool.name:14} {s.seconds:7.3f} s{inner} "
                    f"{_human(s.bytes):>10} over {s.connections} new connection(s)"
                )
        self.verify(scenario)

    def verify(self, scenario: str) -> None:
        local = snapshot(self.ws.src)
        result = {}
        for tool in self.tools:
            diffs = differences(local, snapshot(tool.remote_src))
            result[tool.name] = diffs
            status = (
                "identical" if not diffs else f"{len(diffs)} difference(s): " + "; ".join(diffs[:3])
            )
            self.log(f"  verify {scenario}: {tool.name}: {status} ({len(local)} paths)")
            if diffs:
                self.repair(scenario, tool, local)
        self.verified[scenario] = result

    def repair(
        self, scenario: str, tool: Tool, local: dict[str, tuple[Any, ...]], tries: int = 5
    ) -> None:
        """Push again (untimed) until the tool's tree verifies, so the next scenario starts
        from a mirrored tree and measures what it says. The failure stays in the report."""
        done: list[Sample] = []
        diffs: list[str] = []
        for k in range(tries):
            try:
                done.append(tool.push("repair", k))
            except PushFailed as exc:
                self.log(f"  repair {scenario}: {tool.name} failed: {str(exc)[-300:]}")
            diffs = differences(local, snapshot(tool.remote_src))
            if not diffs:
                break
        self.repairs.setdefault(scenario, {})[tool.name] = {
            "pushes": len(done),
            "converged": not diffs,
            "seconds": sum(s.seconds for s in done),
            "bytes": sum(s.bytes for s in done),
            "remaining": diffs[:20],
        }
        self.log(
            f"  repair {scenario}: {tool.name}: "
            + (
                f"identical after {len(done)} more push(es)"
                if not diffs
                else f"still {len(diffs)} difference(s) after {len(done)} more pushes"
            )
        )

    def run(self) -> None:
        p = self.params
        self.allocator = settle_allocator(self.robot_dir, self.graveyard, self.log, wait=p.settle)
        self.probe_robot()
        for tool in self.tools:
            tool.reset()

        def fresh(tool: Tool) -> None:
            tool.reset()

        self.run_scenario("initial", p.reps_initial, each=fresh)
        edits: dict[str, Callable[[int], None] | None] = {
            "noop": None,
            "edit": self.edits.one_edit,
            "insert": self.edits.insert_top,
            "rename": self.edits.rename,
        }
        for scenario, before in edits.items():
            if scenario in p.scenarios:
                self.run_scenario(scenario, p.reps_small, before=before)
        self.measure_startup(p.reps_small)
        self.owners = {t.name: self.side.owners(t.remote_src) for t in self.tools}

    def probe_robot(self) -> None:
        """The robot's account, python3 and the time of ``ssh robot true`` (for the report)."""
        ssh = ["ssh", "-F", str(self.ssh_config), "-o", "BatchMode=yes", ALIAS]
        self.robot = self.side.probe(ssh)
        self.counter.settle(live=0)
        self.log("  " + self.side.describe(self.robot))

    def measure_startup(self, reps: int) -> None:
        """The wall time of ``fetchsync --version`` per fetchsync tool (median of ``reps``):
        the interpreter's start and the CLI's import, what a one-shot push pays besides its
        own work. A no-op push's wall time minus its in-process seconds minus this is time
        spent neither starting nor working (waiting at exit, say)."""
        for tool in self.tools:
            if not isinstance(tool, FetchsyncPush):
                continue
            argv, env = tool.command()
            times = []
            for _ in range(reps):
                t0 = time.perf_counter()
                subprocess.run(
                    [argv[0], "-m", "fetchsync", "--version"],
                    env=env,
                    cwd=self.workdir,
                    stdin=subprocess.DEVNULL,
                    capture_output=True,
                    check=False,
                )
                times.append(time.perf_counter() - t0)
            self.startup[tool.name] = statistics.median(times)
            self.log(f"  startup {tool.name}: fetchsync --version {self.startup[tool.name]:.3f} s")

    # ---------------------------------------------------------------------- results
    def median(self, tool: str, scenario: str, key: Callable[[Sample], float]) -> float:
        return statistics.median(
            key(s) for s in self.samples if s.tool == tool and s.scenario == scenario
        )

    def verified_ok(self) -> bool:
        return (
            not self.failures
            and set(self.verified) == {"initial", *self.params.scenarios}
            and all(not d for r in self.verified.values() for d in r.values())
        )

    def summary(
        self, ours: str = "fetchsync", theirs: str = "rsync", *, targets: bool = True
    ) -> dict[str, Any]:
        """Per scenario, ``ours`` against ``theirs``; ``targets``: judge the link's targets
        (they are against rsync; an A/B of two fetchsyncs has none)."""
        rows: dict[str, Any] = {}
        time_targets = TIME_TARGETS_BY_LINK[self.params.link] if targets else {}
        byte_targets = BYTE_TARGETS if targets else {}
        ratio_targets = BYTES_RATIO_TARGETS_BY_LINK.get(self.params.link, {}) if targets else {}
        for scenario, title in SCENARIOS:
            if not any(s.scenario == scenario for s in self.samples):
                continue
            if not all(
                any(s.tool == t and s.scenario == scenario for s in self.samples)
                for t in (ours, theirs)
            ):
                continue  # every push of one of them failed (see the failures)
            row: dict[str, Any] = {"title": title}
            for tool in (ours, theirs):
                sel = [s for s in self.samples if s.tool == tool and s.scenario == scenario]
                row[tool] = {
                    "seconds": statistics.median(s.seconds for s in sel),
                    "seconds_min": min(s.seconds for s in sel),
                    "seconds_max": max(s.seconds for s in sel),
                    "bytes": statistics.median(s.bytes for s in sel),
                    "up": statistics.median(s.up for s in sel),
                    "down": statistics.median(s.down for s in sel),
                    "n": len(sel),
                }
                if scenario in BYTE_TARGETS:
                    row[tool]["beyond_noop"] = row[tool]["bytes"] - self.median(
                        tool, "noop", lambda s: s.bytes
                    )
            f, r = row[ours], row[theirs]
            row["time_ratio"] = f["seconds"] / r["seconds"] if r["seconds"] else None
            row["bytes_ratio"] = f["bytes"] / r["bytes"] if r["bytes"] else None
            # each round's push over the other tool's in the same round: the ratio of the
            # medians pairs a fast push of one tool with a slow one of the other when the
            # machine's speed drifts, as it does here over minutes
            mine = {
                s.rep: s.seconds for s in self.samples if s.tool == ours and s.scenario == scenario
            }
            other = {
                s.rep: s.seconds
                for s in self.samples
                if s.tool == theirs and s.scenario == scenario
            }
            rounds = [mine[k] / other[k] for k in sorted(mine) if k in other and other[k]]
            row["round_ratios"] = rounds
            row["round_ratio"] = statistics.median(rounds) if rounds else None
            if scenario in time_targets:
                row["time_target"] = time_targets[scenario]
                # met only if met both ways
                row["time_pass"] = all(
                    x is not None and x <= time_targets[scenario]
                    for x in (row["time_ratio"], row["round_ratio"])
                )
            if scenario in ratio_targets and row["bytes_ratio"] is not None:
                row["bytes_ratio_target"] = ratio_targets[scenario]
                row["bytes_ratio_pass"] = row["bytes_ratio"] <= ratio_targets[scenario]
            if scenario in BYTE_TARGETS:
                if scenario in byte_targets:
                    row["bytes_target"] = byte_targets[scenario]
                    row["bytes_pass"] = f["beyond_noop"] <= byte_targets[scenario]
                if r["beyond_noop"] > 0:
                    row["beyond_noop_ratio"] = f["beyond_noop"] / r["beyond_noop"]
            rows[scenario] = row
        return rows


# --------------------------------------------------------------------------- report
def _human(n: float) -> str:
    sign = "-" if n < 0 else ""
    n = abs(n)
    for unit in ("B", "KiB", "MiB"):
        if n < 1024:
            return f"{sign}{n:.0f} {unit}" if unit == "B" else f"{sign}{n:.1f} {unit}"
        n /= 1024
    return f"{sign}{n:.2f} GiB"


def _ratio(x: float | None) -> str:
    return "—" if x is None else f"{x:.2f}x"


def _verdict(ok: bool) -> str:
    return "**PASS**" if ok else "**MISS**"


def _create_time(where: Path, shape: tuple[int, int] = CREATE_PROBE) -> tuple[float, Path]:
    """Seconds an inode to create a tree of ``shape`` (directories, empty files in each)
    in a new directory under ``where``; that directory. Directories, as a push makes
    them, land in block groups of their own: a probe of files in one directory met a
    settled group while the push after it met unsettled ones."""
    where.mkdir(parents=True, exist_ok=True)
    top = Path(tempfile.mkdtemp(prefix="create-probe-", dir=where))
    dirs, files = shape
    start = time.perf_counter()
    for i in range(dirs):
        d = top / f"d{i}"
        d.mkdir()
        for j in range(files):
            os.close(os.open(d / f"f{j}", os.O_CREAT | os.O_WRONLY | os.O_EXCL, 0o644))
    return (time.perf_counter() - start) / (dirs * (files + 1)), top


def settle_allocator(
    where: Path, graveyard: Path, log: Callable[[str], None], *, wait: float = CREATE_WAIT
) -> dict[str, float]:
    """Wait (at most ``wait`` seconds) until files are created in ``where`` at a usual speed,
    against tmpfs's on this machine. The probes' files go to ``graveyard``: deleting
    them would slow the next creates down again. Returns what was measured."""
    base = None
    shm = Path("/dev/shm")
    if shm.is_dir() and os.access(shm, os.W_OK):
        base, d = _create_time(shm)
        shutil.rmtree(d, ignore_errors=True)
    graveyard.mkdir(parents=True, exist_ok=True)
    waited = 0.0
    while True:
        took, d = _create_time(where)
        d.rename(graveyard / d.name)
        ratio = took / base if base else 0.0
        if base is None or ratio <= CREATE_SLOW or waited >= wait:
            break
        log(
            f"creating files in {where} takes {took * 1e6:.0f} us an inode, {ratio:.0f}x tmpfs's: files were "
            f"deleted near it lately (ext4 skips inodes freed in the last minutes); waiting"
        )
        time.sleep(CREATE_POLL)
        waited += CREATE_POLL
    log(
        f"file creation where the robot's trees go: {took * 1e6:.0f} us an inode"
        + (f", {ratio:.1f}x tmpfs's" if base else "")
    )
    if base is not None and ratio > CREATE_SLOW:
        log(
            f"warning: file creation is still {ratio:.0f}x slower than on tmpfs: this run's times are noisy"
        )
    return {
        "create_us": round(took * 1e6, 1),
        "create_vs_tmpfs": round(ratio, 1),
        "waited_s": waited,
    }


def machine_info() -> dict[str, str]:
    def first_line(argv: list[str]) -> str:
        try:
            out = subprocess.run(argv, capture_output=True, text=True, check=False, cwd=REPO)
            return (out.stdout or out.stderr).strip().splitlines()[0]
        except (OSError, IndexError):
            return "?"

    cpu = "?"
    with contextlib.suppress(OSError):
        m = re.search(r"^model name\s*:\s*(.+)$", Path("/proc/cpuinfo").read_text(), re.MULTILINE)
        cpu = m.group(1) if m else "?"
    try:
        import paramiko

        paramiko_version = paramiko.__version__
    except ImportError:
        paramiko_version = "?"
    git = subprocess.run(
        ["git", "-C", str(REPO), "describe", "--always", "--dirty"],
        capture_output=True,
        text=True,
        check=False,
    )
    # a tree without git (a `git archive` of a commit) says so rather than git's error
    commit = git.stdout.strip() if git.returncode == 0 else "no git: commit not known"
    return {
        "load": load_average(),
        "nproc": str(len(os.sched_getaffinity(0))),
        "cpu": cpu,
        "kernel": platform.release(),
        "python": platform.python_version(),
        "rsync": first_line(["rsync", "--version"]),
        "ssh": first_line(["ssh", "-V"]),
        "paramiko": paramiko_version,
        "fetchsync": first_line([fetchsync_python(), "-m", "fetchsync", "--version"])
        + f" ({commit})",
        "fetchsync_python": fetchsync_python(),
        "commit": commit.split()[0] if git.returncode == 0 else "?",
    }


def load_average() -> str:
    """The 1, 5 and 15 minute load averages: how busy the shared machine was."""
    return ", ".join(f"{x:.2f}" for x in os.getloadavg())


def link_line(link: Link | None) -> str:
    if link is None:
        return "Link: loopback (no shaping; both tools still pass through bench/countproxy.py)."
    return (
        f"Link: {link.describe()}, shaped per direction by bench/countproxy.py "
        "(serialisation at the rate, then the one-way delay on every byte)."
    )


def _secs(cell: dict[str, Any]) -> str:
    """The median, with the range when there was more than one run."""
    if cell["n"] < 2:
        return f"{cell['seconds']:.3f} s"
    return f"{cell['seconds']:.3f} s ({cell['seconds_min']:.2f}–{cell['seconds_max']:.2f})"


def _tables(
    rows: dict[str, Any], ours: str, theirs: str, failed: set[tuple[str, str]]
) -> list[str]:
    def mark(scenario: str, tool: str) -> str:
        return " ✗" if (scenario, tool) in failed else ""

    out = [
        f"| scenario | {ours} | {theirs} | ratio of the medians | median of the rounds' ratios | target |",
        "| --- | ---: | ---: | ---: | ---: | --- |",
    ]
    for scenario, row in rows.items():
        target = "—"
        if "time_target" in row:
            target = f"≤ {row['time_target']:g}x {_verdict(row['time_pass'])}"
        rounds = row.get("round_ratios") or []
        spread = f" ({min(rounds):.2f}–{max(rounds):.2f})" if len(rounds) > 1 else ""
        out.append(
            f"| {row['title']} | {_secs(row[ours])}{mark(scenario, ours)} | "
            f"{_secs(row[theirs])}{mark(scenario, theirs)} | "
            f"{_ratio(row['time_ratio'])} | {_ratio(row.get('round_ratio'))}{spread} | {target} |"
        )
    out += [
        "",
        (
            "Bytes on the wire (both directions, SSH framing and handshakes included; "
            "insert and rename: beyond the same tool's no-op push)"
        ),
        "",
        f"| scenario | {ours} | {theirs} | ratio ({ours}/{theirs}) | target |",
        "| --- | ---: | ---: | ---: | --- |",
    ]
    for scenario, row in rows.items():
        f, r = row[ours], row[theirs]
        if scenario in BYTE_TARGETS:
            target = "—"
            if "bytes_target" in row:
                target = f"≤ {_human(row['bytes_target'])} {_verdict(row['bytes_pass'])}"
            out.append(
                f"| {row['title']} | {_human(f['beyond_noop'])} | {_human(r['beyond_noop'])} | "
                f"{_ratio(row.get('beyond_noop_ratio'))} | {target} |"
            )
        else:
            target = "—"
            if "bytes_ratio_target" in row:
                target = f"≤ {row['bytes_ratio_target']:g}x {_verdict(row['bytes_ratio_pass'])}"
            out.append(
                f"| {row['title']} | {_human(f['bytes'])}{mark(scenario, ours)} | "
                f"{_human(r['bytes'])}{mark(scenario, theirs)} | {_ratio(row['bytes_ratio'])} | {target} |"
            )
    if any(t in (ours, theirs) for _s, t in failed):
        out += [
            "",
            (
                "✗ the robot's tree was not identical to the local one after this scenario "
                "(see verification below)"
            ),
        ]
    return out


# --------------------------------------------------------------------------- results rows
RESULTS_HEADER = (
    "| figure | target | fetchsync ({commit}) | rsync / lsyncd | ratio | verdict |",
    "| --- | --- | ---: | ---: | ---: | --- |",
)
NOOP_WAIT_SLACK = 0.05
"""Seconds a no-op push's wall time may exceed its own work plus the interpreter's start
and still count as "nothing waits" (issue 24): the rest is measurement noise."""


@dataclasses.dataclass
class ResultRow:
    """One row of bench/README.md's "Latest results" tables."""

    figure: str
    target: str
    ours: str
    theirs: str
    ratio: str
    verdict: str

    def markdown(self) -> str:
        return (
            f"| {self.figure} | {self.target} | {self.ours} | {self.theirs} | {self.ratio} | "
            f"{self.verdict} |"
        )


def results_section(title: str, commit: str, rows: list[ResultRow]) -> list[str]:
    """The rows to paste into bench/README.md's "Latest results", with their header."""
    return [
        f"Rows for bench/README.md's Latest results ({title}):",
        "",
        RESULTS_HEADER[0].format(commit=commit),
        RESULTS_HEADER[1],
        *(r.markdown() for r in rows),
    ]


def _ratios(row: dict[str, Any]) -> str:
    return f"{_ratio(row['time_ratio'])} ({_ratio(row.get('round_ratio'))})"


def result_rows(bench: Bench) -> list[ResultRow]:
    """bench/README.md's rows for this run: each figure, its target on this link, both
    tools' medians, the ratios (of the medians, of the rounds' own in brackets), PASS/MISS."""
    rows = bench.summary("fetchsync", "rsync")
    out: list[ResultRow] = []

    def verdict(ok: bool | None) -> str:
        return "" if ok is None else _verdict(ok)

    def time_row(scenario: str, figure: str) -> None:
        if scenario not in rows:
            return
        r = rows[scenario]
        target = f"≤ {r['time_target']:g}x" if "time_target" in r else "—"
        out.append(
            ResultRow(
                figure,
                target,
                f"{r['fetchsync']['seconds']:.3f} s",
                f"{r['rsync']['seconds']:.3f} s",
                _ratios(r),
                verdict(r.get("time_pass")),
            )
        )

    time_row("initial", "initial push, time" + (" (fresh robot trees)" if not bench.link else ""))
    if "initial" in rows:
        r = rows["initial"]
        target = f"≤ {r['bytes_ratio_target']:g}x" if "bytes_ratio_target" in r else "—"
        out.append(
            ResultRow(
                "initial push, bytes",
                target,
                _human(r["fetchsync"]["bytes"]),
                _human(r["rsync"]["bytes"]),
                "—" if r["bytes_ratio"] is None else f"{r['bytes_ratio']:.3f}x",  # near 1
                verdict(r.get("bytes_ratio_pass")),
            )
        )
        if bench.link is not None:  # issue 24: the first push after the master starts
            ok = all(x is not None and x <= 1.0 for x in (r["time_ratio"], r.get("round_ratio")))
            out.append(
                ResultRow(
                    "first push after the master starts (the initial push: no master)",
                    "≤ 1.0x" if bench.params.link == "wifi" else "—",
                    f"{r['fetchsync']['seconds']:.3f} s",
                    f"{r['rsync']['seconds']:.3f} s",
                    _ratios(r),
                    verdict(ok if bench.params.link == "wifi" else None),
                )
            )
    time_row("edit", "one-edit push, time")
    time_row("insert", "one line inserted in a 2 MiB file, time")
    if "insert" in rows and "rename" in rows:
        ri, rr = rows["insert"], rows["rename"]
        ok = ri.get("bytes_pass", True) and rr.get("bytes_pass", True)
        out.append(
            ResultRow(
                "insert / rename, bytes beyond no-op",
                f"≤ {_human(BYTE_TARGETS['insert'])} / ≤ {_human(BYTE_TARGETS['rename'])}",
                f"{_human(ri['fetchsync']['beyond_noop'])} / {_human(rr['fetchsync']['beyond_noop'])}",
                f"{_human(ri['rsync']['beyond_noop'])} / {_human(rr['rsync']['beyond_noop'])}",
                f"{_ratio(ri.get('beyond_noop_ratio'))} / {_ratio(rr.get('beyond_noop_ratio'))}",
                _verdict(ok),
            )
        )
    if "noop" in rows:
        r = rows["noop"]
        sel = [s for s in bench.samples if s.tool == "fetchsync" and s.scenario == "noop"]
        start = bench.startup.get("fetchsync")
        inner = [float(s.report["seconds"]) for s in sel if s.report]
        wall = r["fetchsync"]["seconds"]
        if start is not None and inner:
            own = statistics.median(inner)
            rest = wall - own - start
            ours = (
                f"{wall:.3f} s wall = {own:.3f} s own + {start:.3f} s start "
                f"{'+' if rest >= 0 else '−'} {abs(rest):.3f} s unaccounted"
            )
        else:
            rest, ours = None, f"{wall:.3f} s"
        if "time_target" in r:  # loopback: a ratio
            out.append(
                ResultRow(
                    "no-op push, time",
                    f"≤ {r['time_target']:g}x",
                    ours,
                    f"{r['rsync']['seconds']:.3f} s",
                    _ratios(r),
                    verdict(r.get("time_pass")),
                )
            )
        else:
            out.append(
                ResultRow(
                    "no-op push: wall time = own work + interpreter start",
                    f"nothing waits (≤ {NOOP_WAIT_SLACK * 1000:.0f} ms unaccounted)",
                    ours,
                    f"{r['rsync']['seconds']:.3f} s",
                    _ratios(r),
                    verdict(None if rest is None else rest <= NOOP_WAIT_SLACK)
                    if bench.params.link == "wifi"
                    else "",
                )
            )
    return out


def _startup_lines(bench: Bench) -> list[str]:
    """Per fetchsync: the no-op push's wall time against its own reported seconds and the
    interpreter's start (``fetchsync --version``): issue 24 asks that nothing else wait."""
    out = []
    for name, start in bench.startup.items():
        sel = [s for s in bench.samples if s.tool == name and s.scenario == "noop" and s.report]
        if not sel:
            continue
        wall = statistics.median(s.seconds for s in sel)
        inner = statistics.median(float(s.report["seconds"]) for s in sel if s.report)
        out.append(
            f"No-op push of {name}: {wall:.3f} s wall, {inner:.3f} s of it reported by the push "
            f"itself, {start:.3f} s to start the interpreter and the CLI (`fetchsync --version`): "
            f"{wall - inner - start:+.3f} s unaccounted (waiting at start or exit)."
        )
    return out


def _allocator_line(probe: dict[str, float] | None) -> str:
    if not probe:
        return "File creation on the robot's disk was not probed."
    vs = f", {probe['create_vs_tmpfs']:.1f}x tmpfs's" if probe["create_vs_tmpfs"] else ""
    waited = (
        f", after waiting {probe['waited_s']:.0f} s for it to settle" if probe["waited_s"] else ""
    )
    return f"File creation on the robot's disk at the start: {probe['create_us']:.0f} us an inode{vs}{waited}."


def _series_lines(bench: Bench, failed: set[tuple[str, str]]) -> list[str]:
    """Each revision of a series against the one before it, in the same rounds: what
    one commit did to each figure (issue 23's removals, measured one by one)."""
    names = bench.series
    scenarios = [sc for sc, _ in SCENARIOS if any(s.scenario == sc for s in bench.samples)]
    titles = dict(SCENARIOS)
    out = [
        (
            "Each revision against the one before it (time: ratio of the medians, median of "
            "the rounds' ratios in brackets; above 1.00x the later one is slower; "
            "✗: a tree failed verification)"
        ),
        "",
        "| after vs before | " + " | ".join(titles[sc] for sc in scenarios) + " |",
        "| --- |" + " ---: |" * len(scenarios),
    ]
    for before, after in zip(names, names[1:]):
        rows = bench.summary(after, before, targets=False)
        cells = []
        for sc in scenarios:
            row = rows.get(sc)
            if row is None:
                cells.append("—")
                continue
            bad = " ✗" if (sc, after) in failed or (sc, before) in failed else ""
            cells.append(
                f"{row[after]['seconds']:.3f} vs {row[before]['seconds']:.3f} s: "
                f"{_ratio(row['time_ratio'])} ({_ratio(row.get('round_ratio'))}){bad}"
            )
        label = f"{after.removeprefix('fetchsync@')} vs {before.removeprefix('fetchsync@')}"
        if after == "fetchsync":
            label = (
                f"{bench.measured_rev or 'this checkout'} vs {before.removeprefix('fetchsync@')}"
            )
        out.append(f"| {label} | " + " | ".join(cells) + " |")
    return out


def render(bench: Bench, machine: dict[str, str], ws_info: dict[str, Any]) -> str:
    p = bench.params
    out = [
        (
            f"Machine: {machine['nproc']} CPUs ({machine['cpu']}), Linux {machine['kernel']}, "
            f"Python {machine['python']}, {machine['rsync']}, {machine['ssh']}, "
            f"paramiko {machine['paramiko']}, {machine['fetchsync']}"
        ),
        "",
        (
            f"Workspace: {ws_info['files']} files + 1 symlink, {ws_info['bytes'] / 2**20:.1f} MiB "
            f"(seed {p.seed}); medians of {p.reps_small} runs ({p.reps_initial} for the initial push), "
            f"each push a new process, tools interleaved; rsync {RSYNC_FLAGS} --delete."
        ),
        "",
        link_line(bench.link),
        "",
        bench.side.describe(bench.robot) if bench.robot else "Robot: not probed.",
        "",
        f"Load average: {machine.get('load', '?')} at the start, {load_average()} at the end.",
        "",
        _allocator_line(bench.allocator),
        "",
        (
            "Wall time of `fetchsync push` (as installed: its connection master persists "
            "between calls) and of rsync: median (min–max); a time target is met only if "
            "both the ratio of the medians and the median of each round's ratio meet it"
        ),
        "",
    ]
    failed = {
        (sc, tool) for sc, res in bench.verified.items() for tool, diffs in res.items() if diffs
    }
    out += _tables(bench.summary("fetchsync", "rsync"), "fetchsync", "rsync", failed)
    out += ["", *_startup_lines(bench)]
    if any(t.name == "fetchsync-cold" for t in bench.tools):
        out += [
            "",
            (
                "The same without the connection master (`FETCHSYNC_PERSIST=0`: every push makes "
                "its own SSH connection and starts its own endpoint, as rsync does)"
            ),
            "",
        ]
        out += _tables(bench.summary("fetchsync-cold", "rsync"), "fetchsync-cold", "rsync", failed)
    for base in bench.tools:
        if isinstance(base, FetchsyncPush) and base.name.startswith("fetchsync@"):
            out += [
                "",
                (
                    f"A/B: fetchsync ({bench.measured_rev or 'this checkout'}) against "
                    f"{base.name} (`git archive` of that revision, run "
                    "with PYTHONPATH set to it, its own connection master, state and remote dir), "
                    "in the same rounds"
                ),
                "",
            ]
            out += _tables(
                bench.summary("fetchsync", base.name, targets=False), "fetchsync", base.name, failed
            )
            out += ["", f"{base.name} against rsync", ""]
            out += _tables(bench.summary(base.name, "rsync"), base.name, "rsync", failed)
    if len(bench.series) > 2:
        out += ["", *_series_lines(bench, failed)]
    commit = bench.measured_rev or machine.get("commit", "?")
    title = f"{p.link}, run.py, {ws_info['files']} files, {ws_info['bytes'] / 2**20:.0f} MiB"
    out += ["", *results_section(title, commit, result_rows(bench))]
    out.append("")
    if bench.verified_ok():
        out.append(
            f"verification: PASS (after each of the {len(bench.verified)} scenarios every remote "
            "tree equals the local src/: paths, kinds, modes, symlink targets, SHA-256)"
        )
    else:
        out.append("verification: FAIL")
        out.append("")
        for f in bench.failures:
            out.append(
                f"- {f['tool']}'s {f['scenario']} push #{f['rep']} failed: "
                + " ".join(f["error"].split())[-400:]
            )
        for sc, res in bench.verified.items():
            for tool, diffs in res.items():
                if diffs:
                    out.append(
                        f"- after {sc}, {tool}'s tree had {len(diffs)} difference(s), e.g. "
                        + "; ".join(diffs[:3])
                    )
                    r = bench.repairs.get(sc, {}).get(tool)
                    if r is not None:
                        out.append(
                            f"  - then {r['pushes']} more untimed push(es) "
                            f"({r['seconds']:.1f} s, {_human(r['bytes'])}) "
                            + (
                                "made it identical; the next scenarios start from there"
                                if r["converged"]
                                else "did not make it identical"
                            )
                        )
    return "\n".join(out)


# --------------------------------------------------------------------------- profile
def profile_noop(bench: Bench) -> str:
    """Where a no-op ``fetchsync push`` spends its time: cProfile and ``-X importtime``.

    Profiled both through the connection master (the default) and without it.
    """
    out = []
    for tool in bench.tools:
        if not isinstance(tool, FetchsyncPush):
            continue
        argv, env = tool.command()
        if not tool.persist:
            env["FETCHSYNC_PERSIST"] = "0"
        out += _profile_one(bench, tool, argv, env)
    return "\n".join(out)


def _profile_one(
    bench: Bench, tool: FetchsyncPush, argv: list[str], env: dict[str, str]
) -> list[str]:
    lines = ["", f"Profile of a no-op `{tool.name} push` (cProfile; seconds)", ""]
    prof = bench.workdir / f"noop-{tool.name}.prof"
    t0 = time.perf_counter()
    # `-m cProfile` writes its file after the module returns; fetchsync ends the process
    # with os._exit (the CLI once the exit handlers ran, the resident's fast path without
    # them), so the profile is dumped by an exit handler and by os._exit itself
    profiled = (
        "import atexit, cProfile, os, runpy, sys\n"
        "out = sys.argv.pop(1)\n"
        "p = cProfile.Profile()\n"
        "def dump():\n"
        "    p.disable()\n"
        "    p.dump_stats(out)\n"
        "atexit.register(dump)\n"
        "real_exit = os._exit\n"
        "os._exit = lambda code: (dump(), real_exit(code))\n"
        "p.enable()\n"
        "runpy.run_module('fetchsync', run_name='__main__', alter_sys=True)\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", profiled, str(prof), *argv[argv.index("fetchsync") + 1 :]],
        env=env,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        check=False,
    )
    wall = time.perf_counter() - t0
    bench.counter.settle()
    if run.returncode != 0:
        return lines + [f"profile failed: {run.stderr[-2000:]}"]
    st = pstats.Stats(str(prof))
    entries = []
    for (file, line, func), (_cc, _nc, tt, ct, _callers) in st.stats.items():  # type: ignore[attr-defined]
        entries.append((ct, tt, f"{_short(file)}:{line}({func})"))
    lines.append(f"wall {wall:.3f} s under the profiler, {st.total_tt:.3f} s profiled")  # type: ignore[attr-defined]
    lines.append("```")
    lines.append(f"{'cumulative':>10} {'self':>8}  function")
    for ct, tt, name in sorted(entries, reverse=True)[:22]:
        lines.append(f"{ct:10.3f} {tt:8.3f}  {name}")
    lines.append("-- top by self time")
    for ct, tt, name in sorted(entries, key=lambda e: -e[1])[:12]:
        lines.append(f"{ct:10.3f} {tt:8.3f}  {name}")
    lines.append("```")
    run = subprocess.run(
        [sys.executable, "-X", "importtime", *argv[1:]],
        env=env,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        check=False,
    )
    bench.counter.settle()
    imports = []
    for ln in run.stderr.splitlines():
        m = re.match(r"import time:\s+(\d+) \|\s+(\d+) \|( *)(\S+)", ln)
        if m and len(m.group(3)) == 1:  # top-level imports only
            imports.append((int(m.group(2)), m.group(4)))
    total_us = sum(us for us, _ in imports)
    lines.append("")
    lines.append(
        f"Imports (`-X importtime`): {total_us / 1e6:.3f} s in all; the largest top-level ones:"
    )
    lines.append("```")
    for us, name in sorted(imports, reverse=True)[:12]:
        lines.append(f"{us / 1e6:8.3f}  {name}")
    lines.append("```")
    return lines


def _short(file: str) -> str:
    for marker in ("site-packages/", "/lib/python3.", str(REPO) + "/"):
        if marker in file:
            return file.split(marker, 1)[1]
    return file


# --------------------------------------------------------------------------- main
@contextlib.contextmanager
def _workdir(path: str | None, keep: bool) -> Iterator[Path]:
    if path:
        p = Path(path).resolve()
        p.mkdir(parents=True, exist_ok=True)
        yield p
        return
    p = Path(tempfile.mkdtemp(prefix="fetchsync-bench-"))
    try:
        yield p
    finally:
        if not keep:
            shutil.rmtree(p, ignore_errors=True)


def imported_from(env: dict[str, str], cwd: Path) -> Path:
    """The ``fetchsync`` package a ``python -m fetchsync`` started with ``env`` in ``cwd``
    imports: its directory."""
    proc = subprocess.run(
        [fetchsync_python(), "-c", "import fetchsync; print(fetchsync.__file__)"],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        check=False,
    )
    if proc.returncode != 0:
        raise SystemExit(f"cannot import fetchsync: {proc.stderr.strip()[-500:]}")
    return Path(proc.stdout.strip().splitlines()[-1]).resolve().parent


def check_source(name: str, env: dict[str, str], checkout: Path, cwd: Path) -> str:
    """Refuse to measure a fetchsync that does not import its own tree's modules (a
    baseline picking up this checkout's, or an installed copy, would make an A/B of a
    commit against itself). Returns where it imports fetchsync from."""
    found = imported_from(env, cwd)
    if not found.is_relative_to((checkout / "fetchsync").resolve()):
        raise SystemExit(f"{name} imports fetchsync from {found}, not from {checkout}")
    return str(found)


def compile_checkout(checkout: Path = REPO) -> None:
    """Write the bytecode of the checkout measured, as ``pip install`` does for an
    installed fetchsync: with ``PYTHONDONTWRITEBYTECODE`` set (as on some machines
    and CI), Python would otherwise compile every module at every push, ~30 ms of its
    start that no installed copy pays."""
    import compileall

    if not compileall.compile_dir(str(checkout / "fetchsync"), quiet=1):
        raise SystemExit("cannot compile fetchsync's modules")


def baseline_checkout(rev: str, workdir: Path) -> tuple[str, Path]:
    """The source tree of fetchsync at git revision ``rev``, for an A/B run: a
    ``git archive`` of it under ``workdir`` (no worktree to clean up), its bytecode
    written. Returns (the short commit, the tree)."""
    git = ["git", "-C", str(REPO)]
    proc = subprocess.run(
        [*git, "rev-parse", "--short", f"{rev}^{{commit}}"],
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise SystemExit(f"--baseline-rev {rev}: not a commit of {REPO}")
    short = proc.stdout.strip()
    dest = workdir / f"baseline-{short}"
    if not (dest / "fetchsync").is_dir():
        dest.mkdir(parents=True, exist_ok=True)
        archive = subprocess.Popen([*git, "archive", short], stdout=subprocess.PIPE)
        subprocess.run(["tar", "-x", "-C", str(dest)], stdin=archive.stdout, check=True)
        if archive.wait() != 0:
            raise SystemExit(f"git archive {short} failed")
    compile_checkout(dest)
    return short, dest


def _terminated(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)


def start_robot(
    stack: contextlib.ExitStack,
    user: str | None,
    workdir: Path,
    *,
    keep: bool = False,
    log: Callable[[str], None],
    name: str = "sshd",
    fs: str = "ext4",
) -> tuple[RobotSide, SSHD]:
    """The robot: its account (``--robot-user``; see bench/robot.py), where its side
    lives (``--robot-fs``: a journaled ext4 made for the run, or the account's home),
    and the tests' sshd started for it, whose ``user`` is that account. All end with
    ``stack``."""
    # a SIGTERM (timeout(1), a kill by pid) unwinds like Ctrl-C: the sshds (started in
    # sessions of their own) and the robot's side are stopped, not left behind
    signal.signal(signal.SIGTERM, _terminated)
    parent = None
    where = "the account's home (this machine's root file system: ext4 without a journal)"
    if fs == "ext4":
        try:
            home = Path(ensure_account(user or default_robot_user()).pw_dir)
            parent = stack.enter_context(loop_disk(workdir, mount_in=home))
            where = f"a fresh journaled ext4 on a loop device ({parent})"
        except (OSError, subprocess.CalledProcessError) as exc:
            err = getattr(exc, "stderr", b"") or b""
            log(f"robot: no loop ext4 ({exc} {err.decode(errors='replace').strip()}): on its home")
    side = RobotSide.make(user, workdir, keep=keep, parent=parent)
    stack.callback(side.close)
    log(f"robot: account {side.user}, its side in {side.root}, on {where}")
    sshd = stack.enter_context(running_sshd(side.sshd_dir(name)))
    side.opened(sshd.workdir)
    return side, dataclasses.replace(sshd, user=side.user)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description="fetchsync push vs rsync over the same sshd, as ratios."
    )
    ap.add_argument("--files", type=int, help="files in the workspace (default 7000; --quick 500)")
    ap.add_argument("--size-mb", type=float, help="workspace size in MiB (default 150; --quick 10)")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="a smoke run: 500 files, 10 MiB, 2 repetitions, no cold variant",
    )
    ap.add_argument(
        "--reps", type=int, help="repetitions of the small cases (default 5; --quick 2)"
    )
    ap.add_argument(
        "--reps-initial", type=int, help="repetitions of the initial push (default 2; --quick 1)"
    )
    ap.add_argument(
        "--cold",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="also run fetchsync with FETCHSYNC_PERSIST=0 (default: on, off with --quick)",
    )
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--scenarios",
        default=",".join(sc for sc, _ in SCENARIOS),
        help="comma-separated scenarios to run (default all: initial,noop,edit,insert,rename; "
        "the initial push always runs, the others start from its tree)",
    )
    ap.add_argument(
        "--link",
        choices=sorted(LINKS),
        default="loopback",
        help="the link both tools reach the robot through (bench/countproxy.py; default loopback)",
    )
    ap.add_argument(
        "--settle",
        type=float,
        help=f"seconds at most to wait for the robot's disk to create files at its usual speed "
        f"(default {CREATE_WAIT:.0f}; --quick 0)",
    )
    ap.add_argument(
        "--rev",
        metavar="REV",
        help="measure the fetchsync of git revision REV instead of this checkout's (the bench "
        "is still this checkout's)",
    )
    ap.add_argument(
        "--baseline-rev",
        metavar="REV",
        action="append",
        help="also push with the fetchsync of git revision REV, side by side (an A/B run); "
        "repeated, oldest first: a series of commits, each against the one before it",
    )
    add_robot_user_option(ap)
    ap.add_argument("--json", dest="json_out", type=Path, help="write the raw numbers here")
    ap.add_argument("--profile", action="store_true", help="also profile a no-op fetchsync push")
    ap.add_argument("--workdir", help="work here (kept) instead of in a temporary directory")
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory")
    a = ap.parse_args(argv)
    params = Params(
        files=a.files or (500 if a.quick else 7000),
        size_mb=a.size_mb or (10 if a.quick else 150),
        reps_small=a.reps or (2 if a.quick else 5),
        reps_initial=a.reps_initial or (1 if a.quick else 2),
        seed=a.seed,
        cold=(not a.quick) if a.cold is None else a.cold,
        settle=a.settle if a.settle is not None else 0.0 if a.quick else CREATE_WAIT,
        link=a.link,
        # insert's and rename's bytes are beyond the no-op's: it runs with them
        scenarios=tuple(
            sc
            for sc, _ in SCENARIOS
            if sc in a.scenarios.split(",")
            or (sc == "noop" and {"insert", "rename"} & set(a.scenarios.split(",")))
        ),
    )
    unknown = set(a.scenarios.split(",")) - {sc for sc, _ in SCENARIOS}
    if unknown:
        ap.error(f"--scenarios: unknown {', '.join(sorted(unknown))}")

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    machine = machine_info()
    for k, v in machine.items():
        log(f"{k}: {v}")
    compile_checkout()
    with _workdir(a.workdir, a.keep) as workdir:
        log(f"workdir: {workdir}")
        ws = generate(workdir / "ws", files=params.files, size_mb=params.size_mb, seed=params.seed)
        ws_info = {
            "files": ws.files,
            "bytes": ws.bytes,
            "symlinks": ws.symlinks,
            "generate_seconds": round(ws.seconds, 3),
        }
        log(f"workspace: {ws.files} files, {ws.bytes / 2**20:.1f} MiB in {ws.seconds:.1f} s")
        with contextlib.ExitStack() as stack:
            side, sshd = start_robot(
                stack, a.robot_user, workdir, keep=a.keep, log=log, fs=a.robot_fs
            )
            baseline = [baseline_checkout(rev, workdir) for rev in a.baseline_rev or []]
            measured = baseline_checkout(a.rev, workdir) if a.rev else None
            if measured:
                machine["fetchsync"] += f"; measured: the fetchsync of {measured[0]}"
            bench = Bench(
                workdir=workdir,
                ws=ws,
                sshd=sshd,
                params=params,
                log=log,
                baseline=baseline,
                measured=measured,
                side=side,
            )
            try:
                bench.run()
                report = render(bench, machine, ws_info)
                if a.profile:
                    report += "\n" + profile_noop(bench)
            finally:
                bench.close()
        print(report, flush=True)
        if a.json_out:
            a.json_out.write_text(
                json.dumps(
                    {
                        "machine": machine,
                        "params": dataclasses.asdict(params),
                        "load_end": load_average(),
                        "workspace": ws_info,
                        "samples": [
                            dataclasses.asdict(s) | {"bytes": s.bytes} for s in bench.samples
                        ],
                        "summary": {
                            t.name: bench.summary(t.name, "rsync")
                            for t in bench.tools
                            if isinstance(t, FetchsyncPush)
                        },
                        "ab": {
                            t.name: bench.summary("fetchsync", t.name, targets=False)
                            for t in bench.tools
                            if isinstance(t, FetchsyncPush) and t.name.startswith("fetchsync@")
                        },
                        "series": bench.series,
                        "sources": bench.sources,
                        "verification": bench.verified,
                        "repairs": bench.repairs,
                        "failures": bench.failures,
                        "startup": bench.startup,
                        "allocator": bench.allocator,
                        "robot": bench.robot,
                        "owners": bench.owners,
                        "results_rows": [dataclasses.asdict(r) for r in result_rows(bench)],
                        "verified": bench.verified_ok(),
                    },
                    indent=1,
                    sort_keys=True,
                )
                + "\n"
            )
    return 0 if bench.verified_ok() else 1


if __name__ == "__main__":
    sys.exit(main())
