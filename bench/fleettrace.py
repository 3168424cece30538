#!/usr/bin/env python3
"""Where a fleet push's time goes, per robot: ``fleettrace.py OUT.json -m fetchsync push ...``.

Runs ``fetchsync`` in this process with timing wrappers around the functions a
push's phases are made of (the connection, the endpoint's start, the listing,
each round, each batch sent and answered, the state's commit, the reads and the
hashing, paramiko's packets), each call recorded with its robot (the fleet
thread it ran in, or the thread that thread started), its wall time and its
thread's CPU time (``time.thread_time``: what that thread itself used, however
loaded the machine). The process's own CPU is sampled every 50 ms. At exit it
writes the calls and the samples to OUT.json and prints a summary: the CPU and
wall time per function, the process's CPU per half second, and when each phase
started and ended across the robots. ``bench/fleet.py --trace DIR`` runs its
fleet pushes this way. Issue 27: nothing here is in fetchsync itself.
"""

from __future__ import annotations

import atexit
import collections
import functools
import importlib
import json
import os
import runpy
import statistics
import sys
import threading
import time
from typing import Any

T0 = time.monotonic()
EVENTS: list[tuple[str | None, str, str, float, float, float]] = []
SAMPLES: list[tuple[float, float]] = []

WRAPPED = [
    ("fetchsync.link.session", "open_transport"),
    ("fetchsync.link.connection", "Connection.open"),
    ("fetchsync.sync.state", "open_state"),
    ("fetchsync.sync.state", "State.commit"),
    ("fetchsync.sync.engine", "scan_tree"),
    ("fetchsync.sync.engine", "Syncer.push"),
    ("fetchsync.sync.engine", "Syncer._open_and_list"),
    ("fetchsync.sync.engine", "Round.plan"),
    ("fetchsync.sync.engine", "Round.run"),
    ("fetchsync.sync.engine", "Round.settle"),
    ("fetchsync.sync.engine", "Round.commit"),
    ("fetchsync.sync.engine", "Syncer._send_content"),
    ("fetchsync.sync.engine", "Syncer._kept_of"),
    ("fetchsync.sync.engine", "read_stable"),
    ("fetchsync.sync.engine", "SharedPacks.get"),
    ("fetchsync.sync.engine", "_Batcher._send"),
    ("fetchsync.sync.engine", "_Batcher._send_loop"),
    ("fetchsync.sync.engine", "_Batcher._deflate"),
    ("fetchsync.sync.engine", "_Batcher.answered"),
    ("fetchsync.link.ssh", "_ProxyCommand.recv"),
    ("fetchsync.link.ssh", "_ProxyCommand.send"),
    ("paramiko.transport", "Transport.run"),
    ("paramiko.transport", "Transport._send_user_message"),
    ("paramiko.packet", "Packetizer.read_message"),
    ("fetchsync.cli.fleet", "finish"),
]
PHASES = [
    "open_state",
    "open_transport",
    "Connection.open",
    "Syncer._open_and_list",
    "Round.run",
    "Round.commit",
    "robot",
]


def _wrap(modname: str, qual: str) -> None:
    owner: Any = importlib.import_module(modname)
    *path, name = qual.split(".")
    for part in path:
        owner = getattr(owner, part)
    raw = owner.__dict__[name]
    fn = raw.__func__ if isinstance(raw, classmethod) else raw

    @functools.wraps(fn)
    def timed(*args: Any, **kwargs: Any) -> Any:
        thread = threading.current_thread()
        t0, c0 = time.monotonic(), time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            EVENTS.append(
                (
                    getattr(thread, "fs_robot", None),
                    thread.name,
                    qual,
                    t0 - T0,
                    time.monotonic() - T0,
                    time.thread_time() - c0,
                )
            )

    setattr(owner, name, classmethod(timed) if isinstance(raw, classmethod) else timed)


