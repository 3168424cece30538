"""Durability: what the robot reported written survives the robot's power cut.

The endpoint of the built-in ``local`` robot (the real robot-side code, over
pipes) is checked two ways:

- Syscall order, under ``strace -f``: every rename of a temporary into place
  comes after a sync that follows the last write of that temporary; every
  change under ``src/`` (rename, unlink, mkdir, symlink, chmod, a move to the
  trash or the conflicts) is covered by a sync before the next frame leaves on
  the channel, so no reply reports what a power cut could take back; and none
  is left unsynced when the endpoint ends. A sync is ``syncfs``/``sync`` (the
  whole filesystem) or ``fsync``/``fdatasync`` of the file or of the directory
  holding the entry. ``index.json`` and the batch marker are left out on
  purpose: an index a power cut takes back only costs the next push a full
  listing (its generation goes back, the client sees it stale).
  A run with ``syncfs`` made a no-op (an LD_PRELOAD shim) shows the checker
  catches a missing sync.
- A power cut, on an ext4 loop device: the robot's home is a fresh ext4
  filesystem (journal commit every 600 s, so nothing reaches the device unless
  someone syncs); right after the push reports success the device image is
  copied (checking the device saw no write during the copy), then the copy is
  mounted (journal replay) and must hold every reported file, complete. Runs
  where root can use loop devices; ``FETCHSYNC_TEST_POWERCUT=1`` makes it
  mandatory and larger. The same cut with the no-op ``syncfs`` must lose the
  push, which shows the simulation can fail. (device-mapper's dm-flakey or
  dm-log-writes would drop writes at the block layer; this kernel has no
  device-mapper, and the copy-at-success is the same cut for a disk without a
  volatile cache.) The same disk, with the journal committing every second,
  checks that the endpoint the loader caches in ``~/.cache/fetchsync``
  survives a cut after the robot's first connection.

Gaps these tests found, now fixed: a batch that only deleted, made
directories or changed modes was not synced before its reply, and the loader
cached the endpoint without an fsync (a cut could leave it empty).
"""

from __future__ import annotations

import codecs
import contextlib
import ctypes
import os
import random
import re
import shutil
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import pytest
from helpers import fetchsync, local_env, report, ssh_env, tree_of

TEMP_MARK = ".fetchsync-tmp-"
MAGIC = b"\x89FSYNC"
POWERCUT = bool(os.environ.get("FETCHSYNC_TEST_POWERCUT"))

TRACED = (
    "write,pwrite64,writev,openat,fchmod,ftruncate,rename,renameat,renameat2,unlink,unlinkat,"
    "rmdir,mkdir,mkdirat,symlink,symlinkat,link,linkat,chmod,fchmodat,syncfs,sync,fsync,fdatasync"
)

SHIM_C = """\
/* the endpoint without its durability: syncfs does nothing, and O_DIRECT is
   refused (as tmpfs refuses it), so what it writes reaches the disk only when
   someone else syncs */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <fcntl.h>
#include <stdarg.h>
int syncfs(int fd) { (void)fd; return 0; }
static int forward(const char *name, int fd, int cmd, long arg) {
    int (*real)(int, int, ...) = (int (*)(int, int, ...))dlsym(RTLD_NEXT, name);
    if (cmd == F_SETFL && (arg & O_DIRECT)) { errno = EINVAL; return -1; }
    return real(fd, cmd, arg);
}
int fcntl(int fd, int cmd, ...) {
    va_list ap; va_start(ap, cmd); long arg = va_arg(ap, long); va_end(ap);
    return forward("fcntl", fd, cmd, arg);
}
int fcntl64(int fd, int cmd, ...) {
    va_list ap; va_start(ap, cmd); long arg = va_arg(ap, long); va_end(ap);
    return forward("fcntl64", fd, cmd, arg);
}
"""


# ---------------------------------------------------------------------- tools
def _need(tool: str) -> str:
    found = shutil.which(
        tool, path=os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/sbin"])
    )
    if found is None:
        if os.environ.get("CI"):
            pytest.fail(f"{tool} is not installed (it belongs in .ci/run's APT_PACKAGES)")
        pytest.skip(f"needs {tool}")
    return found


