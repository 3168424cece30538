"""Several robots at once (issue 27) against the real sshd: ssh config aliases of the one
sshd, each with its own remote workspace (robots.toml), stand for robots; an alias to a
closed port of 127.0.0.1 is a robot that is down."""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

import pytest
from helpers import fetchsync, ssh_env, tree_of

from fetchsync.cli import fleet

pytestmark = pytest.mark.ssh

ROBOTS = ("fetch1", "fetch2", "fetch3")


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # closed once the socket is: nothing listens there


@pytest.fixture
def fleet_env(ssh_home, tmp_path: Path) -> dict[str, str]:
    """fetch1..3 are the sshd, each with a remote workspace of its own; ``down`` is nobody;
    robots.toml names groups ``lab`` (fetch1..3) and ``mixed`` (fetch1, down, fetch2)."""
    config = ssh_home.config.read_text()
    block = config[config.index("Host robot") :]
    extra = "".join(block.replace("Host robot", f"Host {name}", 1) for name in ROBOTS)
    extra += block.replace("Host robot", "Host down", 1).replace(
        f"Port {ssh_home.sshd.port}", f"Port {_closed_port()}"
    )
    ssh_home.config.write_text(config + "\n" + extra)
    conf = ssh_home.home / ".config/fetchsync"
    conf.mkdir(parents=True)
    remote = {name: tmp_path / f"robot-{name}" for name in (*ROBOTS, "down")}
    (conf / "robots.toml").write_text(
        'lab = ["fetch1", "fetch2", "fetch3"]\nmixed = ["fetch1", "down", "fetch2"]\n\n'
        + "".join(
            f'[robots.{name}]\nremote_workspace = "{path}"\n\n' for name, path in remote.items()
        )
    )
    env = ssh_env(ssh_home.home, tmp_path / "unused", tmp_path)
    for k in ("FETCHSYNC_ROBOT", "FETCHSYNC_REMOTE_WORKSPACE", "XDG_CONFIG_HOME"):
        env.pop(k, None)
    return env


