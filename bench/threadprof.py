#!/usr/bin/env python3
"""``threadprof.py OUT.prof -m fetchsync ...``: cProfile of every thread, by thread CPU time.

cProfile alone follows the main thread, and a fleet push does its work on one thread
per robot and on paramiko's and the batcher's threads; here each thread gets a profile
of its own whose clock is ``time.thread_time`` (what that thread used, however loaded
the machine is), merged into OUT.prof at exit (fetchsync ends with os._exit after the
exit handlers: the merge is one). Read it with ``python3 -m pstats OUT.prof``. The
profiler slows Python code down, so its shares lean toward Python over C (compression,
ciphers, system calls): compare figures taken the same way. bench/fleetab.py --profile
runs its fleet pushes under it. Issue 27, link track.
"""

from __future__ import annotations

import os
import sys

# this directory holds a profile.py of its own (bench/profile.py), which cProfile's
# ``import profile`` would find first
if sys.path and os.path.abspath(sys.path[0]) == os.path.dirname(os.path.abspath(__file__)):
    del sys.path[0]

import atexit  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import runpy  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402

_PROFILES: list[cProfile.Profile] = []
_LOCK = threading.Lock()


def _start(*_: object) -> None:
    """The first profiling event of a new thread: give it a profile of its own."""
    prof = cProfile.Profile(time.thread_time)
    with _LOCK:
        _PROFILES.append(prof)
    prof.enable()


def _dump(out: str) -> None:
    merged: pstats.Stats | None = None
    with _LOCK:
        profiles = list(_PROFILES)
    for prof in profiles:
        prof.disable()
        prof.create_stats()
        if not prof.stats:  # type: ignore[attr-defined]
            continue
        if merged is None:
            merged = pstats.Stats(prof)
        else:
            merged.add(prof)
    if merged is not None:
        merged.dump_stats(out)


def main() -> None:
    if len(sys.argv) < 4 or sys.argv[2] != "-m":
        raise SystemExit(__doc__)
    out, module = sys.argv[1], sys.argv[3]
    sys.argv = [module, *sys.argv[4:]]
    threading.setprofile(_start)
    main_profile = cProfile.Profile(time.thread_time)
    _PROFILES.append(main_profile)
    atexit.register(_dump, out)
    main_profile.enable()
    runpy.run_module(module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
