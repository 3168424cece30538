"""Link, process and disk faults during push and pull, end to end.

Each test breaks something real while a transfer is under way (the fault
proxy in front of the real sshd, a SIGKILL, a full tmpfs) and then checks two
things: the CLI failed with one clear line and no traceback, and the next
push or pull converges with no temporaries left behind.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import fetchsync, report, ssh_env, tree_of, without_where

pytestmark = pytest.mark.ssh

# Every fault must end a blocked CLI well within this (keepalives are 5 s).
FAULT_DEADLINE = 60


def temporaries(root: Path) -> list[str]:
    """Leftover temporaries of an interrupted write anywhere under ``root``."""
    out = []
    for dirpath, dirs, files in os.walk(root):
        for name in dirs + files:
            if "fetchsync-tmp" in name:
                out.append(os.path.join(dirpath, name))
    return out


def assert_one_line_failure(proc: subprocess.CompletedProcess | tuple[int, bytes]) -> str:
    code, err = (proc.returncode, proc.stderr) if not isinstance(proc, tuple) else proc
    text = err.decode("utf-8", "replace")
    assert code not in (0, None), text
    assert "Traceback" not in text, text
    lines = without_where(text)
    assert len(lines) == 1, text
    return lines[0]


def start(args: list[str], env: dict) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "fetchsync", *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


def finish(proc: subprocess.Popen, timeout: float = FAULT_DEADLINE) -> tuple[int, bytes]:
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        pytest.fail(f"fetchsync hung for {timeout} s after the fault:\n{err.decode()}")
    return proc.returncode, err


def wait_for(cond, timeout: float = 30, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.02)


def bulky_files(src: Path, *, count: int = 40, size: int = 64 * 1024) -> None:
    """Incompressible files, so a throttled link takes a while to carry them."""
    bulk = src / "bulk"
    bulk.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        (bulk / f"blob{i:03}.bin").write_bytes(os.urandom(size))


@pytest.fixture
def env(proxied_home, remote_dir, tmp_path):
    return ssh_env(proxied_home.home, remote_dir, tmp_path)


def local_src(env: dict) -> Path:
    return Path(env["FETCHSYNC_WORKSPACE"]) / "src"


@pytest.mark.slow
@pytest.mark.parametrize("fault", ["blackhole", "cut"])
def test_link_fault_mid_push_fails_cleanly_and_the_next_push_converges(
    env, fault_proxy, remote_dir, fault
):
    bulky_files(local_src(env))
    fault_proxy.throttle(bytes_per_second=200_000)
    proc = start(["push"], env)
    wait_for(
        lambda: (remote_dir / "src").exists() or proc.poll() is not None, what="the push to start"
    )
    time.sleep(0.5)
    getattr(fault_proxy, fault)()
    line = assert_one_line_failure(finish(proc))
    assert "robot" in line
    fault_proxy.throttle()
    fault_proxy.pass_through()
    fetchsync("push", env=env)
    assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
    assert temporaries(remote_dir) == []


@pytest.mark.slow
@pytest.mark.parametrize("fault", ["blackhole", "cut"])
def test_link_fault_mid_pull_leaves_the_local_tree_consistent(env, fault_proxy, remote_dir, fault):
    fetchsync("push", env=env)
    before = tree_of(local_src(env))
    # robot-side content the pull must fetch, big enough to take a while throttled
    bulky_files(remote_dir / "src", count=40)
    fault_proxy.throttle(bytes_per_second=200_000)
    proc = start(["pull", "--yes"], env)
    time.sleep(1.5)
    getattr(fault_proxy, fault)()
    assert_one_line_failure(finish(proc))
    # whatever arrived is whole: every local file is either as before or the robot's
    after = tree_of(local_src(env))
    robot = tree_of(remote_dir / "src")
    for path, entry in after.items():
        assert entry == before.get(path) or entry == robot.get(path), path
    assert temporaries(local_src(env).parent) == []
    fault_proxy.throttle()
    fault_proxy.pass_through()
    fetchsync("pull", "--yes", env=env)
    assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
    assert temporaries(local_src(env).parent) == []


def test_slow_link_push_is_correct(env, fault_proxy, remote_dir):
    fault_proxy.throttle(bytes_per_second=400_000, latency=0.05)
    fetchsync("push", env=env)
    assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
    data = local_src(env) / "my_pkg/data.txt"
    data.write_text("// edited over a slow link\n" + data.read_text())
    (local_src(env) / "my_pkg/package.xml").rename(local_src(env) / "my_pkg/package2.xml")
    r = report(fetchsync("push", "--json", env=env))
    assert r["ok"] and r["deltas"] == 1
    assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
    assert temporaries(remote_dir) == []


def test_a_slow_link_keeps_compressing_what_only_halves(env, fault_proxy, remote_dir):
    """Over a slow link, data that shrinks only to about half (hex dumps here, meshes of
    floats in a workspace) is compressed, even after large requests went out and were
    timed: only a link proved fast leaves it as it is (sync.WORTH_WHEN_FAST)."""
    fault_proxy.throttle(bytes_per_second=8_000_000)
    src = local_src(env)
    big = src / "big"
    big.mkdir(parents=True)
    noise = 0
    for i in range(3):  # each a request of its own, timed; the third waits for the first
        blob = os.urandom(4 * 1024 * 1024 + 65536)
        (big / f"a{i}.bin").write_bytes(blob)
        noise += len(blob)
    hexed = 0
    for i in range(8):
        text = os.urandom(128 * 1024).hex().encode()
        (big / f"b{i}.txt").write_bytes(text)
        hexed += len(text)
    r = report(fetchsync("push", "--json", env=env))
    assert r["ok"] and tree_of(src) == tree_of(remote_dir / "src")
    assert r["bytes_sent"] < noise + 0.75 * hexed  # compressed: ~0.55 of it


@pytest.mark.slow
def test_slow_link_shows_progress_on_a_terminal(env, fault_proxy, remote_dir):
    """A transfer longer than a second draws a progress bar on a terminal: the initial
    push, and a later push of a few changed files (the path-by-path one) too."""
    from terminal import Terminal

    # incompressible and larger than SSH's 2 MiB window (what fits in it counts as
    # sent at once): ~4 s at 1 MB/s
    blob = local_src(env) / "my_pkg" / "blob.bin"
    blob.write_bytes(os.urandom(4_000_000))
    fault_proxy.throttle(bytes_per_second=1_000_000, latency=0.02)
    for _ in range(2):
        term = Terminal(["push"], env)
        assert term.wait(timeout=60) == 0, term.output
        bars = [chunk for chunk in term.output.split(b"\r") if chunk.startswith(b"[#")]
        assert bars and b"% " in bars[-1] and b"of " in bars[-1], term.output
        assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
        blob.write_bytes(os.urandom(4_000_000))
    fault_proxy.pass_through()


def robot_scratch(remote_dir: Path) -> list[str]:
    """Leftovers of an interrupted session in the robot's ``.fetchsync/tmp``."""
    tmp = remote_dir / ".fetchsync" / "tmp"
    return sorted(os.listdir(tmp)) if tmp.is_dir() else []


