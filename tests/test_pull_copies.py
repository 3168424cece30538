"""A pull reuses a local file's content for a robot file that holds it (a copy made on
the laptop, nothing sent), but the pull moves a local file aside before it replaces it
(the trash keeps it): a copy whose source the same pull replaces found its source gone
and failed ('the copy's source ... is not here', exit 5), leaving the robot's new file
missing on the laptop. Such copies are read from the robot; a plain rename still copies.
Over the real sshd."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from helpers import fetchsync, report, ssh_env, tree_of

pytestmark = pytest.mark.ssh

TEXT = "the first version, long enough that a copy is worth it\n" * 40


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    env = ssh_env(ssh_home.home, remote_dir, tmp_path)
    pkg = Path(env["FETCHSYNC_WORKSPACE"]) / "src/my_pkg"
    (pkg / "a.launch").write_text(TEXT)
    (pkg / "b.launch").write_text("b's own content\n" * 30)
    (pkg / "c.yaml").write_text("c: 1\n" * 50)
    assert report(fetchsync("push", "--json", env=env))["ok"]
    return env


def pull(env):
    proc = fetchsync("pull", "--json", "--yes", "--no-safety", env=env, check=False)
    assert proc.returncode == 0, proc.stderr.decode()
    return report(proc)


def trashed(env) -> list[bytes]:
    trash = Path(env["FETCHSYNC_WORKSPACE"]) / ".fetchsync/trash"
    return [p.read_bytes() for p in trash.rglob("*") if p.is_file()]


def test_a_file_copied_then_edited_on_the_robot_is_pulled(env, remote_dir):
    robot = remote_dir / "src/my_pkg"
    (robot / "a2.launch").write_text(TEXT)  # cp a.launch a2.launch; then a.launch edited
    (robot / "a.launch").write_text("edited on the robot\n")
    r = pull(env)
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    assert tree_of(local) == tree_of(remote_dir / "src")
    assert TEXT.encode() in trashed(env)  # the laptop's old a.launch is kept
    assert r["ok"] and not r["errors"]


def test_two_files_swapped_on_the_robot_are_pulled(env, remote_dir):
    robot = remote_dir / "src/my_pkg"
    a, b = (robot / "a.launch").read_bytes(), (robot / "b.launch").read_bytes()
    (robot / "a.launch").write_bytes(b)
    (robot / "b.launch").write_bytes(a)
    pull(env)
    assert tree_of(Path(env["FETCHSYNC_WORKSPACE"]) / "src") == tree_of(remote_dir / "src")


def test_a_copied_file_replaced_by_a_directory_on_the_robot_is_pulled(env, remote_dir):
    robot = remote_dir / "src/my_pkg"
    (robot / "moved.launch").write_text(TEXT)
    os.unlink(robot / "a.launch")
    (robot / "a.launch").mkdir()
    (robot / "a.launch/inside.txt").write_text("now a directory\n")
    pull(env)
    assert tree_of(Path(env["FETCHSYNC_WORKSPACE"]) / "src") == tree_of(remote_dir / "src")


def test_a_file_renamed_on_the_robot_is_still_copied_on_the_laptop(env, remote_dir):
    robot = remote_dir / "src/my_pkg"
    os.rename(robot / "a.launch", robot / "renamed.launch")
    r = pull(env)
    assert tree_of(Path(env["FETCHSYNC_WORKSPACE"]) / "src") == tree_of(remote_dir / "src")
    assert [p["how"] for p in r["planned"] if p["path"].endswith("renamed.launch")] == ["copy"]
    assert r["bytes_received"] < len(TEXT) // 2  # its content did not cross the link
