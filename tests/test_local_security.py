"""Another user on the laptop: the local sockets' directory, the master's and the agent's peers.

Issue 22 item 11: with ``XDG_RUNTIME_DIR`` unset the sockets live in
``$TMPDIR/fetchsync-UID``, a name another user can take first. These tests add a
throwaway local user (they run as root, as CI does) who squats that directory or
connects to our sockets.
"""

from __future__ import annotations

import json
import os
import pwd
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Iterator

import pytest
from helpers import fetchsync, report, ssh_env, tree_of

from fetchsync.link import mux

needs_root = pytest.mark.skipif(
    os.getuid() != 0 or shutil.which("useradd") is None,
    reason="needs root and useradd to make a throwaway user",
)


@pytest.fixture
def intruder() -> Iterator[pwd.struct_passwd]:
    """A throwaway local user, deleted afterwards."""
    name = "fsq" + uuid.uuid4().hex[:8]
    subprocess.run(
        ["useradd", "--no-create-home", "--shell", "/bin/sh", name], check=True, capture_output=True
    )
    try:
        yield pwd.getpwnam(name)
    finally:
        subprocess.run(["pkill", "-KILL", "-u", name], check=False)
        subprocess.run(["userdel", name], check=False, capture_output=True)


def as_user(user: pwd.struct_passwd, *argv: str, **kwargs) -> subprocess.Popen:
    return subprocess.Popen(
        ["setpriv", f"--reuid={user.pw_uid}", f"--regid={user.pw_gid}", "--clear-groups", *argv],
        **kwargs,
    )


def run_as(user: pwd.struct_passwd, *argv: str) -> subprocess.CompletedProcess:
    proc = as_user(user, *argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = proc.communicate(timeout=60)
    return subprocess.CompletedProcess(argv, proc.returncode, out, err)


@pytest.fixture
def shared_tmp() -> Iterator[Path]:
    """A directory like /tmp (everyone may create in it, sticky), used as TMPDIR."""
    path = Path(tempfile.mkdtemp(prefix="fstmp", dir="/tmp"))
    path.chmod(0o1777)
    yield path
    shutil.rmtree(path, ignore_errors=True)


def said(proc: subprocess.CompletedProcess) -> list[str]:
    """The lines of stderr besides the one naming where the call goes (``push A → B``)."""
    return [line for line in proc.stderr.decode().strip().splitlines() if " → " not in line]


def masters_under(path: Path) -> list[int]:
    out = subprocess.run(
        ["pgrep", "-f", f"fetchsync.link.mux.*{path}"], check=False, capture_output=True
    )
    return [int(x) for x in out.stdout.split()]


def stop_masters(path: Path) -> None:
    for pid in masters_under(path):
        os.kill(pid, signal.SIGTERM)


def wait_for(cond, timeout: float = 60.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.1)
    return False


@pytest.mark.slow
@needs_root
@pytest.mark.ssh
@pytest.mark.parametrize("squat", ["their-directory", "symlink"])
def test_a_squatted_socket_directory_never_fails_a_push(
    squat, intruder, shared_tmp, ssh_home, remote_dir, tmp_path, monkeypatch
):
    """Another user's ``$TMPDIR/fetchsync-UID`` (or a symlink there, even to a private
    directory of ours) is never used: a push goes direct (saying why once when it
    wanted a master), ``FETCHSYNC_PERSIST=0`` and ``--robot local`` say nothing."""
    squatted = shared_tmp / f"fetchsync-{os.getuid()}"
    ours = Path(tempfile.mkdtemp(prefix="fsours", dir="/tmp"))  # private to us, 0700
    if squat == "their-directory":
        assert run_as(intruder, "mkdir", "-m", "0777", str(squatted)).returncode == 0
    else:
        assert run_as(intruder, "ln", "-s", str(ours), str(squatted)).returncode == 0
    try:
        env = ssh_env(
            ssh_home.home, remote_dir, tmp_path, TMPDIR=str(shared_tmp), FETCHSYNC_PERSIST="0"
        )
        env.pop("XDG_RUNTIME_DIR", None)
        local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
        proc = fetchsync("push", "--json", env=env, check=False)
        assert proc.returncode == 0, proc.stderr.decode()
        assert said(proc) == []
        assert tree_of(local) == tree_of(remote_dir / "src")
        # wanting a master: one line says why there is none; the push still works
        (local / "my_pkg/after.txt").write_text("after the squat\n")
        proc = fetchsync("push", "--json", env=dict(env, FETCHSYNC_PERSIST="60"), check=False)
        assert proc.returncode == 0, proc.stderr.decode()
        err = said(proc)
        assert len(err) == 1 and "not private to you" in err[0] and str(squatted) in err[0], err
        assert report(proc)["connection"] == "ssh"
        assert tree_of(local) == tree_of(remote_dir / "src")
        time.sleep(1)
        assert not masters_under(squatted) and not list(ours.iterdir())
        # the local robot needs no socket at all
        local_env = dict(
            env,
            FETCHSYNC_ROBOT="local",
            FETCHSYNC_PERSIST="60",
            FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "local-robot"),
            FETCHSYNC_REMOTE_WORKSPACE="~/ws",
            XDG_STATE_HOME=str(tmp_path / "st2"),
        )
        proc = fetchsync("push", "--json", env=local_env, check=False)
        assert proc.returncode == 0 and said(proc) == [], proc.stderr.decode()
        assert tree_of(local) == tree_of(tmp_path / "local-robot/ws/src")
    finally:
        stop_masters(squatted)
        shutil.rmtree(ours, ignore_errors=True)