@pytest.mark.slow
def test_client_killed_mid_transfer_of_a_large_file(env, fault_proxy, remote_dir):
    big = local_src(env) / "my_pkg" / "model.bin"
    old = os.urandom(60 * 1024 * 1024)
    big.write_bytes(old)
    fetchsync("push", env=env)
    robot_big = remote_dir / "src/my_pkg/model.bin"
    assert robot_big.read_bytes() == old
    big.write_bytes(os.urandom(60 * 1024 * 1024))  # nothing in common with the old one
    fault_proxy.throttle(bytes_per_second=4_000_000)
    proc = start(["push"], env)
    # kill it once the robot has started receiving the new content
    wait_for(
        lambda: (
            robot_scratch(remote_dir) or temporaries(remote_dir / "src") or proc.poll() is not None
        ),
        timeout=FAULT_DEADLINE,
        what="the transfer to start",
    )
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    # the robot holds the whole old file, never a mix of the two
    assert robot_big.read_bytes() == old
    fault_proxy.throttle()
    fetchsync("push", env=env)
    assert robot_big.read_bytes() == big.read_bytes()
    assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
    assert temporaries(remote_dir) == [] and robot_scratch(remote_dir) == []


def _children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid:
            out.append(int(entry))
    return out


def endpoints_under(pid: int) -> list[int]:
    """Robot-side endpoints started by our own sshd (never another test run's)."""
    found, todo = [], [pid]
    while todo:
        for child in _children(todo.pop()):
            todo.append(child)
            try:
                cmdline = Path(f"/proc/{child}/cmdline").read_bytes()
            except OSError:
                continue
            if b"FSYNC-NEED" in cmdline:  # the endpoint command (loader.STUB)
                found.append(child)
    return found


def test_robot_endpoint_killed_mid_session(env, fault_proxy, remote_dir, sshd):
    bulky_files(local_src(env))
    sshd_pid = int((sshd.workdir / "sshd.pid").read_text())
    fault_proxy.throttle(bytes_per_second=200_000)
    proc = start(["push"], env)
    wait_for(lambda: endpoints_under(sshd_pid) or proc.poll() is not None, what="the endpoint")
    time.sleep(0.5)
    # an endpoint may end on its own between the listing and the kill (a spare whose
    # connection went with the first one): at least one must have been running to kill
    killed = []
    for pid in endpoints_under(sshd_pid):
        try:
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
        except ProcessLookupError:
            pass
    assert killed, "no robot endpoint was running mid-push"
    line = assert_one_line_failure(finish(proc))
    assert "robot" in line
    fault_proxy.throttle()
    fetchsync("push", env=env)
    assert tree_of(local_src(env)) == tree_of(remote_dir / "src")
    assert temporaries(remote_dir) == [] and robot_scratch(remote_dir) == []