SLOW_SHIM_C = """\
/* syncfs that returns 80 ms late, as on a robot's SD card: the robot falls
   behind the laptop, so the next request is always waiting when one ends */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <time.h>
int syncfs(int fd) {
    static int (*real)(int);
    struct timespec t = {0, 80 * 1000 * 1000};
    if (!real) real = (int (*)(int))dlsym(RTLD_NEXT, "syncfs");
    int r = real(fd);
    nanosleep(&t, 0);
    return r;
}
"""


def _shim(tmp_path_factory: pytest.TempPathFactory, name: str, source: str) -> Path:
    """A shared object built from ``source``, for LD_PRELOAD."""
    cc = shutil.which("gcc") or shutil.which("cc") or _need("gcc")
    d = tmp_path_factory.mktemp("shim")
    (d / f"{name}.c").write_text(source)
    subprocess.run(
        [cc, "-shared", "-fPIC", "-O2", "-o", str(d / f"{name}.so"), str(d / f"{name}.c"), "-ldl"],
        check=True,
        capture_output=True,
    )
    return d / f"{name}.so"


@pytest.fixture(scope="module")
def nosyncfs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A shared object whose syncfs is a no-op, for LD_PRELOAD."""
    return _shim(tmp_path_factory, "nosyncfs", SHIM_C)


@pytest.fixture(scope="module")
def slowsyncfs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A shared object whose syncfs returns 80 ms after the real one, for LD_PRELOAD."""
    return _shim(tmp_path_factory, "slowsyncfs", SLOW_SHIM_C)


def push(env: dict, *, python: str | None = None, preload: Path | None = None) -> dict:
    e = dict(env)
    prefix = f"env LD_PRELOAD={preload} " if preload else ""
    if python or preload:
        e["FETCHSYNC_REMOTE_PYTHON"] = prefix + (python or "python3")
    r = report(fetchsync("push", "--json", env=e))
    assert r["ok"], r
    return r


# ---------------------------------------------------------------------- trace
@dataclass
class Call:
    pid: int
    name: str
    args: str
    ret: str
    start: int  # line index of entry
    end: int  # line index of exit

    @property
    def ok(self) -> bool:
        return not self.ret.startswith("-1") and not self.ret.startswith("?")

    def operands(self) -> list[tuple[str, str]]:
        """("fd", path) for an annotated descriptor, ("str", text) for a quoted string, in order."""
        out = []
        for m in _OPERAND.finditer(self.args):
            if m.group(1) is not None:
                out.append(("str", _unescape(m.group(1))))
            else:
                out.append(("fd", m.group(3) if m.group(3) is not None else os.getcwd()))
        return out

    def paths(self) -> list[str]:
        """The paths the call names, joined with their directory descriptors."""
        out, base = [], None
        for kind, value in self.operands():
            if kind == "fd":
                base = value
                continue
            if self.name in ("write", "pwrite64", "writev"):
                break  # data, not a path
            out.append(
                value if value.startswith("/") or base is None else os.path.join(base, value)
            )
            base = None
        return out

    def fd_path(self) -> str:
        ops = self.operands()
        return ops[0][1] if ops and ops[0][0] == "fd" else ""


_OPERAND = re.compile(r'"((?:[^"\\]|\\.)*)"|(\d+|AT_FDCWD)(?:<([^>]*)>)?')
_LINE = re.compile(r"^(\d+)\s+\d\d:\d\d:\d\d\.\d+\s+(.*)$")
_FULL = re.compile(r"^(\w+)\((.*)\)\s+=\s+(.*)$")
_UNFINISHED = re.compile(r"^(\w+)\((.*?)\s*<unfinished \.\.\.>$")
_RESUMED = re.compile(r"^<\.\.\. (\w+) resumed>(.*)\)\s+=\s+(.*)$")


def _unescape(s: str) -> str:
    return codecs.escape_decode(s.encode("utf-8", "surrogateescape"))[0].decode(
        "utf-8", "surrogateescape"
    )


def parse_trace(text: str) -> list[Call]:
    calls: list[Call] = []
    open_calls: dict[int, tuple[str, str, int]] = {}
    for i, line in enumerate(text.splitlines()):
        m = _LINE.match(line)
        if not m:
            continue
        pid, rest = int(m.group(1)), m.group(2)
        if rest.startswith(("+++", "---")):
            continue
        if f := _FULL.match(rest):
            calls.append(Call(pid, f.group(1), f.group(2), f.group(3), i, i))
        elif u := _UNFINISHED.match(rest):
            open_calls[pid] = (u.group(1), u.group(2), i)
        elif r := _RESUMED.match(rest):
            name, args, start = open_calls.pop(pid, (r.group(1), "", i))
            calls.append(Call(pid, name, args + r.group(2), r.group(3), start, i))
    calls.sort(key=lambda c: c.end)
    return calls