def push_three_in_process(
    env: dict[str, str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, src: Path
) -> None:
    """``push --robot fetch1,fetch2,fetch3 -j 3`` in this process (so a test can count
    what the engine does), with exactly ``env`` as the environment; every robot then
    holds ``src``."""
    from fetchsync.cli import cli

    for key, value in env.items():
        monkeypatch.setenv(key, value)
    for key in [k for k in os.environ if k not in env]:
        monkeypatch.delenv(key)
    with pytest.raises(SystemExit) as exit_:
        cli.main(["push", "--robot", "fetch1,fetch2,fetch3", "-j", "3"], standalone_mode=False)
    assert exit_.value.code == 0
    for name in ("fetch1", "fetch2", "fetch3"):
        assert tree_of(tmp_path / f"robot-{name}/src") == tree_of(src), name


def _src(env: dict[str, str]) -> Path:
    return Path(env["FETCHSYNC_WORKSPACE"]) / "src"


def _rows(stderr: bytes) -> dict[str, list[str]]:
    """The table's rows by robot: [result, files, bytes..., error words]."""
    rows = {}
    for line in stderr.decode().splitlines():
        words = line.split()
        if words and words[0] in (*ROBOTS, "down") and not line.startswith("["):
            rows[words[0]] = words[1:]
    return rows


def test_a_fleet_push_with_a_robot_down_pushes_the_others(fleet_env, tmp_path):
    proc = fetchsync(
        "push", "--robot", "fetch1", "--robot", "down,fetch2", "--json", env=fleet_env, check=False
    )
    assert proc.returncode == 3, proc.stderr.decode()  # the link's exit status: the one failure
    for name in ("fetch1", "fetch2"):
        assert tree_of(tmp_path / f"robot-{name}/src") == tree_of(_src(fleet_env))
    assert not (tmp_path / "robot-fetch3").exists()
    rows = _rows(proc.stderr)
    assert rows["fetch1"][0] == "ok" and rows["fetch2"][0] == "ok"
    assert rows["down"][0] == "failed" and "connect" in " ".join(rows["down"]).lower()
    reports = json.loads(proc.stdout)
    assert [r["robot"] for r in reports] == ["fetch1", "down", "fetch2"]
    assert [r["ok"] for r in reports] == [True, False, True]
    assert reports[0]["files"] == 5 and reports[2]["files"] == 5
    assert reports[1]["exit_code"] == 3 and reports[1]["error"]
    # each robot's line says where its push goes, prefixed with its name
    err = proc.stderr.decode()
    assert "[fetch2] push " in err and "robot-fetch2/src" in err


def test_retry_failed_runs_again_on_the_failed_robots_only(fleet_env, tmp_path):
    fetchsync("push", "--robot", "fetch1,down", env=fleet_env, check=False)
    proc = fetchsync("push", "--retry-failed", env=fleet_env, check=False)
    assert proc.returncode == 3
    assert list(_rows(proc.stderr)) == ["down"]  # fetch1 is not pushed again


def test_fail_fast_starts_no_robot_after_a_failure(fleet_env, tmp_path):
    proc = fetchsync(
        "push", "-j", "1", "--fail-fast", "--robot", "down,fetch1", env=fleet_env, check=False
    )
    assert proc.returncode == 3
    rows = _rows(proc.stderr)
    assert rows["down"][0] == "failed" and rows["fetch1"][:2] == ["not", "started"]
    assert not (tmp_path / "robot-fetch1").exists()


def test_a_group_from_robots_toml_and_in_the_variable(fleet_env, tmp_path):
    env = dict(fleet_env, FETCHSYNC_ROBOT="@lab")
    proc = fetchsync("push", env=env)
    assert sorted(_rows(proc.stderr)) == sorted(ROBOTS)
    for name in ROBOTS:
        assert tree_of(tmp_path / f"robot-{name}/src") == tree_of(_src(env))
    proc = fetchsync("push", "--robot", "@nope", env=env, check=False)
    assert proc.returncode == 2
    [line] = proc.stderr.decode().splitlines()
    assert "unknown group @nope" in line and "@lab, @mixed" in line


@pytest.mark.slow
def test_a_fleet_run_prefixes_each_robots_output_and_fails_if_one_fails(fleet_env):
    proc = fetchsync(
        "run",
        "--robot",
        "@mixed",
        "--",
        "sh",
        "-c",
        'echo "out of $(basename $PWD)"; echo "err line" >&2; exit 0',
        env=fleet_env,
        check=False,
    )
    assert proc.returncode == 255, proc.stderr.decode()  # down: fetchsync could not run it
    out = proc.stdout.decode().splitlines()
    assert sorted(line.split()[0] for line in out) == ["[fetch1]", "[fetch2]"]
    err = proc.stderr.decode()
    assert "[fetch1] err line" in err and "[fetch2] err line" in err
    rows = _rows(proc.stderr)
    assert rows["fetch1"][0] == "ok" and rows["down"][0] == "failed"
    # a command's own status is the robot's result
    proc = fetchsync(
        "run", "--robot", "fetch1,fetch2", "test $(hostname) = nobody", env=fleet_env, check=False
    )
    assert proc.returncode == 1
    assert _rows(proc.stderr)["fetch2"][0] == "failed"


def test_pull_refuses_several_robots(fleet_env):
    for verb in (["pull", "--yes"],):
        proc = fetchsync(
            *verb, "--robot", "fetch1", "--robot", "fetch2", env=fleet_env, check=False
        )
        assert proc.returncode == 2, (verb, proc.stderr.decode())
        [line] = [x for x in proc.stderr.decode().splitlines() if x.strip()]
        assert "several robots (fetch1, fetch2, from --robot): only push, run, watch," in line


# -- naming, without a robot ---------------------------------------------------------


def test_names_expand_lists_and_groups_in_order_each_once(tmp_path):
    conf = tmp_path / "fetchsync"
    conf.mkdir()
    (conf / "robots.toml").write_text('lab = ["b", "c"]\n[robots.c]\nremote_workspace = "~/w"\n')
    environ = {"XDG_CONFIG_HOME": str(tmp_path)}
    assert fleet.expand("a, @lab ,b", environ=environ) == ["a", "b", "c"]
    assert fleet.names_given("solo", environ=environ) is None
    assert fleet.names_given(None, environ={**environ, "FETCH_ROBOT": "a,b"}) == ["a", "b"]
    assert fleet.robot_settings("c", environ=environ) == {"remote_workspace": "~/w"}
    (conf / "robots.toml").write_text('lab = "b"\n')
    with pytest.raises(fleet.ConfigError, match="must be a list"):
        fleet.expand("@lab", environ=environ)
    (conf / "robots.toml").write_text("lab = [\n")
    with pytest.raises(fleet.ConfigError, match="not valid TOML"):
        fleet.expand("@lab", environ=environ)
    os.remove(conf / "robots.toml")
    with pytest.raises(fleet.ConfigError, match="known groups .*: none"):
        fleet.expand("@lab", environ=environ)


def test_ctrl_c_ends_a_fleet_run_and_its_commands_on_every_robot(fleet_env):
    import signal
    import subprocess
    import sys
    import time
    import uuid

    marker = f"0.{uuid.uuid4().int % 10**9:09d}"

    def sleeps() -> list[str]:
        return subprocess.run(
            ["pgrep", "-f", f"^sleep 300 {marker}"], capture_output=True, text=True, check=False
        ).stdout.split()

    saved = signal.getsignal(signal.SIGINT)
    if saved == signal.SIG_IGN:  # as test_run: children of a background suite would ignore it
        signal.signal(signal.SIGINT, signal.default_int_handler)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fetchsync",
            "run",
            "--robot",
            "fetch1,fetch2",
            "--",
            "sleep",
            "300",
            marker,
        ],
        env=fleet_env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 60
        while len(sleeps()) < 2:
            assert time.monotonic() < deadline and proc.poll() is None, proc.stderr.read()
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 130
        deadline = time.monotonic() + 30
        while sleeps():  # the robots' reapers stop the commands once the links close
            assert time.monotonic() < deadline, "a command was left running on a robot"
            time.sleep(0.1)
    finally:
        signal.signal(signal.SIGINT, saved)
        proc.kill()
        for pid in sleeps():
            os.kill(int(pid), signal.SIGKILL)