@pytest.fixture
def tiny_disk(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    where = tmp_path / "tiny-robot-ws"
    where.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(where)], capture_output=True
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    yield where
    subprocess.run(["umount", "-l", str(where)], check=False)


def fill_tiny_disk(env: dict, disk: Path) -> tuple[dict, subprocess.CompletedProcess]:
    """Sync a small tree onto ``disk``, then push edits plus more than it holds."""
    src = local_src(env)
    (src / "my_pkg/data.txt").write_text("small now\n")
    fetchsync("push", env=env)
    synced = tree_of(disk / "src")
    for path, entry in synced.items():
        if entry[0] == "f":
            (src / path).write_bytes(entry[2] + b"# edited\n")
    bulky_files(src, count=6, size=512 * 1024)
    return synced, fetchsync("push", env=env, check=False)


def test_robot_disk_full_keeps_what_was_synced(env, tiny_disk):
    env = dict(env, FETCHSYNC_REMOTE_WORKSPACE=str(tiny_disk))
    synced, proc = fill_tiny_disk(env, tiny_disk)
    err = proc.stderr.decode()
    assert proc.returncode != 0 and "Traceback" not in err
    # the CLI lists each failed path, then ends on one line that names the cause
    last = err.strip().splitlines()[-1]
    assert last.startswith("fetchsync: error:") and "no space" in last.lower(), err
    after = tree_of(tiny_disk / "src")
    local = tree_of(local_src(env))
    for path, entry in synced.items():
        assert after.get(path) in (entry, local.get(path)), path
    assert temporaries(tiny_disk) == [] and robot_scratch(tiny_disk) == []


def test_robot_disk_full_reports_each_failed_path_once(env, tiny_disk):
    env = dict(env, FETCHSYNC_REMOTE_WORKSPACE=str(tiny_disk))
    _synced, proc = fill_tiny_disk(env, tiny_disk)
    lines = [line.strip() for line in proc.stderr.decode().splitlines() if line.strip()]
    per_path = [line for line in lines if line.startswith("error:")]
    assert per_path and len(per_path) == len(set(per_path)), lines


@pytest.mark.slow
def test_a_push_does_not_wait_on_a_watch_agent_whose_robot_is_offline(env, fault_proxy, tmp_path):
    """Issue 22 item 18: with ``fetchsync watch`` running and the robot gone, a push says so
    at once and goes direct, which fails like any push to an unreachable robot."""
    import json
    import tempfile

    runtime = Path(tempfile.mkdtemp(prefix="fsw", dir="/tmp"))
    env = dict(env, XDG_RUNTIME_DIR=str(runtime))
    watch = start(["watch"], env)
    try:

        def live() -> bool:
            out = fetchsync("status", "--json", env=env, check=False)
            return out.returncode == 0 and json.loads(out.stdout).get("state") == "live"

        wait_for(live, 30, "the agent to be live")
        fault_proxy.blackhole()
        (local_src(env) / "my_pkg/while_away.txt").write_text("the robot is away\n")
        code, err = finish(start(["push"], env))
        text = err.decode()
        assert "the watch agent cannot reach its robot" in text and "pushing directly" in text, text
        assert code == 3 and "Traceback" not in text, text
        # and once the agent knows, a push says so without waiting for the agent at all
        code, err = finish(start(["push"], env))
        assert code == 3 and "the watch agent cannot reach its robot" in err.decode()
    finally:
        watch.terminate()
        watch.communicate(timeout=20)
        import shutil

        shutil.rmtree(runtime, ignore_errors=True)


def marked(mark: str) -> list[int]:
    """The robot-side processes of a call started with ``-X fsmark=MARK`` (the robot is here)."""
    out = subprocess.run(["pgrep", "-f", f"fsmark={mark}"], check=False, capture_output=True)
    return [int(p) for p in out.stdout.split() if int(p) != os.getpid()]


def signal_all(pids: list[int], sig: int) -> None:
    for pid in pids:
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            pass


@pytest.fixture
def marked_env(env, tmp_path):
    """``env`` whose robot endpoint is recognisable (``-X fsmark=...``), with a 3 s deadline."""
    import uuid

    mark = uuid.uuid4().hex[:12]
    yield (
        dict(env, FETCHSYNC_DEADLINE="3", FETCHSYNC_REMOTE_PYTHON=f"python3 -X fsmark={mark}"),
        mark,
    )
    signal_all(marked(mark), signal.SIGCONT)
    signal_all(marked(mark), signal.SIGKILL)