def is_temp(path: str) -> bool:
    name = os.path.basename(path)
    return TEMP_MARK in name or name.startswith("upload-")


MUTATIONS = {
    "rename",
    "renameat",
    "renameat2",
    "unlink",
    "unlinkat",
    "rmdir",
    "mkdir",
    "mkdirat",
    "symlink",
    "symlinkat",
    "link",
    "linkat",
    "chmod",
    "fchmodat",
}
DATA = {"write", "pwrite64", "writev", "fchmod", "ftruncate"}


@dataclass
class Verdict:
    violations: list[str] = field(default_factory=list)
    temp_renames: int = 0
    mutations: dict[str, int] = field(default_factory=dict)  # syscall -> count in scope
    changes: list[tuple[str, ...]] = field(default_factory=list)  # (syscall, path, ...) in scope
    syncs: int = 0
    syncfs: int = 0
    replies: int = 0
    overlapped: int = 0  # temporaries made while a syncfs ran (the endpoint's pipeline)


def check_order(calls: list[Call], workspace: str) -> Verdict:
    """Check the endpoint's trace against the durability rules (see the module docstring)."""
    src = workspace.rstrip("/") + "/src/"
    kept = (
        workspace.rstrip("/") + "/.fetchsync/trash/",
        workspace.rstrip("/") + "/.fetchsync/conflicts/",
    )
    v = Verdict()
    touched: dict[str, int] = {}  # temporary -> line of its last write
    syncs: list[Call] = []  # completed syncs, in order of completion
    pending: list[tuple[Call, list[str]]] = []  # changes not yet covered: (call, paths)
    channel = None

    def in_scope(p: str) -> bool:
        return p.startswith(src) or p.startswith(kept)

    def covers(s: Call, paths: list[str]) -> bool:
        if s.name in ("syncfs", "sync"):
            return True
        target = s.fd_path()
        return any(target in (p, os.path.dirname(p)) for p in paths)

    for c in calls:
        if c.name in ("syncfs", "sync", "fsync", "fdatasync"):
            if c.ok:
                v.syncs += 1
                v.syncfs += c.name == "syncfs"
                syncs.append(c)
                pending = [(m, ps) for m, ps in pending if not (m.end < c.start and covers(c, ps))]
            continue
        if c.name in ("write", "writev", "pwrite64"):
            target = c.fd_path()
            ops = c.operands()
            data = ops[1][1] if len(ops) > 1 and ops[1][0] == "str" else ""
            if channel is None and data.encode("utf-8", "surrogateescape").startswith(MAGIC):
                channel = target
            if channel is not None and target == channel:
                v.replies += 1
                for m, ps in pending:
                    if m.end < c.start:
                        v.violations.append(
                            f"reply at line {c.start} leaves before a sync of "
                            f"{m.name}{tuple(ps)} (line {m.end})"
                        )
                pending = [(m, ps) for m, ps in pending if m.end >= c.start]
                continue
        if not c.ok:
            continue
        if c.name == "fchmod" and not is_temp(c.fd_path()) and in_scope(c.fd_path()):
            # a mode changed through a descriptor of the entry itself
            v.mutations[c.name] = v.mutations.get(c.name, 0) + 1
            v.changes.append((c.name, c.fd_path()))
            pending.append((c, [c.fd_path()]))
            continue
        if c.name in DATA or (c.name == "openat" and "O_CREAT" in c.args):
            target = c.fd_path() if c.name in DATA else _ret_path(c)
            if is_temp(target):
                touched[target] = c.end
            continue
        if c.name not in MUTATIONS:
            continue
        ps = c.paths()
        if c.name in ("symlink",):
            ps = ps[1:]  # the target is not a path here
        elif c.name == "symlinkat":
            ps = ps[1:]
        final = ps[-1] if ps else ""
        if is_temp(final):
            # a temporary made (a symlink, an upload part renamed): its
            # content counts from here, like a write
            touched[final] = max(c.end, touched.get(ps[0], -1) if len(ps) > 1 else -1)
            continue
        if c.name.startswith("rename") and is_temp(ps[0]) and in_scope(final):
            v.temp_renames += 1
            wrote = touched.get(ps[0])
            if wrote is None:
                v.violations.append(
                    f"rename of {ps[0]} at line {c.start}: its writes are not in the trace"
                )
            elif not any(s.start > wrote and s.end < c.start and covers(s, [ps[0]]) for s in syncs):
                v.violations.append(
                    f"rename of {ps[0]} into place at line {c.start} before a sync "
                    f"of its content (last written at line {wrote})"
                )
        if any(in_scope(p) for p in ps):
            v.mutations[c.name] = v.mutations.get(c.name, 0) + 1
            v.changes.append((c.name, *ps))
            pending.append((c, ps))
    for m, ps in pending:
        v.violations.append(f"{m.name}{tuple(ps)} at line {m.end} is never synced")
    v.overlapped = _overlapped(calls)
    if channel is None:
        v.violations.append("no frame on the channel found in the trace")
    return v


