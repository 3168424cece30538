"""The watch agent across outages of the link and of the robot's sshd (issue 24: recovery).

A blackhole (packets stop, nothing ends) is ridden out on the same connection: no
new login once the link is back. A robot whose sshd goes away (its sessions end,
new connections are refused) and comes back on the same port is mirrored again by
the same agent process, without the user doing anything. No timing asserts: the
figures are bench/watch.py's.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import fetchsync, make_workspace, ssh_env, tree_of
from sshd import find_sshd, make_ssh_home, running_sshd

from fetchsync.link.ssh import sshd_answers

pytestmark = pytest.mark.ssh


def wait_for(cond, timeout: float = 30.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def same(local: Path, robot: Path) -> bool:
    try:
        return tree_of(local) == tree_of(robot)
    except OSError:
        return False


@pytest.fixture
def runtime() -> Iterator[Path]:
    d = Path(tempfile.mkdtemp(prefix="fsr", dir="/tmp"))  # AF_UNIX paths are short
    d.chmod(0o700)
    yield d
    shutil.rmtree(d, ignore_errors=True)


def agent_env(home: Path, tmp_path: Path, runtime: Path, remote_dir: Path) -> dict[str, str]:
    return ssh_env(home, remote_dir, tmp_path, make_ws=False, XDG_RUNTIME_DIR=str(runtime))


@contextlib.contextmanager
def watching(env: dict[str, str], log: Path) -> Iterator[subprocess.Popen[bytes]]:
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "fetchsync", "watch"], env=env, stdout=out, stderr=out
        )
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        print(log.read_text(errors="replace"))


def status(env: dict[str, str]) -> dict:
    out = fetchsync("status", "--json", env=env, check=False)
    return json.loads(out.stdout) if out.stdout.strip() else {}


def logins(sshd_log: Path) -> int:
    return sshd_log.read_text(errors="replace").count("Accepted publickey")


def test_a_blackhole_is_ridden_out_on_the_same_connection(
    proxied_home, fault_proxy, sshd, remote_dir, tmp_path, runtime
):
    env = agent_env(proxied_home.home, tmp_path, runtime, remote_dir)
    make_workspace(tmp_path / "ws")
    src, robot = tmp_path / "ws" / "src", remote_dir / "src"
    with watching(env, tmp_path / "watch.log") as proc:
        wait_for(lambda: status(env).get("state") == "live", 30, what="live")
        before = logins(sshd.log)
        fault_proxy.blackhole()
        (src / "my_pkg/while_away.txt").write_text("written while the link was a blackhole\n")
        wait_for(lambda: status(env).get("state") == "offline", 30, what="offline to be noticed")
        fault_proxy.pass_through()
        wait_for(lambda: same(src, robot), 40, what="the change to arrive")
        wait_for(lambda: status(env).get("state") == "live", 10, what="live again")
        assert proc.poll() is None
    # what the connection held was delivered: no second login was needed
    assert logins(sshd.log) == before


def listener_pid(config: Path) -> int:
    """The sshd started with ``-f config`` (ours: its path is this test's)."""
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            # sshd rewrites its title: "sshd: /usr/sbin/sshd -D -e -f CONFIG [listener] ..."
            title = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        if b" -f " + os.fsencode(config) in title and b"[listener]" in title:
            return int(entry)
    raise AssertionError(f"no sshd running with {config}")


def children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out.append(int(entry))
    return out


def gone(pid: int) -> bool:
    """Ended (a zombie until running_sshd reaps it counts as ended)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def test_the_agent_comes_back_after_the_robots_sshd_restarts(tmp_path, runtime):
    """The robot's sshd stops, its sessions with it (a reboot, ``systemctl stop ssh``
    and the sessions killed), and starts again on the same port a few seconds later."""
    if find_sshd() is None:
        pytest.skip("sshd not installed")
    remote_dir = (tmp_path / "robot-ws").resolve()
    remote_dir.mkdir()
    restarted: subprocess.Popen[bytes] | None = None
    with running_sshd(tmp_path / "sshd") as server:
        home = make_ssh_home(tmp_path / "home", sshd=server)
        env = agent_env(home.home, tmp_path, runtime, remote_dir)
        env.pop("SSH_AUTH_SOCK", None)
        make_workspace(tmp_path / "ws")
        src, robot = tmp_path / "ws" / "src", remote_dir / "src"
        config = server.workdir / "sshd_config"
        try:
            with watching(env, tmp_path / "watch.log") as proc:
                wait_for(lambda: status(env).get("state") == "live", 30, what="live")
                assert sshd_answers("robot", config_path=home.config) is True
                listener = listener_pid(config)
                sessions = children(listener)
                assert sessions, "the agent's session is a child of the listener"
                os.kill(listener, signal.SIGTERM)
                for pid in sessions:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGTERM)
                wait_for(lambda: gone(listener), 10, what="sshd gone")
                assert sshd_answers("robot", config_path=home.config) is False
                (src / "my_pkg/while_down.txt").write_text("written while sshd was down\n")
                wait_for(lambda: status(env).get("state") == "offline", 30, what="offline")
                time.sleep(3.0)  # down for a while: several attempts fail, refused
                (src / "my_pkg/while_down.txt").write_text("edited again while it was down\n")
                with open(server.workdir / "sshd.log", "ab") as log_fd:
                    restarted = subprocess.Popen(
                        [find_sshd(), "-D", "-e", "-f", str(config)],
                        stdin=subprocess.DEVNULL,
                        stdout=log_fd,
                        stderr=log_fd,
                        start_new_session=True,
                    )
                wait_for(lambda: same(src, robot), 40, what="the changes after the restart")
                assert (robot / "my_pkg/while_down.txt").read_text() == (
                    "edited again while it was down\n"
                )
                wait_for(lambda: status(env).get("state") == "live", 10, what="live again")
                assert proc.poll() is None  # the same process, no user action
            assert "back online" in (tmp_path / "watch.log").read_text()
        finally:
            if restarted is not None:
                restarted.terminate()
                try:
                    restarted.wait(5)
                except subprocess.TimeoutExpired:
                    restarted.kill()
                    restarted.wait()


def test_reconnection_attempts_stay_a_quarter_second_apart_while_the_user_edits(tmp_path):
    """While offline: no wait over a second between attempts once the user changed
    something recently, however many attempts failed; a backoff only when idle; and a
    change ends the wait at once."""
    import threading

    from fetchsync.agent import service
    from fetchsync.config import Target

    target = Target(
        robot="robot",
        host="robot",
        user=None,
        workspace=tmp_path,
        remote_workspace="~/ws",
        is_local=False,
    )
    agent = service.Agent(target, rules=None)
    agent.request(paths={"a"})  # the user saved a file
    assert all(agent._retry_delay(n) <= 1.0 for n in range(50))
    agent._last_activity -= service.EDITING + 1  # nothing changed for a while
    assert agent._retry_delay(0) < agent._retry_delay(3) <= service.BACKOFF_CAP
    assert agent._retry_delay(50) > 1.0
    # the user saves during a wait of an hour: the wait ends then
    service_cap = service.BACKOFF_CAP
    service.BACKOFF_CAP = 3600.0
    try:
        waiter = threading.Thread(target=agent._wait_to_retry, args=(50,), daemon=True)
        waiter.start()
        time.sleep(0.2)
        assert waiter.is_alive()
        agent.request(paths={"b"})
        waiter.join(30)
        assert not waiter.is_alive()
    finally:
        service.BACKOFF_CAP = service_cap
