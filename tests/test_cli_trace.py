"""FETCHSYNC_TRACE: a one-shot push's steps on one clock, to account for its wall time.

bench/run.py's accounting of a push (exec, imports, the master's answer, the endpoint's
hello, the ping, the push's own work, exit) reads these lines; off, nothing is written.
"""

from __future__ import annotations

import time

from helpers import fetchsync, local_env, report


def test_a_traced_push_marks_its_steps_in_order_on_the_monotonic_clock(tmp_path):
    trace = tmp_path / "trace"
    env = local_env(tmp_path, FETCHSYNC_TRACE=str(trace))
    before = time.monotonic()
    assert report(fetchsync("push", "--json", env=env))["ok"]
    after = time.monotonic()
    lines = [ln.split(None, 2) for ln in trace.read_text().splitlines()]
    steps = [what for _, _, what in lines]
    times = [float(t) for t, _, _ in lines]
    assert len({pid for _, pid, _ in lines}) == 1
    assert times == sorted(times) and before < times[0] and times[-1] < after
    expected = [
        "main: the interpreter is up",
        "cli: imported",
        "push: start",
        "connection: the endpoint's command sent",
        "connection: the endpoint's hello in",
        "push: connected",
        "push: done",
        "exit: output flushed",
    ]
    assert [s for s in steps if s in expected] == expected, steps
    assert trace.stat().st_mode & 0o077 == 0