def _overlapped(calls: list[Call]) -> int:
    """Temporaries made while an earlier one still waited for its rename although a
    syncfs had begun after it: a batch written during the commit of the one before.
    (One batch at a time makes all its temporaries, syncs, renames them all.)"""
    waiting: dict[str, int] = {}  # temporary -> line it was made
    sync_starts: list[int] = []
    n = 0
    for c in sorted(calls, key=lambda c: c.start):
        if not c.ok:
            continue
        if c.name == "syncfs":
            sync_starts.append(c.start)
        elif (
            c.name == "openat"
            and "O_CREAT" in c.args
            and TEMP_MARK in os.path.basename(_ret_path(c))
        ):
            if waiting and any(min(waiting.values()) < s < c.start for s in sync_starts):
                n += 1
            waiting[_ret_path(c)] = c.start
        elif c.name.startswith(("rename", "unlink")) and c.paths():
            waiting.pop(c.paths()[0], None)
    return n


def _ret_path(c: Call) -> str:
    m = re.match(r"\d+<([^>]*)>", c.ret)
    return m.group(1) if m else ""


def traced_push(
    env: dict, trace: Path, *, preload: Path | None = None, workspace: Path | None = None
) -> tuple[dict, Verdict]:
    strace = _need("strace")
    python = f"{strace} -f -tt -y -s 8 -e trace={TRACED} -o {trace} python3"
    r = push(env, python=python, preload=preload)
    workspace = workspace or Path(env["FETCHSYNC_LOCAL_ROBOT_HOME"]) / "robot_ws"
    return r, check_order(parse_trace(trace.read_text()), str(workspace))


# ---------------------------------------------------------------------- syscall order
@pytest.fixture
def env(tmp_path: Path) -> dict:
    return local_env(tmp_path)


def robot_src(env: dict) -> Path:
    return Path(env["FETCHSYNC_LOCAL_ROBOT_HOME"]) / "robot_ws" / "src"


def local_src(env: dict) -> Path:
    return Path(env["FETCHSYNC_WORKSPACE"]) / "src"


def test_initial_push_renames_after_sync_and_replies_after_the_last_sync(env, tmp_path):
    r, v = traced_push(env, tmp_path / "trace")
    assert r["files"] == 5 and r["links"] == 2 and r["dirs"] == 4
    assert v.violations == []
    assert v.temp_renames == 7  # 5 files and 2 symlinks went through temporaries
    assert (
        v.mutations.get("mkdir", 0) + v.mutations.get("mkdirat", 0) == 4
        and v.syncs >= 2
        and v.replies >= 3
    )
    assert tree_of(local_src(env)) == tree_of(robot_src(env))


