"""``fetchsync run`` over the real sshd robot (and the local one): argv, streams, exit codes,
the ROS environment, and nothing left running on the robot after Ctrl-C or a lost link."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
import uuid

import pytest
from helpers import fetchsync, ssh_env
from terminal import Terminal

pytestmark = pytest.mark.ssh


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    return ssh_env(ssh_home.home, remote_dir, tmp_path, make_ws=False)


def _marker() -> str:
    """A sleep duration unique to one test, to find its processes with pgrep."""
    return f"0.{uuid.uuid4().int % 10**9:09d}"


def _remote_sleeps(marker: str) -> list[str]:
    out = subprocess.run(
        ["pgrep", "-f", f"^sleep 300 {marker}"], capture_output=True, text=True, check=False
    )
    return out.stdout.split()


def _wait_for(predicate, what: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.1)


def _start(args: list[str], env: dict[str, str]) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "fetchsync", "run", *args],
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


def _kill_leftovers(marker: str) -> None:
    for pid in _remote_sleeps(marker):
        try:
            os.kill(int(pid), signal.SIGKILL)
        except ProcessLookupError:
            pass


# --------------------------------------------------------------------------- argv and streams
def test_after_dashes_the_arguments_are_the_exact_argv(env):
    proc = fetchsync("run", "--", "printf", r"%s\n", "a b", "$HOME", "it's", env=env)
    assert proc.stdout == b"a b\n$HOME\nit's\n"


def test_one_argument_is_a_shell_command_line(env):
    proc = fetchsync("run", "printf '%s\\n' one two | grep -c o; echo $((6 * 7))", env=env)
    assert proc.stdout == b"2\n42\n"


def test_several_words_without_dashes_are_joined_as_ssh_does(env):
    assert fetchsync("run", "echo", "$((1 + 1))", env=env).stdout == b"2\n"


@pytest.mark.slow
def test_stdout_and_stderr_stay_apart_and_the_exit_code_is_the_commands(env):
    proc = fetchsync("run", "echo to-out; echo to-err >&2; exit 42", env=env, check=False)
    assert (proc.returncode, proc.stdout, proc.stderr) == (42, b"to-out\n", b"to-err\n")


def test_stdin_reaches_the_command_and_its_end_is_eof(env):
    proc = fetchsync("run", "--", "wc", "-c", env=env, input=b"x" * 100000)
    assert proc.stdout.strip() == b"100000"


def test_options_after_the_command_belong_to_it(env):
    assert fetchsync("run", "--", "echo", "--robot", "-n", env=env).stdout == b"--robot -n\n"


def test_output_streams_live(env):
    proc = _start(["echo first; sleep 300 " + _marker()], env)
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 30)
        assert ready and os.read(proc.stdout.fileno(), 100) == b"first\n"
    finally:
        proc.kill()
        proc.wait()


# --------------------------------------------------------------------------- ROS environment
def test_the_workspace_setup_comes_first(env, remote_dir):
    (remote_dir / "devel").mkdir()
    (remote_dir / "devel/setup.bash").write_text("export FETCHSYNC_TEST_SPACE=devel\n")
    (remote_dir / "install").mkdir()
    (remote_dir / "install/setup.bash").write_text("export FETCHSYNC_TEST_SPACE=install\n")
    assert fetchsync("run", "echo $FETCHSYNC_TEST_SPACE", env=env).stdout == b"devel\n"
    (remote_dir / "devel/setup.bash").unlink()
    assert fetchsync("run", "echo $FETCHSYNC_TEST_SPACE", env=env).stdout == b"install\n"


def test_without_any_ros_the_command_still_runs(env, tmp_path):
    # no local workspace and no ROS_DISTRO: run needs neither
    env = dict(env)
    env.pop("FETCHSYNC_WORKSPACE")
    env.pop("FETCHSYNC_REMOTE_WORKSPACE")
    assert fetchsync("run", "echo ok", env=env).stdout == b"ok\n"


def test_a_lost_robot_is_exit_255_with_a_message(env, ssh_home):
    ssh_home.known_hosts.write_text("")
    proc = fetchsync("run", "true", env=env, check=False)
    assert proc.returncode == 255
    assert b"host key" in proc.stderr and b"Traceback" not in proc.stderr


def test_the_local_robot_runs_commands_too(tmp_path):
    env = ssh_env(
        tmp_path / "home",
        tmp_path / "unused",
        tmp_path,
        FETCHSYNC_ROBOT="local",
        FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "robot-home"),
        FETCHSYNC_REMOTE_WORKSPACE="~/ws",
        make_ws=False,
    )
    (tmp_path / "robot-home/ws/devel").mkdir(parents=True)
    (tmp_path / "robot-home/ws/devel/setup.bash").write_text("export FROM_WS=yes\n")
    proc = fetchsync("run", "--", "sh", "-c", 'echo "$HOME $FROM_WS"; exit 3', env=env, check=False)
    assert (proc.returncode, proc.stdout) == (3, f"{tmp_path / 'robot-home'} yes\n".encode())


# --------------------------------------------------------------------------- stopping
def test_ctrl_c_without_a_pty_leaves_nothing_running(env):
    marker = _marker()
    # a background job too: non-interactive shells make those ignore SIGINT
    proc = _start([f"sleep 300 {marker} & sleep 300 {marker}; wait"], env)
    try:
        _wait_for(lambda: len(_remote_sleeps(marker)) == 2, "the remote sleeps to start")
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 130
        assert b"interrupted" in proc.stderr.read()
        _wait_for(lambda: not _remote_sleeps(marker), "the remote sleeps to end")
    finally:
        proc.kill()
        proc.wait()
        _kill_leftovers(marker)


def test_a_killed_fetchsync_leaves_nothing_running(env):
    marker = _marker()
    proc = _start(["--", "sleep", "300", marker], env)
    try:
        _wait_for(lambda: _remote_sleeps(marker), "the remote sleep to start")
        proc.kill()
        proc.wait()
        _wait_for(lambda: not _remote_sleeps(marker), "the remote sleep to end")
    finally:
        _kill_leftovers(marker)


def test_a_lost_link_is_exit_255_and_leaves_nothing_running(
    proxied_home, fault_proxy, remote_dir, tmp_path
):
    env = ssh_env(proxied_home.home, remote_dir, tmp_path, make_ws=False)
    marker = _marker()
    proc = _start(["--", "sleep", "300", marker], env)
    try:
        _wait_for(lambda: _remote_sleeps(marker), "the remote sleep to start")
        fault_proxy.cut()
        assert proc.wait(timeout=60) == 255
        err = proc.stderr.read()
        assert b"lost" in err and b"Traceback" not in err
        _wait_for(lambda: not _remote_sleeps(marker), "the remote sleep to end")
    finally:
        proc.kill()
        proc.wait()
        _kill_leftovers(marker)


# --------------------------------------------------------------------------- with a PTY
def test_with_a_terminal_the_command_gets_a_pty_of_our_size(env):
    term = Terminal(["run", "--", "sh", "-c", "tty; stty size"], env, rows=33, cols=77)
    try:
        out = term.read_until(b"33 77")
        assert b"/dev/pts/" in out
        assert term.wait() == 0
    finally:
        term.close()


def test_a_window_change_reaches_the_pty(env):
    script = "echo ready; while read line; do stty size; done"
    term = Terminal(["run", "--", "sh", "-c", script], env, rows=20, cols=60)
    try:
        term.read_until(b"ready")
        term.resize(41, 99)  # the kernel sends fetchsync SIGWINCH
        deadline = time.monotonic() + 30
        while b"41 99" not in term.output:  # the resize travels apart from the keys
            assert time.monotonic() < deadline, term.output
            term.send(b"\r")
            term.read_until(b"\n", timeout=10)
            term.output = term.output.replace(b"\n", b"|")
        term.send(b"\x04")
    finally:
        term.close()


def test_ctrl_c_through_the_pty_stops_the_command_and_leaves_nothing(env):
    marker = _marker()
    term = Terminal(["run", "--", "sh", "-c", f"echo started; sleep 300 {marker}"], env)
    try:
        term.read_until(b"started")
        _wait_for(lambda: _remote_sleeps(marker), "the remote sleep to start")
        term.send(b"\x03")
        assert term.wait() == 130
        _wait_for(lambda: not _remote_sleeps(marker), "the remote sleep to end")
    finally:
        term.close()
        _kill_leftovers(marker)


def test_no_tty_gives_pipes_even_at_a_terminal(env):
    term = Terminal(["run", "-T", "--", "sh", "-c", "tty; true"], env)
    try:
        assert b"not a tty" in term.read_until(b"not a tty")
        assert term.wait() == 0
    finally:
        term.close()
