"""A source file of a few KiB edited in one line travels as a delta against the
signature the laptop kept of what it last sent (issue 24: real history's bytes), and
the robot ends up byte for byte identical; one the robot changed meanwhile is not
patched blindly."""

from __future__ import annotations

import random
import time
from pathlib import Path

import pytest
from helpers import fetchsync, local_env, report, tree_of


@pytest.fixture
def env(tmp_path: Path) -> dict:
    return local_env(tmp_path)


def source(lines: int, seed: int) -> str:
    """Code-like text that zlib cannot shrink much (distinct identifiers)."""
    rng = random.Random(seed)
    words = ["%08x" % rng.getrandbits(32) for _ in range(lines * 3)]
    return "".join(
        f"int f_{words[3 * i]}(int a) {{ return a * 0x{words[3 * i + 1]} ^ {words[3 * i + 2]}; }}\n"
        for i in range(lines)
    )


def test_a_small_source_files_one_line_edit_goes_as_a_delta(env):
    src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    robot = Path(env["FETCHSYNC_LOCAL_ROBOT_HOME"]) / "robot_ws/src"
    f = src / "my_pkg/src/node.cpp"
    f.parent.mkdir(parents=True, exist_ok=True)
    f.write_text(source(90, 1))  # ~5 KiB: under the old 16 KiB threshold
    size = f.stat().st_size
    assert size < 16 * 1024  # under the old threshold, which sent such files whole
    report(fetchsync("push", "--json", env=env))
    time.sleep(0.01)
    lines = f.read_text().splitlines(keepends=True)
    lines[45] = "int edited(int a) { return a; }\n"
    f.write_text("".join(lines))
    r = report(fetchsync("push", "--json", env=env))
    assert r["deltas"] == 1, r
    assert r["bytes_sent"] < size // 2, r  # not the whole file (which barely compresses)
    assert tree_of(src) == tree_of(robot)


def test_a_small_file_changed_on_the_robot_is_not_patched_blindly(env):
    src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    robot = Path(env["FETCHSYNC_LOCAL_ROBOT_HOME"]) / "robot_ws/src"
    f = src / "my_pkg/src/node.cpp"
    f.parent.mkdir(parents=True, exist_ok=True)
    f.write_text(source(90, 2))
    report(fetchsync("push", "--json", env=env))
    # someone edits the robot's copy, then the laptop's changes too
    theirs = robot / "my_pkg/src/node.cpp"
    theirs.write_text(theirs.read_text().replace("int f_", "long f_", 1))
    time.sleep(0.01)
    f.write_text(f.read_text() + "int added(void) { return 1; }\n")
    r = report(fetchsync("push", "--json", env=env))
    assert len(r["conflicts"]) == 1, r  # the robot's version is kept aside, not lost
    assert tree_of(src) == tree_of(robot)