def test_mixed_push_with_deletes_links_dirs_and_a_conflict(env, tmp_path):
    push(env)
    src, robot = local_src(env), robot_src(env)
    (robot / "my_pkg/src/node.cpp").write_text("edited on the robot\n")  # kept in conflicts/
    (src / "my_pkg/src/node.cpp").write_text("edited on the laptop\n")
    data = src / "my_pkg/data.txt"
    data.write_text("// new first line\n" + data.read_text())  # a delta
    (src / "my_pkg/package.xml").unlink()  # a delete
    shutil.rmtree(src / "my_pkg/scripts")  # a directory deleted
    (src / "my_pkg/config").mkdir()  # a new directory
    (src / "my_pkg/config/a.yaml").write_text("a: 1\n")
    (src / "my_pkg/launch/link.launch").symlink_to("../config/a.yaml")  # a new symlink
    (src / "my_pkg/CMakeLists.txt").chmod(0o600)  # a chmod
    r, v = traced_push(env, tmp_path / "trace")
    assert r["deleted"] == 2 and r["deltas"] == 1 and len(r["conflicts"]) == 1
    assert v.violations == []
    assert v.temp_renames == 4  # node.cpp, data.txt, a.yaml, link.launch
    # the conflict is kept by a link made once its replacement is durable, the deletes moved
    aside = [
        c[2].split("/.fetchsync/")[1].split("/")[0]
        for c in v.changes
        if c[0].startswith(("rename", "link")) and "/.fetchsync/" in c[2]
    ]
    assert sorted(aside) == ["conflicts", "trash", "trash"]
    assert ("mkdirat", str(robot / "my_pkg/config")) in v.changes
    assert ("fchmod", str(robot / "my_pkg/CMakeLists.txt")) in v.changes
    assert tree_of(src) == tree_of(robot)


def test_large_file_in_pieces_is_synced_before_its_reply(env, tmp_path):
    big = local_src(env) / "my_pkg/big.bin"
    with open(big, "wb") as fh:  # above the 32 MiB upload size: several batches
        fh.writelines(bytes([i]) * (1 << 20) for i in range(33))
    r, v = traced_push(env, tmp_path / "trace")
    assert r["files"] == 6
    assert v.violations == []
    assert v.replies >= 6
    assert (robot_src(env) / "my_pkg/big.bin").read_bytes() == big.read_bytes()


def test_many_batches_keep_every_rule(env, tmp_path, slowsyncfs):
    """Many batches, the next request always waiting (each syncfs returns 80 ms late):
    each rename still follows a sync of its content, and each reply a sync begun
    after its renames."""
    bulk = local_src(env) / "my_pkg/bulk"
    bulk.mkdir()
    rnd = random.Random(5)
    for i in range(48):  # 24 MiB that zlib cannot shrink: six batches
        (bulk / f"f{i:02d}.bin").write_bytes(rnd.randbytes(512 * 1024))
    r, v = traced_push(env, tmp_path / "trace", preload=slowsyncfs)
    assert r["files"] == 5 + 48
    assert v.violations == []
    assert tree_of(local_src(env)) == tree_of(robot_src(env))


@pytest.mark.slow
@pytest.mark.ssh
def test_push_over_ssh_replies_after_the_last_sync(ssh_home, remote_dir, tmp_path):
    """The same order when sshd starts the endpoint, as on a real robot."""
    # no connection master: each push starts its own endpoint, under strace
    e = ssh_env(ssh_home.home, remote_dir, tmp_path, FETCHSYNC_PERSIST="0")
    src = tmp_path / "ws" / "src"
    _r, v = traced_push(e, tmp_path / "trace1", workspace=remote_dir)
    assert v.violations == [] and v.temp_renames == 7
    (src / "my_pkg/package.xml").unlink()
    (src / "my_pkg/src/node.cpp").write_text("edited\n")
    (src / "my_pkg/more").mkdir()
    _r, v = traced_push(e, tmp_path / "trace2", workspace=remote_dir)
    assert v.violations == [] and v.temp_renames == 1
    assert any(c[0].startswith("rename") and "/.fetchsync/trash/" in c[2] for c in v.changes)
    assert tree_of(src) == tree_of(remote_dir / "src")


def _only_deletes(src: Path) -> None:
    (src / "my_pkg/package.xml").unlink()


def _only_mkdir(src: Path) -> None:
    (src / "my_pkg/empty_dir").mkdir()


def _only_chmod(src: Path) -> None:
    (src / "my_pkg/src/node.cpp").chmod(0o600)


@pytest.mark.parametrize(
    "change",
    [
        pytest.param(_only_deletes, id="deletes"),
        pytest.param(_only_mkdir, id="mkdir"),
        pytest.param(_only_chmod, id="chmod"),
    ],
)
def test_a_batch_without_writes_is_synced_before_its_reply(env, tmp_path, change):
    push(env)
    change(local_src(env))
    _r, v = traced_push(env, tmp_path / "trace")
    assert sum(v.mutations.values()) >= 1
    assert v.violations == []
    assert tree_of(local_src(env)) == tree_of(robot_src(env))


