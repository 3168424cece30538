"""A workspace found around the current directory must be the user's (or root's).

Anyone can make ``/tmp/x/src`` and ``/tmp/x/devel``: a push typed in a directory of
one's own below it (``/tmp/x/mine``) took ``/tmp/x`` for its workspace and sent the
stranger's ``src/`` to the user's robot (with ``--build`` built and run there as the
user), and a pull wrote the robot's tree into the stranger's directory (git's
CVE-2022-24765). Such a workspace is refused in one line; one given with
``--workspace`` is the user's choice."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from helpers import local_env, make_workspace

from fetchsync.config import workspace_around
from fetchsync.errors import ConfigError

STRANGER = 54321  # a uid nobody on this machine has


@pytest.fixture
def planted(tmp_path: Path) -> Path:
    """``tmp_path/shared`` as /tmp is (1777), holding another user's workspace marks."""
    if os.geteuid() != 0:
        pytest.skip("giving files to another uid needs root")
    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, 0o1777)
    for part in ("src/evil_pkg", "devel"):
        (shared / part).mkdir(parents=True)
    (shared / "src/evil_pkg/payload.py").write_text("print('their code')\n")
    for path in [shared / "src", shared / "src/evil_pkg", shared / "devel"]:
        os.chown(path, STRANGER, STRANGER)
    os.chown(shared / "src/evil_pkg/payload.py", STRANGER, STRANGER)
    mine = shared / "mine"
    mine.mkdir()
    return mine


def test_another_users_workspace_around_is_refused(planted):
    with pytest.raises(ConfigError, match="belongs to another user"):
        workspace_around(planted)


def test_a_workspace_of_ours_whose_src_is_anothers_is_refused(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("giving files to another uid needs root")
    ws = make_workspace(tmp_path / "ws")
    (ws / "devel").mkdir()
    os.chown(ws / "src", STRANGER, STRANGER)
    with pytest.raises(ConfigError, match="src belongs to another user"):
        workspace_around(ws / "src")


def test_our_own_workspace_around_is_found(tmp_path):
    ws = make_workspace(tmp_path / "ws")
    (ws / "devel").mkdir()
    (ws / "src/deep").mkdir()
    assert workspace_around(ws / "src/deep") == ws


@pytest.mark.parametrize("verb", ["push", "pull"])
def test_a_push_or_pull_typed_below_a_planted_workspace_touches_nothing(planted, tmp_path, verb):
    env = local_env(tmp_path, make_ws=False)
    del env["FETCHSYNC_WORKSPACE"]
    env["PWD"] = str(planted)
    robot = tmp_path / "robot-home/robot_ws"
    (robot / "src/mine_on_robot").mkdir(parents=True)
    (robot / "src/mine_on_robot/secret.txt").write_text("the user's robot code\n")
    before = sorted(p.name for p in (planted.parent / "src").iterdir())
    args = [verb, "--json"] + (["--yes", "--no-safety"] if verb == "pull" else [])
    proc = _in(planted, args, env)
    assert proc.returncode == 2, proc.stderr.decode()
    lines = [ln for ln in proc.stderr.decode().splitlines() if ln.strip()]
    assert len(lines) == 1 and "belongs to another user" in lines[0], lines
    assert sorted(p.name for p in (robot / "src").iterdir()) == ["mine_on_robot"]
    assert sorted(p.name for p in (planted.parent / "src").iterdir()) == before
    # named, it is the user's choice
    given = _in(planted, ["push", "--json", "--workspace", str(planted.parent)], env)
    assert given.returncode == 0, given.stderr.decode()


def _in(cwd: Path, args: list[str], env: dict[str, str]):
    import subprocess
    import sys

    return subprocess.run(
        [sys.executable, "-m", "fetchsync", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        timeout=120,
    )
