"""watch --build's lock (issue 22, item 13): in the robot user's private directory, so another
robot user cannot block builds; run here as the Builder's bash, with a throwaway local user as
the other robot user."""

from __future__ import annotations

import hashlib
import os
import secrets
import shutil
import signal
import stat
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from fetchsync.agent.builder import lock_prelude

pytestmark = pytest.mark.skipif(
    os.geteuid() != 0
    or not all(shutil.which(t) for t in ("useradd", "userdel", "runuser", "flock")),
    reason="needs root, useradd, userdel, runuser and flock",
)

WORKSPACE = "/home/fetch/noetic"


@pytest.fixture
def other_user() -> Iterator[str]:
    name = f"fslock{os.getpid() % 100000}{secrets.randbelow(1000)}"
    subprocess.run(["useradd", "-m", "-s", "/bin/sh", name], check=True, capture_output=True)
    try:
        yield name
    finally:
        subprocess.run(["userdel", "-r", "-f", name], check=False, capture_output=True)


def build(env: dict[str, str], timeout: float = 20) -> subprocess.CompletedProcess[str]:
    """The Builder's lock lines, then a stand-in build."""
    script = lock_prelude(WORKSPACE) + "\necho built"
    return subprocess.run(
        ["bash", "-c", script],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def squat(user: str, path: Path) -> subprocess.Popen:
    """``user`` creates ``path`` for everyone to open and holds its lock until killed."""
    proc = subprocess.Popen(
        ["runuser", "-u", user, "--", "sh", "-c", f"umask 000; exec flock {path} sleep 300"],
        start_new_session=True,
    )
    end = time.monotonic() + 10
    while not path.exists() and time.monotonic() < end:
        time.sleep(0.02)
    time.sleep(0.2)  # flock has the lock once the file is there and it runs sleep
    return proc


def test_another_robot_user_cannot_block_builds(tmp_path, other_user):
    home = tmp_path / "home"
    home.mkdir()
    runtime = tmp_path / "run"
    runtime.mkdir(mode=0o700)
    env = {"PATH": os.environ["PATH"], "HOME": str(home), "XDG_RUNTIME_DIR": str(runtime)}
    key = hashlib.sha256(WORKSPACE.encode()).hexdigest()[:16]
    # the other user squats where the lock used to be: /tmp, named by our uid and the workspace
    old = Path(f"/tmp/fetchsync-build-{os.getuid()}-{key}.lock")
    old.unlink(missing_ok=True)
    squatter = squat(other_user, old)
    try:
        out = build(env)
        assert (out.returncode, out.stdout) == (0, "built\n"), out.stderr
        assert out.stderr == ""
        lock_dir = runtime / "fetchsync"
        assert (lock_dir / f"build-{key}.lock").is_file()
        info = lock_dir.stat()
        assert stat.S_IMODE(info.st_mode) == 0o700 and info.st_uid == os.getuid()
        # without XDG_RUNTIME_DIR: ~/.cache/fetchsync, private too
        out = build({k: v for k, v in env.items() if k != "XDG_RUNTIME_DIR"})
        assert out.stdout == "built\n" and out.stderr == ""
        assert stat.S_IMODE((home / ".cache/fetchsync").stat().st_mode) == 0o700
    finally:
        os.killpg(squatter.pid, signal.SIGKILL)  # runuser and the flock under it
        squatter.wait()
        old.unlink(missing_ok=True)


def test_a_lock_directory_of_someone_else_is_not_used(tmp_path, other_user):
    # a runtime directory that is not ours, and a ~/.cache/fetchsync that is a link to the
    # other user's directory: neither is used, the build runs without a lock and says so
    theirs = Path(f"/home/{other_user}/trap")
    subprocess.run(
        ["runuser", "-u", other_user, "--", "mkdir", "-m", "777", str(theirs)], check=True
    )
    home = tmp_path / "home"
    (home / ".cache").mkdir(parents=True)
    (home / ".cache/fetchsync").symlink_to(theirs)
    out = build({"PATH": os.environ["PATH"], "HOME": str(home), "XDG_RUNTIME_DIR": str(theirs)})
    assert out.stdout == "built\n"
    assert "no private directory for the build lock" in out.stderr
    assert list(theirs.iterdir()) == []
    # a lock that is ours and held makes the next build wait: the lock still works
    env = {"PATH": os.environ["PATH"], "HOME": str(tmp_path / "home2")}
    (tmp_path / "home2").mkdir()
    assert build(env).stdout == "built\n"
    key = hashlib.sha256(WORKSPACE.encode()).hexdigest()[:16]
    held = subprocess.Popen(
        ["flock", str(tmp_path / f"home2/.cache/fetchsync/build-{key}.lock"), "sleep", "300"]
    )
    try:
        time.sleep(0.3)
        with pytest.raises(subprocess.TimeoutExpired):
            build(env, timeout=1.5)
    finally:
        held.kill()
        held.wait()
