"""Secrets given to one call never sit in the environment of the long-lived processes it
leaves behind (the connection master, the resident).

A script may export FETCHSYNC_SUDO_PASSWORD (or the account passwords) for the whole
session; a plain push made there leaves a connection master (FETCHSYNC_PERSIST seconds)
and a resident (FETCHSYNC_RESIDENT seconds) running detached, which need none of it.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import fetchsync, report
from test_mux_spare import masters, wait_for
from test_resident import env, resident_up, residents  # noqa: F401 - the fixture

pytestmark = pytest.mark.ssh

SECRETS = {
    "FETCHSYNC_SUDO_PASSWORD": "sudo-secret-4b1d",
    "FETCHSYNC_ADMIN_PASSWORD": "admin-secret-77c2",
    "FETCHSYNC_NEW_PASSWORD": "new-secret-9e0a",
}


def environ(pid: int) -> bytes:
    return Path(f"/proc/{pid}/environ").read_bytes()


def test_the_master_and_the_resident_inherit_no_password(env):  # noqa: F811
    env = dict(env, **SECRETS)
    resident = resident_up(env)
    runtime = Path(env["XDG_RUNTIME_DIR"])
    assert wait_for(lambda: bool(masters(runtime)))
    for pid in masters(runtime) + residents(runtime) + [resident]:
        seen = environ(pid)
        for name, value in SECRETS.items():
            assert value.encode() not in seen, f"{name} in the environment of {pid}"
    # and the resident still makes the pushes of a caller that has them set
    (Path(env["FETCHSYNC_WORKSPACE"]) / "src/my_pkg/after.txt").write_text("after\n")
    assert report(fetchsync("push", "--json", env=env))["connection"] == "resident"
