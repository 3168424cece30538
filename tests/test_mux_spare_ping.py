"""The ping that proves a handed-over spare alive (06049d3: sent with our hello).

The master checks its spare endpoint before handing it over, but the spare may still die
after that check. test_mux_spare.py kills it before the client reads anything (the
client's start-up sees the end); this file kills it later: after it has had our hello
and before it answers the ping sent with it. Only the wait for the ping's answer stands
between that death and the push's first request: without it the push would send its
requests into a dead endpoint and fail (a request may have been a write, so it is never
replayed), where waiting for the ping lets it start a fresh endpoint in the same call.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import fetchsync, report, tree_of
from test_mux_spare import env, mux_log, spare_ready  # noqa: F401 (env is a fixture)

pytestmark = pytest.mark.ssh


@pytest.mark.slow
def test_a_spare_dying_before_it_answers_the_ping_does_not_fail_the_push(env, remote_dir):  # noqa: F811
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    env = dict(env, FETCHSYNC_TEST_SPARE_DIES="answer")  # the master inherits it
    spare_ready(env)
    (local / "my_pkg" / "after_ping_death.txt").write_text("still lands\n")
    proc = fetchsync("push", "--json", env=env, check=False)
    assert proc.returncode == 0, proc.stderr.decode()
    assert "Traceback" not in proc.stderr.decode()
    r = report(proc)
    assert r["connection"] == "master" and r["ok"]
    log = mux_log(env)
    # the spare taken died (the hook fired on it) and the push started another endpoint
    assert log.count("took the spare endpoint") + log.count("no spare endpoint ready") == 2
    assert (remote_dir / "src" / "my_pkg" / "after_ping_death.txt").read_text() == "still lands\n"
    assert tree_of(local) == tree_of(remote_dir / "src")
