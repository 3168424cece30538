"""Another user of the robot reads nothing of a file its owner kept private, whatever
fetchsync does with it there: pushed, replaced, set aside in the robot's trash (deleted)
or conflicts (edited on both sides), nor what fetchsync keeps of it (its index: content
hashes). The robot's home is one others may enter (0755: Ubuntu's default before 21.04);
the other user is ``nobody`` (setpriv), looking with grep and find.

The robot here is the built-in ``local`` one (the same endpoint, run as a process)."""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest
from helpers import fetchsync, local_env

NOBODY = 65534

pytestmark = pytest.mark.skipif(
    os.getuid() != 0 or shutil.which("setpriv") is None, reason="needs root and setpriv"
)


def _as_nobody(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", *argv],
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.fixture
def robot_home():
    """A robot home outside pytest's private temporary directory, open to others."""
    home = Path(tempfile.mkdtemp(prefix="fs-robot-home-", dir="/tmp"))
    home.chmod(0o755)
    yield home
    shutil.rmtree(home, ignore_errors=True)


def test_another_robot_user_reads_nothing_kept_private(tmp_path, robot_home):
    env = local_env(tmp_path, FETCHSYNC_LOCAL_ROBOT_HOME=str(robot_home))
    pkg = tmp_path / "ws/src/my_pkg"
    secret = pkg / "config/secret.yaml"
    secret.parent.mkdir()
    old = os.umask(0o022)  # the robot user's (and the laptop's) usual umask
    try:
        secret.write_text("token: SECRET-one\n")
        secret.chmod(0o600)
        fetchsync("push", env=env)
        robot = robot_home / "robot_ws/src/my_pkg/config/secret.yaml"
        assert robot.read_text() == "token: SECRET-one\n"
        # edited on both sides: the robot's version goes to its conflicts
        robot.write_text("token: SECRET-robot\n")
        secret.write_text("token: SECRET-two\n")
        proc = fetchsync("push", "--force", env=env, check=False)
        assert proc.returncode in (0, 1), proc.stderr
        # replaced again, then deleted: to the trash
        secret.write_text("token: SECRET-three\n")
        fetchsync("push", "--force", env=env)
        secret.unlink()
        fetchsync("push", "--force", env=env)
    finally:
        os.umask(old)
    ws = robot_home / "robot_ws"
    mine = subprocess.run(
        ["grep", "-rl", "SECRET", str(ws)], capture_output=True, text=True, check=False
    ).stdout.split()
    assert any("/.fetchsync/trash/" in p for p in mine), mine  # kept there, as promised
    assert any("/.fetchsync/conflicts/" in p for p in mine), mine
    # the other user enters the home and the workspace, and finds none of it
    seen = _as_nobody("ls", str(ws / "src/my_pkg"))
    assert seen.returncode == 0 and "package.xml" in seen.stdout, seen.stderr
    found = _as_nobody("grep", "-rl", "SECRET", str(ws))
    assert found.stdout == "", found.stdout
    readable = _as_nobody("find", str(ws / ".fetchsync"), "-readable")
    assert readable.stdout.strip() in ("", str(ws / ".fetchsync")), readable.stdout


def test_a_records_directory_another_user_made_is_refused(tmp_path):
    """In a workspace another robot user can write (a group's shared one), they may put
    their own ``.fetchsync`` in place of ours: the endpoint trusted its index, so a
    stat-cache row they forged made the robot list the content they chose for a file
    (their edit unseen by drift). It is refused, in one line."""
    from fetchsync.protocol import store as store_mod
    from fetchsync.protocol.hashing import BLAKE2B_128, digest

    ws = tmp_path / "ws"
    (ws / "src").mkdir(parents=True)
    node = ws / "src/node.py"
    node.write_text("print('theirs')\n")
    os.utime(node, (1_600_000_000, 1_600_000_000))
    meta = ws / ".fetchsync"
    meta.mkdir()
    # their index: node.py holds what the owner pushed (so drift sees no change)
    forger = store_mod.Store(str(ws), algorithm=BLAKE2B_128)
    forger.lock()
    st = node.stat()
    claimed = digest(BLAKE2B_128, b"print('mine!!')\n").hex()
    forger._set_cache("node.py", [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, claimed])
    forger.save_index()
    forger.close()
    for path in [meta, *meta.iterdir()]:
        os.chown(path, NOBODY, NOBODY)
    with pytest.raises(store_mod.StoreError, match="another user"):
        store = store_mod.Store(str(ws), algorithm=BLAKE2B_128)
        store.lock()
        listed = {x.path: x.hash for x in store.listing()[0]}
        store.close()
        assert listed["node.py"] != claimed, "the forged index was trusted"
