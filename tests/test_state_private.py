"""The laptop's state is its user's alone: it keeps the content of small text files
(dictionary writes), which another user of the laptop must not read."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from helpers import fetchsync, local_env


def _mode(path: Path) -> int:
    return stat.S_IMODE(os.lstat(path).st_mode)


def test_the_state_and_its_directory_are_the_users_alone(tmp_path):
    env = local_env(tmp_path)
    states = tmp_path / "state" / "fetchsync"
    states.mkdir(parents=True, mode=0o755)  # made before, by something with a wider umask
    states.chmod(0o755)
    old_umask = os.umask(0o022)
    try:
        fetchsync("push", env=env)
    finally:
        os.umask(old_umask)
    files = list(states.iterdir())
    assert any(f.name.endswith(".sqlite") for f in files), files
    assert _mode(states) == 0o700
    for f in files:
        assert _mode(f) == 0o600, (f.name, oct(_mode(f)))
    # a database left readable (by an older fetchsync) is made private again
    db = next(f for f in files if f.name.endswith(".sqlite"))
    db.chmod(0o644)
    (tmp_path / "ws/src/my_pkg/new.txt").write_text("new\n")
    fetchsync("push", env=env)
    assert _mode(db) == 0o600


def test_a_state_directory_that_is_not_the_users_is_refused(tmp_path):
    env = local_env(tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "fetchsync").symlink_to(elsewhere)  # a link put there
    proc = fetchsync("push", env=env, check=False)
    err = proc.stderr.decode()
    assert proc.returncode != 0 and "Traceback" not in err, err
    errors = [line for line in err.splitlines() if "error" in line]
    assert len(errors) == 1 and "not a directory of yours" in errors[0], err
    assert list(elsewhere.iterdir()) == []