@needs_root
def test_socket_directory_checks_do_not_follow_a_symlink(intruder, shared_tmp, monkeypatch):
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    monkeypatch.setenv("TMPDIR", str(shared_tmp))
    monkeypatch.setattr(tempfile, "tempdir", None)  # gettempdir() reads TMPDIR again
    ours = Path(tempfile.mkdtemp(prefix="fsours", dir="/tmp"))
    try:
        squatted = shared_tmp / f"fetchsync-{os.getuid()}"
        assert run_as(intruder, "ln", "-s", str(ours), str(squatted)).returncode == 0
        with pytest.raises(mux.ConnectError, match="symlink"):
            mux.socket_path("robot", None)
        os.unlink(squatted)
        assert mux.runtime_dir() == squatted  # made by us, 0700
        st = os.lstat(squatted)
        assert st.st_uid == os.getuid() and st.st_mode & 0o777 == 0o700
    finally:
        shutil.rmtree(ours, ignore_errors=True)


@pytest.mark.ssh
def test_an_unusable_runtime_directory_is_one_line_and_a_push_still_works(
    ssh_home, remote_dir, tmp_path
):
    """Issue 22 item 22: an ``XDG_RUNTIME_DIR`` where nothing can be made (here a file)."""
    fd, name = tempfile.mkstemp(prefix="fsnd", dir="/tmp")  # short: else /tmp would serve
    os.close(fd)
    blocker = Path(name)
    env = ssh_env(
        ssh_home.home, remote_dir, tmp_path, FETCHSYNC_PERSIST="60", XDG_RUNTIME_DIR=str(blocker)
    )
    proc = fetchsync("push", "--json", env=env, check=False)
    err = proc.stderr.decode()
    assert proc.returncode == 0 and "Traceback" not in err, err
    assert len(said(proc)) == 1 and str(blocker) in err
    assert tree_of(Path(env["FETCHSYNC_WORKSPACE"]) / "src") == tree_of(remote_dir / "src")
    proc = fetchsync("status", env=env, check=False)
    err = proc.stderr.decode()
    blocker.unlink()
    assert proc.returncode != 0 and "Traceback" not in err and len(said(proc)) == 1


@needs_root
@pytest.mark.ssh
def test_the_master_refuses_another_users_connection(intruder, ssh_home, remote_dir, tmp_path):
    """Even when its directory and socket are opened up (a mistake), the master serves
    no process of another uid (SO_PEERCRED)."""
    runtime = Path(tempfile.mkdtemp(prefix="fsrun", dir="/tmp"))
    try:
        env = ssh_env(
            ssh_home.home,
            remote_dir,
            tmp_path,
            FETCHSYNC_PERSIST="60",
            XDG_RUNTIME_DIR=str(runtime),
        )
        fetchsync("push", env=env)
        assert wait_for(lambda: list((runtime / "fetchsync").glob("mux-*.sock")))
        sock = next((runtime / "fetchsync").glob("mux-*.sock"))
        for path in (runtime, runtime / "fetchsync"):
            path.chmod(0o711)
        sock.chmod(0o666)
        marker = remote_dir / "pwned"
        code = (
            "import socket, sys; s = socket.socket(socket.AF_UNIX); s.connect(sys.argv[1]); "
            "s.sendall(sys.argv[2].encode() + b'\\n'); s.shutdown(socket.SHUT_WR); "
            "s.settimeout(10); data = s.recv(1 << 16); print(len(data))"
        )
        request = json.dumps({"exec": f"touch {marker}"})
        got = run_as(intruder, sys.executable, "-c", code, str(sock), request)
        assert got.stdout.strip() in (b"0", b""), got
        time.sleep(1)
        assert not marker.exists()
        # and we still are served
        for path in (runtime, runtime / "fetchsync"):
            path.chmod(0o700)
        (Path(env["FETCHSYNC_WORKSPACE"]) / "src/my_pkg/x.txt").write_text("x\n")
        assert report(fetchsync("push", "--json", env=env))["connection"] == "master"
    finally:
        stop_masters(runtime)
        shutil.rmtree(runtime, ignore_errors=True)


LISTENER = """
import os, socket, struct, sys
srv = socket.socket(socket.AF_UNIX)
srv.bind(sys.argv[1])
os.chmod(sys.argv[1], 0o666)
srv.listen(4)
print("up", flush=True)
while True:
    conn, _ = srv.accept()
    conn.recv(65536)
    out = b'{"ok": true, "status": {"state": "live"}}\\n' if "agent" in sys.argv[1] else (
        struct.pack(">BI", 3, 4) + struct.pack(">i", 0))
    conn.sendall(out)
    conn.close()
"""


@needs_root
@pytest.mark.parametrize("kind", ["mux", "agent"])
def test_a_socket_served_by_another_user_is_not_used(kind, intruder):
    """A master or agent socket in our directory but served by another uid is ignored."""
    from fetchsync.agent.control import call

    runtime = Path(tempfile.mkdtemp(prefix="fsrun", dir="/tmp"))
    listener = None
    try:
        runtime.chmod(0o777)  # the window a planted socket needs; closed again below
        path = runtime / f"{kind}-x.sock"
        listener = as_user(
            intruder, sys.executable, "-c", LISTENER, str(path), stdout=subprocess.PIPE
        )
        assert listener.stdout is not None and listener.stdout.readline() == b"up\n"
        runtime.chmod(0o700)
        if kind == "mux":
            assert mux.MuxTransport.attach(path, "robot") is None
        else:
            assert call(path, {"cmd": "status"}, timeout=5) is None
    finally:
        if listener is not None:
            listener.kill()
            listener.wait()
        shutil.rmtree(runtime, ignore_errors=True)