def test_at_a_terminal_a_host_key_is_asked_once_for_robots_sharing_it(
    fleet_env, ssh_home, tmp_path
):
    """fetch1..3 are one host: its key is asked about once, before any robot uses it, and
    the question is whole (asked in parallel, three would wait on one answer)."""
    from terminal import Terminal

    question = b"(yes/no/[fingerprint])? "
    ssh_home.known_hosts.write_text("")
    env = dict(fleet_env, PYTHONPATH=os.environ.get("PYTHONPATH", ""))
    term = Terminal(["push", "--robot", "@lab"], env, cols=200)
    try:
        term.read_until(question)
        term.send(b"yes\n")
        assert term.wait(60) == 0, term.output.decode()
    finally:
        term.close()
    assert term.output.count(question) == 1, term.output.decode()
    for name in ROBOTS:
        assert tree_of(tmp_path / f"robot-{name}/src") == tree_of(_src(env))


@pytest.mark.slow
def test_run_sources_each_robots_own_remote_workspace_from_robots_toml(fleet_env, tmp_path):
    devel = tmp_path / "robot-fetch2/devel"
    devel.mkdir(parents=True)
    (devel / "setup.bash").write_text("export FLEET_MARK=fetch2-workspace\n")
    proc = fetchsync("run", "--robot", "fetch2", "echo mark=$FLEET_MARK", env=fleet_env)
    assert proc.stdout == b"mark=fetch2-workspace\n"
    proc = fetchsync("run", "--robot", "fetch1,fetch2", "echo mark=$FLEET_MARK", env=fleet_env)
    assert sorted(proc.stdout.decode().splitlines()) == [
        "[fetch1] mark=",
        "[fetch2] mark=fetch2-workspace",
    ]
