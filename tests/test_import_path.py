"""Our background and robot processes import nothing from their working directory.

``python -m`` and ``python -c`` put the working directory first on the import path. The
connection master (``-m fetchsync.link.mux``) and the resident (``-c``) a push starts
ran a ``json.py`` (``logging.py``, ``queue.py``, ...) lying in the directory where the
user typed ``fetchsync push`` (a shared checkout another user of the laptop can write,
/tmp): another user's code in the process holding the SSH session, where the push
itself (the console script puts its own directory first) never ran it. On the robot
the endpoint's stub (``python3 -S -c``, started in the login's home) imported
``hashlib``, ``json``, ``typing``, ``queue``, ... from there first: a ``~/queue.py``
broke every push ('the endpoint did not start: ImportError') or ran as the endpoint."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from helpers import fetchsync, local_env, report, ssh_env, tree_of
from test_mux_spare import masters, wait_for
from test_resident import resident_env, residents, traced

PLANTED = """
import os
with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "RAN"), "a") as fh:
    fh.write("%d\\n" % os.getpid())
raise ImportError("planted")
"""
# what the master, the resident, the stub, the loader and the endpoint import after start
NAMES = ("json", "argparse", "logging", "queue", "socket", "zlib", "hashlib", "typing")
NAMES += ("struct", "threading", "select", "zipfile", "shutil", "fcntl", "io", "os", "stat")


def plant(where: Path) -> Path:
    where.mkdir(parents=True, exist_ok=True)
    for name in NAMES:
        (where / f"{name}.py").write_text(PLANTED)
    return where / "RAN"


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    yield from resident_env(ssh_home.home, remote_dir, tmp_path)


@pytest.mark.ssh
def test_the_master_and_the_resident_import_nothing_from_where_the_push_was_typed(env, tmp_path):
    here = tmp_path / "shared"  # where the user typed the push
    ran = plant(here)

    def push() -> dict:
        # -P: the push as the console script runs it (its working directory not on its
        # path); what it starts in the background is what is checked
        proc = subprocess.run(
            [sys.executable, "-P", "-m", "fetchsync", "push", "--json"],
            cwd=here,
            env=env,
            capture_output=True,
            timeout=120,
        )
        assert proc.returncode == 0, proc.stderr.decode()
        return report(proc)

    runtime = Path(env["XDG_RUNTIME_DIR"])
    assert push()["connection"] in ("ssh", "master")
    assert wait_for(lambda: bool(masters(runtime)), timeout=30)
    if not residents(runtime):
        push()  # the first left the master (a resident needs one): this one the resident
    assert wait_for(lambda: bool(residents(runtime)), timeout=30)
    assert wait_for(lambda: any("resident: connected" in ln for ln in traced(env)), timeout=30)
    assert push()["connection"] == "resident"
    assert not ran.exists(), "the master or the resident ran a module of the working directory"


@pytest.mark.ssh
def test_the_robot_endpoint_imports_nothing_from_its_working_directory(
    ssh_home, remote_dir, tmp_path
):
    """Over the real sshd, the endpoint started in a directory of planted modules (the
    login's home stands there: the tests' robot logs in to this machine's own home)."""
    ran = plant(tmp_path / "robot-home")
    env = ssh_env(
        ssh_home.home,
        remote_dir,
        tmp_path,
        FETCHSYNC_REMOTE_PYTHON=f"cd {tmp_path / 'robot-home'} && python3",
    )
    r = report(fetchsync("push", "--json", env=env))
    assert r["ok"] and not ran.exists()
    assert tree_of(Path(env["FETCHSYNC_WORKSPACE"]) / "src") == tree_of(remote_dir / "src")
    # a Python 3.6 robot imports os at its first line (3.11 has it frozen)
    py36 = Path("/root/.pyenv/versions/3.6.15/bin/python3.6")
    if py36.exists():
        env["FETCHSYNC_REMOTE_PYTHON"] = f"cd {tmp_path / 'robot-home'} && {py36}"
        (Path(env["FETCHSYNC_WORKSPACE"]) / "src/new.txt").write_text("3.6\n")
        assert report(fetchsync("push", "--json", env=env))["ok"] and not ran.exists()


def test_the_local_robots_endpoint_imports_nothing_from_its_home(tmp_path):
    """The ``local`` robot starts its endpoint in its home, as sshd does."""
    env = local_env(tmp_path)
    ran = plant(tmp_path / "robot-home")
    r = report(fetchsync("push", "--json", env=env))
    assert r["ok"] and not ran.exists()