def _install() -> None:
    start = threading.Thread.start

    def inherit(self: threading.Thread) -> None:  # a robot's threads are its own
        self.fs_robot = getattr(threading.current_thread(), "fs_robot", None)  # type: ignore[attr-defined]
        start(self)

    threading.Thread.start = inherit  # type: ignore[method-assign]

    import fetchsync.cli.fleet as fleet

    run_all = fleet.run_all

    def traced_run_all(robots: Any, work: Any, **kwargs: Any) -> Any:
        def one(name: str, out: Any) -> Any:
            thread = threading.current_thread()
            thread.fs_robot = name  # type: ignore[attr-defined]
            t0, c0 = time.monotonic(), time.thread_time()
            try:
                return work(name, out)
            finally:
                EVENTS.append(
                    (
                        name,
                        thread.name,
                        "robot",
                        t0 - T0,
                        time.monotonic() - T0,
                        time.thread_time() - c0,
                    )
                )
                thread.fs_robot = None  # type: ignore[attr-defined]

        return run_all(robots, one, **kwargs)

    fleet.run_all = traced_run_all
    for modname, qual in WRAPPED:
        try:
            _wrap(modname, qual)
        except (ImportError, AttributeError, KeyError) as exc:
            print(f"fleettrace: not traced: {modname}.{qual} ({exc})", file=sys.stderr)

    def sample() -> None:
        tick = os.sysconf("SC_CLK_TCK")
        while True:
            with open("/proc/self/stat") as fh:
                f = fh.read().rsplit(")", 1)[1].split()
            SAMPLES.append((time.monotonic() - T0, (int(f[11]) + int(f[12])) / tick))
            time.sleep(0.05)

    threading.Thread(target=sample, daemon=True, name="fleettrace").start()


def summary(events: list[Any], samples: list[Any]) -> str:
    """The per-function totals, the CPU timeline and the phases across robots."""
    lines = [f"{'function':34} {'calls':>6} {'wall s':>8} {'CPU s':>7}"]
    agg: dict[str, list[float]] = collections.defaultdict(lambda: [0, 0.0, 0.0])
    for _robot, _thread, fn, t0, t1, cpu in events:
        a = agg[fn]
        a[0] += 1
        a[1] += t1 - t0
        a[2] += cpu
    for fn, (n, wall, cpu) in sorted(agg.items(), key=lambda x: -x[1][2]):
        lines.append(f"{fn:34} {int(n):6d} {wall:8.2f} {cpu:7.2f}")
    if samples:
        t = os.times()
        lines.append(
            f"process CPU {t.user + t.system:.2f} s over {samples[-1][0]:.2f} s; per 0.5 s:"
        )
        prev, row = (0.0, 0.0), []
        for at, cpu in samples:
            if at - prev[0] >= 0.5:
                row.append(f"{at:.1f}:{(cpu - prev[1]) / (at - prev[0]):.2f}")
                prev = (at, cpu)
        lines.append("  " + " ".join(row))
    spans: dict[str, list[tuple[float, float]]] = collections.defaultdict(list)
    for robot, _thread, fn, t0, t1, _cpu in events:
        if robot and fn in PHASES:
            spans[fn].append((t0, t1))
    lines.append(
        f"{'phase (robots)':24} {'first start':>11} {'last start':>10} {'first end':>9} {'last end':>8} {'median':>7}"
    )
    for fn in PHASES:
        v = spans.get(fn)
        if v:
            lines.append(
                f"{fn:24} {min(a for a, _ in v):11.2f} {max(a for a, _ in v):10.2f} "
                f"{min(b for _, b in v):9.2f} {max(b for _, b in v):8.2f} "
                f"{statistics.median(b - a for a, b in v):7.2f}"
            )
    return "\n".join(lines)


def main() -> None:
    out = sys.argv[1]
    args = sys.argv[2:]
    if args[:2] != ["-m", "fetchsync"]:
        sys.exit("usage: fleettrace.py OUT.json -m fetchsync ARGS...")
    _install()

    def dump() -> None:
        with open(out, "w") as fh:
            json.dump({"events": EVENTS, "samples": SAMPLES}, fh)
        with open(
            out[: -len(".json")] + ".txt" if out.endswith(".json") else out + ".txt", "w"
        ) as fh:
            fh.write(summary(EVENTS, SAMPLES) + "\n")

    atexit.register(dump)  # fetchsync ends with os._exit after the exit handlers
    sys.argv = ["fetchsync", *args[2:]]
    runpy.run_module("fetchsync", run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
