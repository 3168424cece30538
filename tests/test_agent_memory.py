"""The watch agent does not keep a large first sync's freed buffers (issue 24: the agent
<= 100 MB after its first sync of 7,000 files; bench/watch.py's idle case measures that)."""

from __future__ import annotations

import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import helpers
import pytest

HEAP_ALIGN = 64 * 2**20  # glibc's thread heaps (HEAP_MAX_SIZE) start at multiples of this


def thread_heaps_kib(pid: int) -> int:
    """Resident KiB of the process's glibc thread heaps (anonymous, 64 MiB-aligned)."""
    total = 0
    start = None
    for line in Path(f"/proc/{pid}/smaps").read_text().splitlines():
        m = re.match(r"^([0-9a-f]+)-[0-9a-f]+ rw-p 00000000 00:00 0\s*$", line)
        if m:
            start = int(m.group(1), 16)
        elif re.match(r"^[0-9a-f]+-[0-9a-f]+ ", line):
            start = None
        elif line.startswith("Rss:") and start is not None and start % HEAP_ALIGN == 0:
            total += int(line.split()[1])
    return total


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's heaps, /proc")
def test_the_first_syncs_large_buffers_are_not_kept(tmp_path: Path) -> None:
    """A 24 MiB file and 2,000 of 5-40 KB: without the agent's fixed mmap and trim thresholds, glibc
    raises it to the largest buffer freed and keeps the later ones' memory at the top of
    the sync and sender threads' heaps for good (12 MiB here, 2 with it; 34 + 26 MiB
    after 7,000 files / 150 MiB)."""
    runtime = Path(tempfile.mkdtemp(prefix="fsm", dir="/tmp"))  # AF_UNIX paths are short
    runtime.chmod(0o700)
    env = helpers.local_env(tmp_path, XDG_RUNTIME_DIR=str(runtime))
    src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    big = src / "big"
    big.mkdir()
    (big / "map.bag").write_bytes(os.urandom(24 * 2**20))
    rnd = random.Random(1)
    for i in range(2000):
        d = big / f"s{i // 100}"  # after the large file: the order buffers are freed in
        d.mkdir(exist_ok=True)
        (d / f"f{i}.cpp").write_bytes(rnd.randbytes(rnd.randint(5000, 40000)))
    proc = subprocess.Popen(
        [sys.executable, "-m", "fetchsync", "watch"],
        env=env,
        stdout=open(tmp_path / "watch.log", "wb"),
        stderr=subprocess.STDOUT,
    )
    try:
        deadline = time.monotonic() + 120
        while b"live:" not in (tmp_path / "watch.log").read_bytes():
            assert proc.poll() is None, (tmp_path / "watch.log").read_text()
            assert time.monotonic() < deadline, (tmp_path / "watch.log").read_text()
            time.sleep(0.1)
        time.sleep(0.5)  # the compaction after the first sync
        held = thread_heaps_kib(proc.pid)
        assert held < 8 * 1024, f"{held} KiB held in thread heaps"
        # the local robot's endpoint, which the agent keeps running: the same thresholds
        # (protocol/heap.py) keep what it holds small (88-95 MiB resident without, 38 with)
        endpoint = _endpoint_of(proc.pid)
        assert _rss_kib(endpoint) < 60 * 1024, f"the endpoint holds {_rss_kib(endpoint)} KiB"
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(runtime, ignore_errors=True)


def _endpoint_of(pid: int) -> int:
    """The robot endpoint's pid among ``pid``'s descendants (its Python runs the loader)."""
    todo = [pid]
    while todo:
        for child in Path(f"/proc/{todo.pop()}/task").glob("*/children"):
            for c in child.read_text().split():
                cmdline = Path(f"/proc/{c}/cmdline").read_bytes()
                if b"FSYNC-NEED" in cmdline and b"/bin/sh" not in cmdline:  # loader.STUB
                    return int(c)
                todo.append(int(c))
    raise AssertionError(f"no endpoint under {pid}")


def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")
