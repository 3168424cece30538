"""The watch agent before a mass deletion: it pauses, says so, and resumes once confirmed."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest
from helpers import fetchsync, local_env, report, tree_of
from test_watch import Watch, wait_for


@pytest.fixture
def agent_env(tmp_path: Path):
    runtime = Path(tempfile.mkdtemp(prefix="fsw", dir="/tmp"))  # AF_UNIX paths are short
    runtime.chmod(0o700)
    e = local_env(tmp_path, XDG_RUNTIME_DIR=str(runtime))
    src = tmp_path / "ws" / "src"
    (src / "many").mkdir()
    for i in range(40):
        (src / f"many/f{i}.txt").write_text(f"file {i}\n")
    yield e
    shutil.rmtree(runtime, ignore_errors=True)


def test_watch_pauses_before_deleting_most_of_the_robots_files(agent_env, tmp_path):
    src = Path(agent_env["FETCHSYNC_WORKSPACE"]) / "src"
    robot = Path(agent_env["FETCHSYNC_LOCAL_ROBOT_HOME"]) / "robot_ws" / "src"
    w = Watch(agent_env, tmp_path / "watch.log")
    try:
        wait_for(lambda: w.status().get("state") == "live", what="the agent to be live")
        assert tree_of(src) == tree_of(robot)
        files = sum(1 for p in robot.rglob("*") if not p.is_dir())
        shutil.rmtree(src / "many")  # rm -rf of most of the tree
        (src / "my_pkg/data.txt").unlink()
        wait_for(lambda: w.status().get("state") == "paused", what="the agent to pause")
        st = w.status()
        assert "would delete" in st["last_error"] and "push --force" in st["last_error"]
        # the watcher may see the rm -rf in several batches: those that together delete
        # no more than half of the robot's files go (to the robot's trash), the rest waits
        gone = 40 - len(list((robot / "many").iterdir()))
        assert gone * 2 <= files, (gone, files)
        text = fetchsync("status", env=agent_env).stdout.decode()
        assert text.startswith("paused:") and "push --force" in text
        wait_for(
            lambda: b"paused:" in (tmp_path / "watch.log").read_bytes(), what="the agent to say so"
        )
        flushed = fetchsync("flush", "--timeout", "5", env=agent_env, check=False)
        assert flushed.returncode != 0 and b"paused" in flushed.stderr
        # the confirmation: a forced push, which then has the agent look again
        r = report(fetchsync("push", "--json", "--force", env=agent_env))
        assert r["ok"] and r["deleted"] >= 2
        wait_for(lambda: w.status().get("state") == "live", what="the agent to resume")
        assert tree_of(src) == tree_of(robot)
        (src / "my_pkg/package.xml").write_text("<after/>\n")
        wait_for(lambda: tree_of(src) == tree_of(robot), what="the next change to be mirrored")
    finally:
        w.stop()
