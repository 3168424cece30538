"""Where a push scans the local tree (issue 24, start track).

While the robot's endpoint starts (a direct connection's takes tenths of a second) the
push scans then, under that wait. Once the endpoint is up (a connection master's warm
spare says hello within milliseconds) there is no such wait left: the push sends its
list request first and scans while the robot lists its tree, so that request's round
trip and the robot's work (its drift check: a walk of its whole tree) overlap the scan
instead of following it (bench/run.py --link wifi, 2,000 files: the wait for the
robot's list after the laptop's work 77 -> 0 ms, see NOTES.md).

The CLI runs in this process with the built-in local robot (a real endpoint process);
the endpoint's start is made deterministic by wrapping the local work handed to
Connection.open: it runs once the start-up is over, or is told the endpoint is still
starting.
"""

from __future__ import annotations

import gc
import json
import os
import time
from pathlib import Path

import pytest
from click.testing import CliRunner
from helpers import local_env

import fetchsync.sync.engine as engine
from fetchsync.cli import cli
from fetchsync.link.client import Endpoint
from fetchsync.link.connection import Connection


@pytest.fixture(autouse=True)
def _gc_back():
    """The push command freezes the collector and raises its thresholds: for one process."""
    threshold = gc.get_threshold()
    yield
    gc.unfreeze()
    gc.set_threshold(*threshold)


def invoke(args: list[str], env: dict[str, str]):
    """The CLI in this process with exactly ``env`` (CliRunner adds, so unset the rest)."""
    unset = {k: None for k in os.environ if k not in env}
    return CliRunner().invoke(cli, args, env={**unset, **env})


def record(monkeypatch, *, endpoint_up: bool) -> list[str]:
    """The order of the push's local scans and list requests; the endpoint is up (its
    hello in) when the local work starts, or still starting."""
    events: list[str] = []
    real_open = Connection._open.__func__  # type: ignore[attr-defined]

    def _open(cls, transport, python, meanwhile, ping=False):
        def local_work(started):
            if endpoint_up:
                deadline = time.monotonic() + 60
                while not started():  # until the endpoint's hello is in and ours sent
                    assert time.monotonic() < deadline, "the start-up never said it was over"
                    time.sleep(0.005)
                return meanwhile(started)
            return meanwhile(lambda: False)

        return real_open(cls, transport, python, local_work if meanwhile else None, ping)

    monkeypatch.setattr(Connection, "_open", classmethod(_open))
    real_scan = engine.scan_tree

    def scan_tree(*args):
        events.append("scan")
        return real_scan(*args)

    monkeypatch.setattr(engine, "scan_tree", scan_tree)
    real_list = Endpoint.send_listing

    def send_listing(self, **kw):
        events.append("list")
        return real_list(self, **kw)

    monkeypatch.setattr(Endpoint, "send_listing", send_listing)
    return events


def push(tmp_path: Path) -> dict:
    result = invoke(["push", "--json"], local_env(tmp_path))
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_with_the_endpoint_up_the_push_asks_for_the_list_before_it_scans(tmp_path, monkeypatch):
    events = record(monkeypatch, endpoint_up=True)
    first = push(tmp_path)
    assert first["ok"] and first["files"] > 0
    assert events == ["list", "scan"]
    (tmp_path / "ws" / "src" / "my_pkg" / "edited.txt").write_text("new\n")
    events.clear()
    second = push(tmp_path)
    assert second["ok"] and second["files"] == 1
    assert events == ["list", "scan"]


def test_while_the_endpoint_starts_the_push_scans_then(tmp_path, monkeypatch):
    events = record(monkeypatch, endpoint_up=False)
    first = push(tmp_path)
    assert first["ok"] and first["files"] > 0
    assert events == ["scan", "list"]  # scanned once, before the list request
    (tmp_path / "ws" / "src" / "my_pkg" / "edited.txt").write_text("new\n")
    events.clear()
    second = push(tmp_path)
    assert second["ok"] and second["files"] == 1
    assert events == ["scan", "list"]