def test_the_checker_catches_a_push_without_syncfs(env, tmp_path, nosyncfs):
    _r, v = traced_push(env, tmp_path / "trace", preload=nosyncfs)
    assert v.syncfs == 0
    assert any("before a sync of its content" in x for x in v.violations)
    assert any(x.startswith("reply at line") for x in v.violations)


# ---------------------------------------------------------------------- power cut
@dataclass
class Disk:
    image: Path
    device: str
    mount: Path

    def writes(self) -> tuple[int, int]:
        """(write I/Os, sectors written) the device has completed."""
        fields = Path(f"/sys/block/{os.path.basename(self.device)}/stat").read_text().split()
        return int(fields[4]), int(fields[6])

    def settle(self) -> None:
        """Make everything so far durable: the cut under test must only concern what follows."""
        fd = os.open(self.mount, os.O_RDONLY)
        try:
            ctypes.CDLL(None, use_errno=True).syncfs(fd)
        finally:
            os.close(fd)


def _sh(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(list(args), check=False, capture_output=True, text=True, timeout=60)


def _unavailable(why: str) -> None:
    if POWERCUT:
        pytest.fail(f"FETCHSYNC_TEST_POWERCUT is set but {why}")
    pytest.skip(why)


@contextlib.contextmanager
def loop_ext4(image: Path, mount: Path, *, options: str = "") -> Iterator[str]:
    """``image`` attached to a free loop device and mounted on ``mount``; yields the device."""
    res = _sh(_need("losetup"), "-f", "--show", str(image))
    if res.returncode != 0:
        _unavailable(f"no loop device: losetup -f --show: {res.stderr.strip()}")
    device = res.stdout.strip()
    try:
        mount.mkdir(parents=True, exist_ok=True)
        res = _sh("mount", *(["-o", options] if options else []), device, str(mount))
        if res.returncode != 0:
            _unavailable(f"cannot mount a loop device: mount: {res.stderr.strip()}")
        try:
            yield device
        finally:
            for _ in range(50):  # a process that had a file there may still be exiting
                res = _sh("umount", str(mount))
                if res.returncode == 0:
                    break
                time.sleep(0.1)
            else:
                _sh("umount", "-l", str(mount))
                pytest.fail(f"cannot unmount {mount}: {res.stderr.strip()}")
    finally:
        _sh(_need("losetup"), "-d", device)


@contextlib.contextmanager
def robot_disk(tmp_path: Path, options: str) -> Iterator[Disk]:
    """A fresh ext4 filesystem on a loop device, mounted with ``options``."""
    if os.geteuid() != 0:
        _unavailable("loop devices and mount need root")
    size_mb = 256 if POWERCUT else 64
    image = tmp_path / "robot.img"
    with open(image, "wb") as fh:
        fh.truncate(size_mb << 20)
    # every table written now: no lazy init thread writing to the device later
    res = _sh(
        _need("mkfs.ext4"), "-q", "-F", "-E", "lazy_itable_init=0,lazy_journal_init=0", str(image)
    )
    assert res.returncode == 0, res.stderr
    with loop_ext4(image, tmp_path / "robot-disk", options=options) as device:
        yield Disk(image, device, tmp_path / "robot-disk")


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Disk]:
    # commit=600: the journal commits only when someone syncs, within a test;
    # noauto_da_alloc: no flush of a file's data when a rename replaces
    # another, so nothing reaches the device by the side of a sync
    with robot_disk(tmp_path, "commit=600,noauto_da_alloc") as d:
        yield d


def cut_power(d: Disk, tmp_path: Path, name: str) -> dict:
    """The tree of ``robot/robot_ws/src`` as it would come back after a power cut now.

    The device image is copied while the device is idle (its write counters
    unchanged across the copy: a consistent image of what reached the disk),
    then mounted, which replays the journal like a reboot does.
    """
    snap = tmp_path / f"{name}.img"
    for _attempt in range(5):
        before = d.writes()
        shutil.copyfile(d.image, snap)
        if d.writes() == before:
            break
    else:
        pytest.skip("the robot's disk was never idle long enough to copy a consistent image")
    with loop_ext4(snap, tmp_path / f"{name}-mnt"):
        src = tmp_path / f"{name}-mnt" / "robot" / "robot_ws" / "src"
        tree = tree_of(src) if src.is_dir() else {}
    snap.unlink()
    return tree


