"""bench/fleet.py runs to the end with 3 robots (each its own sshd and shaped link): a smoke
test, no timing asserted (the figures are the bench's, run by hand: bench/README.md)."""

from __future__ import annotations

import pytest
from helpers import run_bench

pytestmark = pytest.mark.ssh


def test_the_fleet_bench_runs_with_three_robots(tmp_path):
    out, data = run_bench(
        "fleet.py",
        "--robots",
        "3",
        "--files",
        "200",
        "--size-mb",
        "3",
        "--quick",
        "--no-loopback",
        tmp_path=tmp_path,
    )
    [initial] = data["scenarios"]
    assert initial["scenario"] == "initial" and initial["link"] == "wifi"
    assert sorted(initial["fleet"]["bytes"]) == ["r01", "r02", "r03"]
    # each robot receives what a push to it alone sends (give or take the handshake's noise)
    for name, ratio in initial["bytes_ratio"].items():
        assert 0.8 < ratio < 1.25, (name, ratio)
    # the tree went over (compressed: 3 MiB of generated sources and meshes make ~1 MiB)
    assert all(b > data["workspace"]["bytes"] / 5 for b in initial["fleet"]["bytes"].values())
    # who used the CPUs: the laptop's push, the bench's link proxies, the robots' sshds
    for key in ("cpu", "cpu_links", "cpu_robots"):
        assert initial["fleet"][key] > 0, (key, initial["fleet"])
    down = data["two_down"]
    assert down["ok"] == ["r03"] and sorted(down["failed"]) == ["r01", "r02"]
    assert down["exit"] == 3, down
    for name, why in down["failed"].items():  # each failed row says why, naming its robot
        assert name in why, down
    assert "| initial | wifi |" in out and "Two robots down" in out
    assert "The CPU floor" in out and "laptop CPU per further robot" in out


def test_the_fleet_bench_traces_where_a_fleet_push_goes(tmp_path):
    """--trace: each fleet push runs under bench/fleettrace.py, which records every robot's
    phases (connection, endpoint, rounds, commit) and the functions' CPU per thread."""
    import json

    trace = tmp_path / "trace"
    run_bench(
        "fleet.py",
        "--robots",
        "3",
        "--files",
        "200",
        "--size-mb",
        "3",
        "--quick",
        "--no-loopback",
        "--no-down",
        "--singles",
        "1",
        "--trace",
        str(trace),
        tmp_path=tmp_path,
    )
    [summary] = trace.glob("wifi-*.txt")
    data = json.loads(summary.with_suffix(".json").read_text())
    robots = {e[0] for e in data["events"] if e[2] == "robot"}
    assert robots == {"r01", "r02", "r03"}
    for phase in ("open_transport", "Connection.open", "Round.run", "State.commit"):
        assert {e[0] for e in data["events"] if e[2] == phase} == robots, phase
    text = summary.read_text()
    assert "process CPU" in text and "Round.run" in text
