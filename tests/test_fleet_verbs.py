"""create-account, workspace-status and snapshot on several robots (issue 27), against the
real sshd: ``fetch1``/``fetch2`` are aliases of it, ``down`` a closed port (test_fleet.py's
``fleet_env``)."""

from __future__ import annotations

import json
import os
import secrets
import subprocess
from pathlib import Path

import pytest
from helpers import fetchsync
from test_fleet import _rows, fleet_env  # noqa: F401 - the fixture

pytestmark = pytest.mark.ssh

needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="creating accounts needs root")


@pytest.fixture
def account_env(fleet_env, ssh_home):  # noqa: F811 - the fixture imported above
    """fleet_env for create-account: the account's workspace is ~/fs_ws on every robot."""
    (ssh_home.home / ".config/fetchsync/robots.toml").write_text(
        'lab = ["fetch1", "fetch2"]\nmixed = ["fetch1", "down", "fetch2"]\n'
    )
    env = dict(fleet_env, ROS_DISTRO="noetic", FETCHSYNC_REMOTE_WORKSPACE="~/fs_ws")
    for name in ("FETCHSYNC_NEW_PASSWORD", "FETCHSYNC_ADMIN_PASSWORD", "FETCHSYNC_ADMIN_USER"):
        env.pop(name, None)
    return env


@pytest.fixture
def account_name():
    name = "fsfleet" + secrets.token_hex(3)
    yield name
    subprocess.run(["userdel", "--remove", "--force", name], capture_output=True, check=False)


@needs_root
def test_create_account_on_several_robots_one_down(account_env, account_name):
    password = "Pw-" + secrets.token_urlsafe(12)
    env = dict(account_env, FETCHSYNC_NEW_PASSWORD=password)
    # one at a time: fetch1 and fetch2 are one machine, where the account is made once
    proc = fetchsync(
        "create-account",
        "--robot",
        "@mixed",
        "-j",
        "1",
        "--user",
        account_name,
        "--admin-user",
        "root",
        "--json",
        env=env,
        check=False,
    )
    err = proc.stderr.decode()
    assert proc.returncode == 3, err  # down: the link's status, its one failure
    rows = _rows(proc.stderr)
    assert rows["fetch1"][0] == "ok" and rows["fetch2"][0] == "ok" and rows["down"][0] == "failed"
    reports = {r["robot"]: r for r in json.loads(proc.stdout)}
    assert reports["fetch1"]["created"] is True and reports["fetch2"]["created"] is False
    assert f"[fetch2] create-account: {account_name} already exists on fetch2" in err
    assert "create-account: 2 of 3 robots succeeded; failed: down" in err
    assert password not in err + proc.stdout.decode()
    # the account is there, with its key: it logs in through the robot's sshd
    proc = fetchsync(
        "run", "--robot", "fetch1", "--user", account_name, "--", "id", "-un", env=account_env
    )
    assert proc.stdout.decode().strip() == account_name


@needs_root
def test_at_a_terminal_create_account_asks_each_password_once(account_env, account_name):
    from terminal import Terminal

    env = dict(account_env, PYTHONPATH=os.environ.get("PYTHONPATH", ""))
    password = "Pw-" + secrets.token_urlsafe(12)
    args = ["create-account", "--robot", "@lab", "-j", "1", "--user", account_name]
    term = Terminal([*args, "--admin-user", "root"], env, cols=200)
    try:
        term.read_until(b"New password for " + account_name.encode())
        term.send(password.encode() + b"\n")
        term.read_until(b"Repeat for confirmation")
        term.send(password.encode() + b"\n")
        term.read_until(b"Enter: none, it logs in with a key")
        term.send(b"\n")
        assert term.wait(90) == 0, term.output.decode()
    finally:
        term.close()
    out = term.output.decode()
    assert out.count("New password for") == 1 and out.count("Password of root") == 1, out
    assert "create-account: 2 of 2 robots succeeded" in out


def test_workspace_status_of_several_robots(fleet_env, tmp_path):  # noqa: F811
    fetchsync("push", "--robot", "fetch1", env=fleet_env)
    proc = fetchsync(
        "workspace-status", "--robot", "fetch1,fetch2,down", "--json", env=fleet_env, check=False
    )
    err = proc.stderr.decode()
    assert proc.returncode == 3, err  # down could not be compared
    rows = _rows(proc.stderr)
    assert [rows[n][0] for n in ("fetch1", "fetch2", "down")] == ["ok", "ok", "failed"]
    assert "unreachable" in " ".join(rows["down"])
    reports = {r["robot"]: r for r in json.loads(proc.stdout)}
    # fetch1 was pushed: in sync; fetch2 never was
    assert {row["robot"] for row in reports["fetch1"]["rows"]} == {"in sync"}
    assert {row["robot"] for row in reports["fetch2"]["rows"]} == {"not pushed yet"}
    proc = fetchsync("workspace-status", "--robot", "fetch1,fetch2", env=fleet_env)
    out = proc.stdout.decode().splitlines()
    assert any(line.startswith("[fetch1] ") and "in sync" in line for line in out), out
    assert any(line.startswith("[fetch2] ") and "not pushed" in line for line in out), out


def test_snapshot_of_several_robots(fleet_env, tmp_path):  # noqa: F811
    out_dir = tmp_path / "snaps"
    out_dir.mkdir()
    proc = fetchsync(
        "snapshot",
        "--robot",
        "fetch1,down,fetch2",
        "--only",
        "uname",
        "--no-sudo",
        "-o",
        str(out_dir),
        "--json",
        env=fleet_env,
        check=False,
    )
    err = proc.stderr.decode()
    assert proc.returncode == 3, err
    rows = _rows(proc.stderr)
    assert [rows[n][0] for n in ("fetch1", "down", "fetch2")] == ["ok", "failed", "ok"]
    names = sorted(p.name for p in out_dir.iterdir())
    assert len(names) == 2 and names[0].startswith("snapshot-fetch1-"), names
    assert names[1].startswith("snapshot-fetch2-")
    reports = {r["robot"]: r for r in json.loads(proc.stdout)}
    assert Path(reports["fetch2"]["archive"]).parent == out_dir
    # an archive path cannot hold several robots' snapshots
    proc = fetchsync(
        "snapshot",
        "--robot",
        "@lab",
        "-o",
        str(tmp_path / "one.tar.gz"),
        env=fleet_env,
        check=False,
    )
    assert proc.returncode == 2
    [line] = proc.stderr.decode().strip().splitlines()
    assert "a directory" in line