@pytest.mark.slow
@pytest.mark.parametrize("via", ["direct", "master", "local"])
def test_a_stalled_robot_endpoint_ends_the_call_within_the_deadline(
    via, marked_env, fault_proxy, remote_dir, tmp_path
):
    """Issue 22 item 17: the robot's endpoint stops (SIGSTOP) mid-push with the link up; the
    call ends after the progress deadline with one line and exit 3, and once the endpoint
    runs again it ends: nothing is left running on the robot."""
    import tempfile

    env, mark = marked_env
    runtime = Path(tempfile.mkdtemp(prefix="fsrun", dir="/tmp"))
    if via == "master":
        env = dict(env, FETCHSYNC_PERSIST="60", XDG_RUNTIME_DIR=str(runtime))
    elif via == "local":
        env = dict(
            env,
            FETCHSYNC_ROBOT="local",
            FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "lr"),
            FETCHSYNC_REMOTE_WORKSPACE="~/ws",
        )
    try:
        fetchsync("push", env=dict(env, FETCHSYNC_DEADLINE="30"))
        if via == "master":
            wait_for(lambda: list((runtime / "fetchsync").glob("mux-*.sock")), 20, "a master")
        # the local robot has no link to slow it: enough data that the push still runs
        # when the test stops its endpoint on a busy machine (with 60 files it had
        # finished before the SIGSTOP once, at load 12)
        bulky_files(local_src(env), count=60 if via != "local" else 400)
        fault_proxy.throttle(bytes_per_second=300_000)
        proc = start(["push"], env)
        wait_for(lambda: marked(mark), 30, "the robot's endpoint")
        if via != "local":  # no link to throttle: stopped as it starts
            time.sleep(0.5)
        stopped = marked(mark)
        signal_all(stopped, signal.SIGSTOP)
        line = assert_one_line_failure(finish(proc))
        assert proc.returncode == 3 and "made no progress for 3 s" in line, line
        signal_all(stopped, signal.SIGCONT)
        # the link at full speed again before the wait: through a master, the abandoned
        # call's bytes already in the master's socket (up to the whole 3.8 MB push) are
        # carried to the resumed endpoint before it reads the end of its input, 13 s of
        # the 300 kB/s throttle alone, over the 20 s below at load 20 (a flake, not a
        # lingering endpoint: it ended once they were through)
        fault_proxy.pass_through()
        # nothing but the master's new spare endpoint (test_mux_spare.py) is left
        wait_for(lambda: len(marked(mark)) <= (via == "master"), 20, "the robot's endpoint to end")
        fetchsync("push", env=dict(env, FETCHSYNC_DEADLINE="30"))  # the next call converges
        robot = tmp_path / "lr/ws/src" if via == "local" else remote_dir / "src"
        assert tree_of(local_src(env)) == tree_of(robot)
    finally:
        subprocess.run(["pkill", "-f", f"fetchsync.link.mux.*{runtime}"], check=False)
        import shutil

        shutil.rmtree(runtime, ignore_errors=True)


def test_an_endpoint_that_never_says_hello_ends_the_call(marked_env):
    """The robot's command never starts the endpoint (here: it waits on its input first)."""
    env, mark = marked_env
    env = dict(env, FETCHSYNC_REMOTE_PYTHON=f"read x; : fsmark={mark}; python3")
    line = assert_one_line_failure(finish(start(["push"], env)))
    assert "made no progress for 3 s" in line
    wait_for(lambda: not marked(mark), 20, "the robot's command to end")


@pytest.mark.slow
def test_the_first_ctrl_c_ends_a_push_and_leaves_no_endpoint_running(marked_env, fault_proxy):
    env, mark = marked_env
    env = dict(env, FETCHSYNC_DEADLINE="600")
    fetchsync("push", env=env)
    bulky_files(local_src(env), count=100)  # more than the SSH window and the pipes hold
    fault_proxy.throttle(bytes_per_second=1_000_000)
    proc = start(["push"], env)
    wait_for(lambda: marked(mark), 30, "the robot's endpoint")
    time.sleep(0.5)
    stopped = marked(mark)
    signal_all(stopped, signal.SIGSTOP)  # the robot stalls: blocked in I/O, or stopped
    time.sleep(4.0)  # the push fills the SSH window and blocks sending
    proc.send_signal(signal.SIGINT)
    code, err = finish(proc, timeout=15)
    assert code == 130 and "interrupted" in err.decode() and "Traceback" not in err.decode(), err
    signal_all(stopped, signal.SIGCONT)
    wait_for(lambda: not marked(mark), 20, "the robot's endpoint to end")
