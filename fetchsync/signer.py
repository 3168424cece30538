"""Signing a push's text files after the push has returned.

The next edit of a text file is sent as a delta against the delta signature
the laptop kept of what it sent (see :mod:`fetchsync.state`). A first push of
a large tree sends hundreds of such files, and signing them is a fifth of the
laptop's CPU in that push. It cannot overlap the transfer (the laptop's CPU is
the limit while batches stream), and done at the end it competed with the
robot's last batches and with reading the robot's answers: on a machine whose
cores the robot shares (the ``local`` robot, the benchmark), the push took
about 5% longer than without it (the median of 40 interleaved rounds of a
7,000-file initial push; see bench/README.md).

So a one-shot push hands those files to a process of its own, started once the
state is committed (``python -m fetchsync.signer JOB_FD JOB_PATH PARENT_FD``),
at a lower priority, which begins once the push has exited. It reads each file
again (from the page cache, as a rule), keeps a signature only for content
whose hash is the one the state holds for that path, and writes them in one
transaction. A file edited meanwhile gets none; its next edit then asks the
robot to sign its copy, as any unsigned file does.

The job is a JSON file beside the state, held under an exclusive ``flock`` from
before the process starts until it ends (the lock is inherited with the file
descriptor). A later push of the same state waits for it (see :func:`wait`),
boundedly, so it sends deltas as if the signing had been done in the push; a
job whose process died is removed by that push.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import select
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterable, Iterator

log = logging.getLogger(__name__)

Item = tuple[str, str, int]  # path, content hash, size: what the push sent there
WAIT_MAX = 10.0  # seconds a push waits for the signing left by the one before
NICE = 10  # the signer yields the CPU to whatever the user does next
PARENT_WAIT = 5.0  # seconds the signer waits for the push that started it to exit
_parent_end = None  # our end of the pipe the signer waits on: closed when this process exits


def job_prefix(state_path: Path) -> str:
    return f".{state_path.name}.sign-"


def start(state_path: Path, root: str, algorithm: str, items: list[Item]) -> bool:
    """Start signing ``items`` (files under ``root``) in the background; False if it
    could not start (the caller signs them itself)."""
    try:
        fd, job = tempfile.mkstemp(prefix=job_prefix(state_path), suffix=".json",
                                   dir=state_path.parent)
    except OSError as exc:
        log.debug("no signing job: %s", exc)
        return False
    global _parent_end
    r = -1
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.write(fd, json.dumps({"state": str(state_path), "root": root, "algorithm": algorithm,
                                 "items": items}).encode("utf-8", "surrogateescape"))
        r, w = os.pipe()  # the signer starts its work once this process has ended (see main)
        subprocess.Popen([sys.executable, "-m", "fetchsync.signer", str(fd), job, str(r)], pass_fds=(fd, r),
                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL, start_new_session=True)
    except OSError as exc:
        log.debug("the signer did not start: %s", exc)
        _remove(job)
        return False
    finally:
        os.close(fd)  # the lock stays with the signer's copy of the descriptor
        if r >= 0:
            os.close(r)
    if _parent_end is not None:
        os.close(_parent_end)
    _parent_end = w
    return True


def wait(state_path: Path, timeout: float = WAIT_MAX) -> None:
    """Wait until no signing of ``state_path`` is under way (at most ``timeout``
    seconds); remove the jobs whose process is gone."""
    try:
        names = [e.name for e in os.scandir(state_path.parent)
                 if e.name.startswith(job_prefix(state_path))]
    except OSError:
        return
    deadline = time.monotonic() + timeout
    for name in names:
        path = state_path.parent / name
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            continue  # done meanwhile
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() >= deadline:
                        log.debug("the signing of %s is still under way; not waiting longer", state_path)
                        return
                    time.sleep(0.01)
            _remove(str(path))  # unlocked and still there: its process died
        finally:
            os.close(fd)


def sign_files(root: str, algorithm: str, items: Iterable[Item]) -> Iterator[tuple[str, str, bytes]]:
    """``(path, hash, signature)`` for each of ``items`` whose file under ``root`` still
    holds the content with that hash."""
    from fetchsync.protocol import delta as delta_mod
    from fetchsync.protocol import hashing
    from fetchsync.sync import read_stable

    for path, digest, size in items:
        try:
            data, _entry = read_stable(os.path.join(root, path), tries=1)
        except OSError:
            continue
        if len(data) != size or hashing.digest(algorithm, data).hex() != digest:
            continue
        yield path, digest, delta_mod.signature(data, algorithm=algorithm).to_bytes()


def _remove(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def main(argv: list[str]) -> int:
    """``JOB_FD JOB_PATH PARENT_FD``: the job's descriptor (locked), its path (removed at
    the end), and a pipe that ends when the push that started this one exits."""
    fd, path, parent = int(argv[1]), argv[2], int(argv[3])
    try:
        os.nice(NICE)
    except OSError:
        pass
    # the push's last steps (closing its connection, its exit) go first
    select.select([parent], [], [], PARENT_WAIT)
    os.close(parent)
    try:
        with os.fdopen(fd, "rb", closefd=False) as fh:
            fh.seek(0)
            job = json.loads(fh.read().decode("utf-8", "surrogateescape"))
        from fetchsync.state import State

        rows = list(sign_files(job["root"], job["algorithm"], (tuple(x) for x in job["items"])))
        if not os.path.exists(job["state"]):
            return 0  # removed meanwhile: not ours to make again
        state = State(Path(job["state"]))
        try:
            state.add_signatures(rows)
        finally:
            state.close()
    finally:
        _remove(path)  # before the lock goes with this process: a waiter finds it done
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
