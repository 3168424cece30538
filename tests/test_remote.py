"""fetchsync.chores.remote and fetchsync.robot.reaper, here: the ROS environment script, quoting, and
the reaper's process-group handling (the same code runs on the robot)."""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from fetchsync.chores import remote

REAPER = str(Path(remote.__file__).parent.parent / "robot" / "reaper.py")


def bash(script: str, *, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    full = dict(os.environ)
    full.pop("ROS_DISTRO", None)
    full.update(env or {})
    return subprocess.run(
        ["bash", "-c", script], capture_output=True, text=True, env=full, timeout=30, check=False
    )


def fake_distro(root: Path, name: str) -> None:
    (root / name).mkdir(parents=True)
    (root / name / "setup.bash").write_text(f"export FROM_SETUP=/opt/ros/{name}\n")


def fake_space(workspace: Path, space: str) -> None:
    (workspace / space).mkdir(parents=True, exist_ok=True)
    (workspace / space / "setup.bash").write_text(f"export FROM_SETUP={space}\n")


def where_from(workspace: str | None, ros_root: Path, **kwargs: object) -> str:
    env_lines = remote.ros_environment(workspace, ros_root=str(ros_root), **kwargs)  # type: ignore[arg-type]
    return env_lines + '\nprintf "%s|%s" "${FROM_SETUP:-none}" "${__fetchsync_distro:-unset}"'


# --------------------------------------------------------------------------- quoting
@pytest.mark.parametrize(
    "path, expected",
    [
        ("~", '"$HOME"'),
        ("~/ws", '"$HOME"/ws'),
        ("~/my ws/x", "\"$HOME\"/'my ws/x'"),
        ("/abs/it's", "'/abs/it'\"'\"'s'"),
    ],
)
def test_shell_path_keeps_tilde_for_the_other_end(path, expected):
    assert remote.shell_path(path) == expected


def test_shell_path_expands_to_home_there():
    out = bash(f"printf %s {remote.shell_path('~/a b')}", env={"HOME": "/robot home"})
    assert out.stdout == "/robot home/a b"


def test_command_line_is_the_exact_argv():
    argv = ["printf", r"%s\n", "a b", "$HOME", "it's", "*", "", "-n"]
    out = subprocess.run(["sh", "-c", remote.command_line(argv)], capture_output=True, check=True)
    assert out.stdout == b"a b\n$HOME\nit's\n*\n\n-n\n"
    with pytest.raises(ValueError):
        remote.command_line([])


# --------------------------------------------------------------------------- ROS environment
def test_the_workspaces_devel_space_wins(tmp_path):
    fake_distro(tmp_path / "ros", "noetic")
    ws = tmp_path / "ws"
    fake_space(ws, "install")
    fake_space(ws, "devel")
    assert bash(where_from(str(ws), tmp_path / "ros")).stdout == "devel|unset"
    (ws / "devel/setup.bash").unlink()
    assert bash(where_from(str(ws), tmp_path / "ros")).stdout == "install|unset"


def test_without_a_built_workspace_the_robots_distro(tmp_path):
    fake_distro(tmp_path / "ros", "melodic")
    fake_distro(tmp_path / "ros", "noetic")
    (tmp_path / "ros" / "zzz-not-ros").mkdir()
    out = bash(where_from(str(tmp_path / "missing"), tmp_path / "ros"))
    # several and nothing tells which: ask, listing them (more in test_build_env.py)
    assert out.returncode == 2 and out.stdout == "", out
    assert "several ROS distributions" in out.stderr and " melodic noetic;" in out.stderr
    fake_distro(tmp_path / "one-ros", "noetic")
    out = bash(where_from(str(tmp_path / "missing"), tmp_path / "one-ros"))
    assert out.stdout == "/opt/ros/noetic|unset"  # the only one; helper variables are unset after
    out = bash(
        where_from(str(tmp_path / "missing"), tmp_path / "ros"), env={"ROS_DISTRO": "melodic"}
    )
    assert out.stdout == "/opt/ros/melodic|unset"


def test_without_any_ros_nothing_is_sourced_and_nothing_complains(tmp_path):
    out = bash(where_from(None, tmp_path / "no-ros") + "; echo; echo ran")
    assert (out.returncode, out.stdout, out.stderr) == (0, "none|unset\nran\n", "")
    out = bash(where_from(str(tmp_path), tmp_path / "no-ros"), env={"ROS_DISTRO": "noetic"})
    assert (out.stdout, out.stderr) == ("none|unset", "")


def test_spaces_choose_which_setup_files_count(tmp_path):
    fake_distro(tmp_path / "ros", "humble")
    fake_space(tmp_path / "ws", "install")
    out = bash(where_from(str(tmp_path / "ws"), tmp_path / "ros", spaces=()))
    assert out.stdout == "/opt/ros/humble|unset"


def test_tilde_workspace_is_the_home_of_where_it_runs(tmp_path):
    fake_space(tmp_path / "home" / "my ws", "devel")
    out = bash(where_from("~/my ws", tmp_path / "ros"), env={"HOME": str(tmp_path / "home")})
    assert out.stdout == "devel|unset"


def test_script_changes_directory_first(tmp_path):
    (tmp_path / "ws").mkdir()
    out = bash(remote.script("pwd", environment=":", directory=str(tmp_path / "ws")))
    assert out.stdout.strip() == str(tmp_path / "ws")
    out = bash(remote.script("echo never", environment=":", directory=str(tmp_path / "missing")))
    assert out.returncode == 1 and out.stdout == ""


# --------------------------------------------------------------------------- wrap and reaper
def test_wrapped_commands_keep_streams_and_status():
    line = remote.wrap("echo out; echo err >&2; exit 7", tty=False, python=sys.executable)
    out = subprocess.run(["sh", "-c", line], capture_output=True, check=False, timeout=30)
    assert (out.returncode, out.stdout, out.stderr) == (7, b"out\n", b"err\n")


def test_without_python_there_the_command_still_runs():
    line = remote.wrap("echo ran; exit 3", tty=False, python="/nonexistent/python3")
    out = subprocess.run(["sh", "-c", line], capture_output=True, check=False, timeout=30)
    assert (out.returncode, out.stdout, out.stderr) == (3, b"ran\n", b"")


def test_the_reaper_reports_signals_as_the_shell_does():
    out = subprocess.run(
        [sys.executable, REAPER, "pipe", "sh", "-c", "kill -TERM $$"],
        capture_output=True,
        check=False,
        timeout=30,
    )
    assert out.returncode == 128 + signal.SIGTERM
    out = subprocess.run(
        [sys.executable, REAPER, "pipe", "/nonexistent/cmd"],
        capture_output=True,
        check=False,
        timeout=30,
    )
    assert out.returncode == 127 and b"cannot run /nonexistent/cmd" in out.stderr


def test_the_command_gets_default_signal_handling():
    # Python ignores SIGPIPE; a command run from it must not
    script = 'yes | head -1; echo "${PIPESTATUS[0]}"'
    out = subprocess.run(
        [sys.executable, REAPER, "pipe", "bash", "-c", script],
        capture_output=True,
        check=False,
        timeout=30,
    )
    assert out.stdout == b"y\n141\n"


def _sleeps(marker: str) -> list[str]:
    out = subprocess.run(
        ["pgrep", "-f", f"^sleep 300 {marker}"], capture_output=True, text=True, check=False
    )
    return out.stdout.split()


def _wait_for(predicate, what: str) -> None:
    deadline = time.monotonic() + 30
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


@pytest.mark.parametrize("stop", ["close-output", "sigterm"])
def test_the_reaper_stops_the_whole_group(stop):
    marker = f"0.{uuid.uuid4().int % 10**9:09d}"
    command = f"sleep 300 {marker} & sleep 300 {marker}; wait"
    proc = subprocess.Popen(
        [sys.executable, REAPER, "pipe", "bash", "-c", command],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        _wait_for(lambda: len(_sleeps(marker)) == 2, "the sleeps to start")
        if stop == "close-output":  # what sshd does when the channel closes
            proc.stdout.close()
            proc.stderr.close()
        else:
            proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        _wait_for(lambda: not _sleeps(marker), "the sleeps to end")
    finally:
        proc.kill()
        proc.wait()
        for pid in _sleeps(marker):
            os.kill(int(pid), signal.SIGKILL)


def test_wrap_quotes_everything_for_the_login_shell():
    script = "printf '%s\\n' \"$0\" 'a b'"
    line = remote.wrap(script, tty=False, python="python3")
    assert shlex.split(line)[0] == "if"
    out = subprocess.run(["sh", "-c", line], capture_output=True, check=True, timeout=30)
    assert out.stdout == b"bash\na b\n"