def _edit(src: Path, n: int) -> None:
    """A push's worth of changes: files written whole and by delta, a symlink, a directory."""
    d = src / f"pkg_{n}"
    d.mkdir()
    for i in range(40 if POWERCUT else 5):
        (d / f"f{i}.cpp").write_text(f"// file {i} of edit {n}\n" * (i + 1))
    (d / "link").symlink_to("f0.cpp")
    data = src / "my_pkg/data.txt"
    data.write_text(f"// edit {n}\n" + data.read_text())


def test_power_cut_right_after_success_keeps_every_reported_file(tmp_path, disk):
    env = local_env(tmp_path, FETCHSYNC_LOCAL_ROBOT_HOME=str(disk.mount / "robot"))
    src = local_src(env)
    rounds = 4 if POWERCUT else 2
    for n in range(rounds):
        if n:
            _edit(src, n)
        disk.settle()
        push(env)
        assert cut_power(disk, tmp_path, f"cut{n}") == tree_of(src), (
            f"push {n} lost data in a power cut"
        )


def test_power_cut_without_syncfs_loses_the_push(tmp_path, disk, nosyncfs):
    """The simulation can fail: the endpoint with syncfs made a no-op loses what it reported."""
    env = local_env(tmp_path, FETCHSYNC_LOCAL_ROBOT_HOME=str(disk.mount / "robot"))
    src = local_src(env)
    push(env)
    for n in range(1, 4):
        _edit(src, n)
        disk.settle()
        before = disk.writes()
        push(env, preload=nosyncfs)
        if disk.writes() != before:
            continue  # someone synced every filesystem meanwhile (sync(1)): try again
        after = cut_power(disk, tmp_path, f"cut{n}")
        assert f"pkg_{n}/f0.cpp" not in after and after != tree_of(src)
        return
    pytest.skip("the robot's disk was flushed by someone else during every push")


@pytest.mark.parametrize(
    "change",
    [
        pytest.param(_only_deletes, id="deletes"),
        pytest.param(_only_mkdir, id="mkdir"),
    ],
)
def test_power_cut_after_a_batch_without_writes(tmp_path, disk, change):
    env = local_env(tmp_path, FETCHSYNC_LOCAL_ROBOT_HOME=str(disk.mount / "robot"))
    src = local_src(env)
    push(env)
    change(src)
    disk.settle()
    push(env)
    assert cut_power(disk, tmp_path, "cut") == tree_of(src)


def _start_endpoint(home: Path) -> bytes:
    """Run the loader as the client does, on a robot without fetchsync installed; its first bytes."""
    from fetchsync.protocol.loader import NEED, loader_command

    cmd, archive = loader_command("python3 -S")  # -S: no installed fetchsync to fall back on
    env = {"HOME": str(home), "PATH": os.environ.get("PATH", "/usr/bin:/bin")}
    proc = subprocess.Popen(
        ["/bin/sh", "-c", cmd],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        cwd=str(home),
    )
    assert proc.stdin is not None and proc.stdout is not None
    first = proc.stdout.read(len(NEED))
    if first == NEED:
        proc.stdin.write(archive)
        proc.stdin.flush()
        first = proc.stdout.read(len(MAGIC))
    proc.stdin.close()  # the endpoint ends at end of input
    proc.stdout.read()
    proc.wait(timeout=30)
    return first[: len(MAGIC)]


def test_power_cut_after_the_endpoint_is_cached_leaves_a_working_robot(tmp_path):
    # commit=1: the journal commits on its own within a second, as ext4's
    # default 5 s would between a robot's first connection and a power cut
    with robot_disk(tmp_path, "commit=1") as d:
        home = d.mount / "robot"
        home.mkdir()
        d.settle()
        assert _start_endpoint(home) == MAGIC
        cached = list((home / ".cache/fetchsync").glob("endpoint-*.pyz"))
        assert len(cached) == 1 and cached[0].stat().st_size > 0
        before = d.writes()
        for _ in range(50):  # until the journal has committed the new file
            time.sleep(0.1)
            if d.writes() != before:
                break
        time.sleep(0.3)
        snap = tmp_path / "cut.img"
        shutil.copyfile(d.image, snap)
        with loop_ext4(snap, tmp_path / "cut-mnt"):
            home_after = tmp_path / "cut-mnt" / "robot"
            assert _start_endpoint(home_after) == MAGIC, (
                "the robot cannot start the endpoint after the cut"
            )
