"""``fetchsync conflicts``: list, diff and restore the robot's kept versions, over the real sshd."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers import fetchsync, report, ssh_env

pytestmark = pytest.mark.ssh

NODE = "my_pkg/src/node.cpp"
ROBOT_EDIT = "int main() { return 7; }  // robot edit\n"


@pytest.fixture
def env(ssh_home, remote_dir, tmp_path):
    return ssh_env(ssh_home.home, remote_dir, tmp_path)


def _make_conflict(env: dict, remote_dir: Path) -> Path:
    """Push, edit node.cpp on the robot and locally, push again: the robot's edit is kept."""
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    fetchsync("push", env=env)
    (remote_dir / "src" / NODE).write_text(ROBOT_EDIT)
    (local / NODE).write_text("int main() { return 1; }  // laptop edit\n")
    r = report(fetchsync("push", "--json", env=env))
    assert len(r["conflicts"]) == 1
    return local


@pytest.mark.slow
def test_list_diff_restore_a_robot_conflict(env, remote_dir):
    local = _make_conflict(env, remote_dir)
    ws = Path(env["FETCHSYNC_WORKSPACE"])

    listed = json.loads(fetchsync("conflicts", "--json", env=env).stdout)
    assert [(e["path"], e["size"]) for e in listed] == [(NODE, len(ROBOT_EDIT))]
    entry = listed[0]
    assert entry["remote_workspace"] == str(remote_dir) and entry["robot"] == "robot"
    assert (remote_dir / entry["kept"]).read_text().endswith("// robot edit\n")
    text = fetchsync("conflicts", "list", env=env)
    assert entry["time"] in text.stdout.decode() and NODE in text.stdout.decode()
    assert "conflicts list" in text.stderr.decode()  # says where it reads

    diff = fetchsync("conflicts", "diff", NODE, env=env).stdout.decode().splitlines()
    assert "+int main() { return 7; }  // robot edit" in diff
    assert "-int main() { return 1; }  // laptop edit" in diff

    out = fetchsync("conflicts", "restore", NODE, "--at", entry["time"], env=env).stdout.decode()
    assert (local / NODE).read_text() == ROBOT_EDIT
    trashed = list((ws / ".fetchsync" / "trash").glob("*/" + NODE))
    assert len(trashed) == 1 and trashed[0].read_text().endswith("// laptop edit\n")
    assert str(trashed[0]) in out and "next push" in out
    # the robot was only read: its kept version is still there
    assert (remote_dir / entry["kept"]).exists()
    # and the next push sends the restored version
    fetchsync("push", env=env)
    assert (remote_dir / "src" / NODE).read_text().endswith("// robot edit\n")


def test_trash_lists_what_a_push_deleted(env, remote_dir):
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    fetchsync("push", env=env)
    (local / NODE).unlink()
    fetchsync("push", env=env)
    assert json.loads(fetchsync("conflicts", "--json", env=env).stdout) == []
    listed = json.loads(fetchsync("conflicts", "--trash", "--json", env=env).stdout)
    assert [e["path"] for e in listed] == [NODE]
    fetchsync("conflicts", "--trash", "restore", NODE, env=env)
    assert (local / NODE).read_text() == "int main() { return 0; }\n"


def test_unknown_path_is_one_line_error(env, remote_dir):
    _make_conflict(env, remote_dir)
    proc = fetchsync("conflicts", "diff", "my_pkg/nothing.cpp", env=env, check=False)
    assert proc.returncode == 2
    assert "keeps no version" in proc.stderr.decode() and "Traceback" not in proc.stderr.decode()
    proc = fetchsync("conflicts", "restore", "../etc/passwd", env=env, check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr.decode()


def test_symlinked_conflicts_directory_on_the_robot_is_refused(env, remote_dir, tmp_path):
    fetchsync("push", env=env)
    outside = tmp_path / "outside"
    (outside / "20260101-000000-000001" / "my_pkg").mkdir(parents=True)
    (outside / "20260101-000000-000001" / "my_pkg" / "secret.txt").write_text("secret\n")
    (remote_dir / ".fetchsync" / "conflicts").symlink_to(outside)
    proc = fetchsync("conflicts", "--json", env=env, check=False)
    err = proc.stderr.decode()
    assert proc.returncode != 0 and "symlink" in err and "Traceback" not in err
    assert "secret" not in proc.stdout.decode()
    proc = fetchsync("conflicts", "restore", "my_pkg/secret.txt", env=env, check=False)
    assert proc.returncode != 0
    assert not (Path(env["FETCHSYNC_WORKSPACE"]) / "src/my_pkg/secret.txt").exists()


def test_symlinked_time_directory_on_the_robot_is_not_followed(env, remote_dir, tmp_path):
    _make_conflict(env, remote_dir)
    outside = tmp_path / "outside"
    (outside / "my_pkg").mkdir(parents=True)
    (outside / "my_pkg" / "secret.txt").write_text("secret\n")
    (remote_dir / ".fetchsync" / "conflicts" / "20990101-000000-000001").symlink_to(outside)
    listed = json.loads(fetchsync("conflicts", "--json", env=env).stdout)
    assert [e["path"] for e in listed] == [NODE]
    proc = fetchsync(
        "conflicts",
        "restore",
        "my_pkg/secret.txt",
        "--at",
        "20990101-000000-000001",
        env=env,
        check=False,
    )
    assert proc.returncode != 0
    assert not (Path(env["FETCHSYNC_WORKSPACE"]) / "src/my_pkg/secret.txt").exists()


def test_binary_versions_are_said_to_differ_with_their_sizes():
    from fetchsync.cli.conflicts import Kept, diff_lines

    kept = Kept("20260101-000000-000001", "my_pkg/blob.bin", 5, "conflicts")
    lines = diff_lines(kept, b"a\0bcd", b"xy\0", local_size=3)
    assert lines == ["my_pkg/blob.bin: binary or large files differ: robot 5 bytes, local 3 bytes"]
    assert diff_lines(kept, b"same\n", b"same\n", local_size=5)[0].endswith(
        "same as the local file"
    )
    assert "+robot" in diff_lines(kept, b"robot\n", None, local_size=-1)
