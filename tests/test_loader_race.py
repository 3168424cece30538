"""Two endpoint starts at once on one robot whose cache lacks this endpoint.

Two laptops, or two pushes of one laptop, start the endpoint of a new fetchsync on a
robot at the same moment. Each finds no extracted tree and extracts one; the first to
finish runs from it, and imports modules from it lazily while it serves (the delta
code at its first delta write). The second must not move that tree away: it waits for
the extraction under way (a lock on the cache directory), then looks again and uses
the tree it finds whole. Leftovers of an extraction that was killed are removed by the
next one, and an extraction that holds the lock too long is not waited for: the start
runs from the checked zip.
"""

from __future__ import annotations

import fcntl
import os
import subprocess
import sys
import time
from pathlib import Path

from fetchsync.protocol import loader, wire

ROOT = str(Path(loader.__file__).parents[2])
TAG = "-" + sys.implementation.cache_tag

# Held right after it found no extracted tree (its first os.path.isdir of the tree said
# no), until the test lets it go: the moment another start may finish its extraction.
HOLD = r"""
import os, os.path, time
_isdir = os.path.isdir
_held = []
def _hold(p):
    r = _isdir(p)
    if not r and not _held and str(p).endswith(%r):
        _held.append(1)
        open(%r, "w").close()
        while not os.path.exists(%r):
            time.sleep(0.01)
    return r
os.path.isdir = _hold
"""


def _args() -> list[str]:
    cmd, _archive = loader.loader_spec(sys.executable)
    words = cmd.split()
    return words[-4:]  # the loader's digest and length, the endpoint's digest and length


def _spawn(home: Path, code: str) -> subprocess.Popen[bytes]:
    env = {"HOME": str(home), "PATH": "/usr/bin:/bin", "PYTHONPATH": ROOT}
    return subprocess.Popen(
        [sys.executable, "-S", "-c", code, *_args()],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
    )


def _serve_until_hello(proc: subprocess.Popen[bytes]) -> bytes:
    """Answer the robot's asks as the client does, until the endpoint's hello."""
    _cmd, archive = loader.loader_spec(sys.executable)
    assert proc.stdout is not None and proc.stdin is not None
    said = b""
    while wire.MAGIC not in said:
        chunk = proc.stdout.read1(1 << 16)
        if not chunk:
            break
        said += chunk
        for need, data in ((loader.NEED_LOADER, loader.LOADER_BYTES), (loader.NEED, b"")):
            if need in said:
                said = said.replace(need, b"", 1)
                proc.stdin.write(data + archive())
                proc.stdin.flush()
    return said


def _read_until_hello(proc: subprocess.Popen[bytes]) -> bytes:
    assert proc.stdout is not None
    said = b""
    while wire.MAGIC not in said:
        chunk = proc.stdout.read1(1 << 16)
        if not chunk:
            break
        said += chunk
    return said


def _end(proc: subprocess.Popen[bytes]) -> tuple[int, bytes]:
    _out, err = proc.communicate(b"", timeout=60)
    return proc.returncode, err


def _wait_for(path: Path, what: str) -> None:
    deadline = time.monotonic() + 60
    while not path.exists():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def _extracted(home: Path) -> Path:
    [x] = [
        p
        for p in (home / ".cache" / "fetchsync").iterdir()
        if p.name.startswith("endpoint-") and p.name.endswith(TAG)
    ]
    return x


def test_a_second_start_does_not_move_away_the_tree_the_first_runs_from(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    paused, go = tmp_path / "paused", tmp_path / "go"
    second = _spawn(home, HOLD % (TAG, str(paused), str(go)) + loader.STUB)
    first = None
    try:
        assert wire.MAGIC not in _serve_until_hello_or(second, paused)
        # the second start found no tree and is about to extract one; the first starts now
        first = _spawn(home, loader.STUB)
        assert wire.MAGIC in _serve_until_hello(first), first.stderr
        x = _extracted(home)
        mark = x / "fetchsync" / "protocol" / "running.txt"  # the user's, 0600: still whole
        mark.write_text("")
        mark.chmod(0o600)
        go.touch()
        assert wire.MAGIC in _read_until_hello(second)
        code, err = _end(second)
        assert code == 0, err
        # the first endpoint's tree is where it was, whole: its lazy imports still work
        assert mark.exists()
        assert (x / "fetchsync" / "protocol" / "delta.py").is_file()
        assert [p.name for p in x.parent.iterdir() if p.name.endswith((".tmp", ".old"))] == []
        code, err = _end(first)
        assert code == 0, err
    finally:
        go.touch()
        for proc in (first, second):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.communicate()


def _serve_until_hello_or(proc: subprocess.Popen[bytes], paused: Path) -> bytes:
    """Answer the asks of a start that will hold (see HOLD) until it holds."""
    _cmd, archive = loader.loader_spec(sys.executable)
    assert proc.stdout is not None and proc.stdin is not None
    proc.stdin.write(loader.LOADER_BYTES + archive())  # it asks for both: a fresh robot
    proc.stdin.flush()
    _wait_for(paused, "the second start to find no tree")
    return b""


def test_a_killed_extractions_leftovers_go_at_the_next_extraction(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    assert wire.MAGIC in _serve_until_hello(p := _spawn(home, loader.STUB))
    assert _end(p)[0] == 0
    x = _extracted(home)
    # what an extraction killed midway leaves, and a tree to extract again
    left = x.parent / (x.name + ".99999.tmp")
    (left / "fetchsync").mkdir(parents=True)
    (left / "fetchsync" / "half.py").write_text("")
    subprocess.run(["rm", "-rf", str(x)], check=True)
    assert wire.MAGIC in _serve_until_hello(p := _spawn(home, loader.STUB))
    assert _end(p)[0] == 0
    assert not left.exists()
    assert (_extracted(home) / "fetchsync" / "protocol" / "delta.py").is_file()


def test_an_extraction_holding_the_lock_too_long_is_not_waited_for(tmp_path):
    """Another start's extraction that stalls (a stopped process, a hung disk) holds the
    cache's lock: a start runs from the checked zip instead, without extracting."""
    home = tmp_path / "home"
    home.mkdir()
    assert wire.MAGIC in _serve_until_hello(p := _spawn(home, loader.STUB))
    assert _end(p)[0] == 0
    x = _extracted(home)
    subprocess.run(["rm", "-rf", str(x)], check=True)
    fd = os.open(x.parent, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        p = _spawn(home, loader.STUB)
        assert wire.MAGIC in _serve_until_hello(p)
        assert _end(p)[0] == 0
        assert not x.exists()  # it ran from the zip
    finally:
        os.close(fd)
    assert wire.MAGIC in _serve_until_hello(p := _spawn(home, loader.STUB))
    assert _end(p)[0] == 0
    assert (x / "fetchsync" / "protocol" / "delta.py").is_file()


def test_many_first_starts_at_once_all_run_and_leave_one_whole_tree(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    from concurrent.futures import ThreadPoolExecutor

    procs = [_spawn(home, loader.STUB) for _ in range(6)]
    with ThreadPoolExecutor(len(procs)) as pool:
        said = list(pool.map(_serve_until_hello, procs))
    for proc, hello in zip(procs, said):
        code, err = _end(proc)
        assert code == 0 and wire.MAGIC in hello, err
    x = _extracted(home)
    assert (x / "fetchsync" / "protocol" / "delta.py").is_file()
    assert [p.name for p in x.parent.iterdir() if p.name.endswith((".tmp", ".old"))] == []
