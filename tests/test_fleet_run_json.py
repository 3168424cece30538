"""``run --json``: the list of per-robot reports on stdout, the command's output on stderr.

Issue 27: "--json gives a list of the per-robot reports" for the verbs across a fleet;
``push`` and the others had it, ``run`` did not. Over the tests' real sshd, robots
``fetch1``/``fetch2`` and ``down`` (nothing listens) from test_fleet's configuration.
"""

from __future__ import annotations

import json

import pytest
from helpers import fetchsync
from test_fleet import fleet_env  # noqa: F401 - the fixture

pytestmark = pytest.mark.ssh


def test_a_fleet_run_lists_each_robots_report_and_keeps_stdout_for_it(fleet_env):  # noqa: F811
    proc = fetchsync(
        "run",
        "--json",
        "--robot",
        "fetch1,down,fetch2",
        "--",
        "sh",
        "-c",
        'echo "out line"; echo "err line" >&2; exit 3',
        env=fleet_env,
        check=False,
    )
    assert proc.returncode != 0
    reports = json.loads(proc.stdout)  # stdout is the JSON list alone
    by_robot = {r["robot"]: r for r in reports}
    assert [r["robot"] for r in reports] == ["fetch1", "down", "fetch2"]
    assert by_robot["fetch1"]["result"] == "failed" and by_robot["fetch1"]["exit_code"] == 3
    assert by_robot["fetch2"]["exit_code"] == 3 and "exit status 3" in by_robot["fetch2"]["error"]
    assert by_robot["down"]["result"] == "failed" and by_robot["down"]["exit_code"] == 255
    err = proc.stderr.decode()
    assert "[fetch1] out line" in err and "[fetch2] err line" in err  # the output, prefixed
    proc = fetchsync(
        "run", "--json", "--robot", "fetch1,fetch2", "true", env=fleet_env, check=False
    )
    assert proc.returncode == 0, proc.stderr.decode()
    assert [(r["robot"], r["result"], r["exit_code"]) for r in json.loads(proc.stdout)] == [
        ("fetch1", "ok", 0),
        ("fetch2", "ok", 0),
    ]


def test_run_json_on_one_robot_is_a_list_of_one(fleet_env):  # noqa: F811
    proc = fetchsync("run", "--json", "--robot", "fetch1", "echo hi", env=fleet_env, check=False)
    assert proc.returncode == 0, proc.stderr.decode()
    [report] = json.loads(proc.stdout)
    assert report["robot"] == "fetch1" and report["result"] == "ok" and report["exit_code"] == 0
    assert "[fetch1] hi" in proc.stderr.decode()
