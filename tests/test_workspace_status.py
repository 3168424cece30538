"""workspace-status: real git repositories, the ``local`` robot and the real sshd robot."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import time
from pathlib import Path

import pytest
from helpers import clean_env, fetchsync, tree_of, without_where

from fetchsync.chores.workspace_status import (
    DIFFERS,
    IN_SYNC,
    Found,
    RobotView,
    count_by_row,
    find_repositories,
)

# a developer's git configuration (signing, hooks, default branch) stays out of the tests
GIT_ENV = {
    "GIT_AUTHOR_NAME": "t",
    "GIT_AUTHOR_EMAIL": "t@example.com",
    "GIT_COMMITTER_NAME": "t",
    "GIT_COMMITTER_EMAIL": "t@example.com",
    "GIT_CONFIG_GLOBAL": os.devnull,
    "GIT_CONFIG_NOSYSTEM": "1",
}


def git(cwd: Path, *args: str) -> str:
    proc = subprocess.run(
        ["git", "-C", str(cwd), *args],
        capture_output=True,
        check=True,
        env={**os.environ, **GIT_ENV},
    )
    return proc.stdout.decode().strip()


def repo(
    path: Path,
    *,
    branch: str = "main",
    files: dict[str, str] | None = None,
    commit: bool = True,
    git_dir: Path | None = None,
) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    extra = [f"--separate-git-dir={git_dir}"] if git_dir is not None else []
    git(path, "-c", f"init.defaultBranch={branch}", "init", "-q", *extra)
    for name, text in (files or {"README.md": f"{path.name}\n"}).items():
        (path / name).parent.mkdir(parents=True, exist_ok=True)
        (path / name).write_text(text)
    if commit:
        git(path, "add", "-A")
        git(path, "commit", "-q", "-m", "init")
    return path


@pytest.fixture
def ws(tmp_path: Path) -> Path:
    """src/ with every shape: nested repos, a .git file, dirty, detached, no commits, untracked."""
    src = tmp_path / "ws" / "src"
    alpha = repo(src / "alpha", files={"a.txt": "a\n", "b.txt": "b\n", "c.txt": "c\n"})
    repo(alpha / "nested", branch="devel", files={"n.txt": "n\n"})  # a repository in a repository
    beta = repo(src / "beta")
    (beta / "README.md").write_text("changed\n")  # dirty
    gamma = repo(src / "gamma")
    git(gamma, "checkout", "-q", "--detach", "HEAD")  # detached
    repo(src / "delta", branch="wip", commit=False)  # no commits yet
    repo(src / "sub", git_dir=tmp_path / "sub.git")  # .git is a file
    assert (src / "sub" / ".git").is_file()
    (src / "loose" / "inner").mkdir(parents=True)  # untracked, holding a repo
    (src / "loose" / "notes.txt").write_text("notes\n")
    repo(src / "loose" / "inner", files={"i.txt": "i\n"})
    (src / "CMakeLists.txt").symlink_to("/opt/ros/noetic/share/catkin/cmake/toplevel.cmake")
    return src.parent


def base_env(ws: Path, tmp_path: Path, **extra: str) -> dict[str, str]:
    values = {**GIT_ENV, "FETCHSYNC_WORKSPACE": str(ws), "XDG_STATE_HOME": str(tmp_path / "state")}
    return clean_env(**{**values, **extra})


def status(env: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    return fetchsync("workspace-status", *args, env=env)


def table(proc: subprocess.CompletedProcess) -> tuple[list[str], dict[str, list[str]]]:
    """The header and the rows of the printed table, by repository path."""
    lines = proc.stdout.decode().splitlines()
    assert lines[0].startswith("Status of ") and set(lines[2]) <= {"-", "|"}
    split = [[c.strip() for c in line.split("|")] for line in lines[1:2] + lines[3:]]
    return split[0], {r[0]: r[1:] for r in split[1:]}


def robot_column(proc: subprocess.CompletedProcess) -> dict[str, str]:
    header, rows = table(proc)
    assert header[-1] == "robot"
    return {path: cells[-1] for path, cells in rows.items()}


# --------------------------------------------------------------------------- library
def test_find_repositories_nested_submodule_like_and_untracked(ws: Path):
    assert find_repositories(ws / "src") == [
        Found("alpha", True),
        Found("alpha/nested", True),
        Found("beta", True),
        Found("delta", True),
        Found("gamma", True),
        Found("loose", False),
        Found("loose/inner", True),
        Found("sub", True),
    ]


def test_src_that_is_a_repository_has_no_untracked_rows(tmp_path: Path):
    src = repo(tmp_path / "src", files={"pkg/x.txt": "x\n"})
    repo(src / "vendored")
    assert find_repositories(src) == [Found(".", True), Found("vendored", True)]


def test_paths_count_for_the_innermost_repository():
    counts = count_by_row(["a/x", "a/b/y", "a/b/z", "a", "c/d", "top.txt"], ["a", "a/b", "c"])
    assert counts == {"a": 2, "a/b": 2, "c": 1}
    assert count_by_row(["top.txt", "a/x"], [".", "a"]) == {".": 1, "a": 1}
    assert RobotView(DIFFERS, 1).text() == "1 path differs"
    assert RobotView(DIFFERS, 2).text() == "2 paths differ"
    assert RobotView(IN_SYNC).text() == "in sync"


# --------------------------------------------------------------------------- git columns
def test_table_without_a_robot(ws: Path, tmp_path: Path):
    proc = status(base_env(ws, tmp_path))
    assert proc.returncode == 0 and proc.stderr == b""
    header, rows = table(proc)
    assert header == ["repository", "branch", "sha"]
    src = ws / "src"

    def short(path: str) -> str:
        return git(src / path, "rev-parse", "--short", "HEAD")

    assert rows == {
        "alpha": ["main", short("alpha")],
        "alpha/nested": ["devel", short("alpha/nested")],
        "beta": ["main", short("beta") + "-dirty"],
        "delta": ["wip", "(no commits)"],
        "gamma": ["(detached)", short("gamma")],
        "loose": ["-", "untracked"],
        "loose/inner": ["main", short("loose/inner")],
        "sub": ["main", short("sub")],
    }


def test_untracked_files_do_not_make_a_repository_dirty_but_staged_ones_do(
    ws: Path, tmp_path: Path
):
    env = base_env(ws, tmp_path)
    (ws / "src/alpha/new.txt").write_text("new\n")  # untracked (the nested repo is too)
    assert table(status(env))[1]["alpha"][1].endswith("-dirty") is False
    git(ws / "src/alpha", "add", "new.txt")
    assert table(status(env))[1]["alpha"][1].endswith("-dirty")


def test_a_broken_repository_is_a_row_and_a_note(ws: Path, tmp_path: Path):
    broken = ws / "src" / "broken"
    broken.mkdir()
    (broken / ".git").write_text("gitdir: /nonexistent/modules/broken\n")
    proc = status(base_env(ws, tmp_path))
    assert proc.returncode == 0
    assert table(proc)[1]["broken"] == ["?", "(git error)"]
    assert "git failed in" in proc.stderr.decode()


def test_json_shape(ws: Path, tmp_path: Path):
    rows = json.loads(status(base_env(ws, tmp_path), "--json").stdout)
    by_path = {r["path"]: r for r in rows}
    assert [r["path"] for r in rows] == [
        "alpha",
        "alpha/nested",
        "beta",
        "delta",
        "gamma",
        "loose",
        "loose/inner",
        "sub",
    ]
    assert set(rows[0]) == {
        "path",
        "git",
        "branch",
        "detached",
        "sha",
        "dirty",
        "error",
        "packages",
    }
    assert by_path["beta"]["dirty"] is True and by_path["alpha"]["dirty"] is False
    assert by_path["gamma"]["branch"] is None and by_path["gamma"]["detached"] is True
    assert by_path["delta"]["sha"] is None and by_path["delta"]["branch"] == "wip"
    assert by_path["loose"]["git"] is False and by_path["loose"]["sha"] is None


def test_a_roscore_on_this_machine_is_no_robot(ws: Path, tmp_path: Path):
    proc = status(base_env(ws, tmp_path, ROS_MASTER_URI="http://localhost:11311"))
    assert table(proc)[0] == ["repository", "branch", "sha"] and proc.stderr == b""


def test_a_robot_named_explicitly_must_be_valid(ws: Path, tmp_path: Path):
    proc = fetchsync(
        "workspace-status", "--robot", "localhost", env=base_env(ws, tmp_path), check=False
    )
    assert proc.returncode == 2 and b"this machine" in proc.stderr


# --------------------------------------------------------------------------- the local robot
@pytest.mark.slow
def test_robot_column_with_the_local_robot(ws: Path, tmp_path: Path):
    robot_home = tmp_path / "robot-home"
    env = base_env(
        ws,
        tmp_path,
        FETCHSYNC_ROBOT="local",
        FETCHSYNC_LOCAL_ROBOT_HOME=str(robot_home),
        FETCHSYNC_REMOTE_WORKSPACE="~/robot_ws",
    )
    assert set(robot_column(status(env)).values()) == {"not pushed yet"}
    assert not (robot_home / "robot_ws").exists()  # looked at, not created
    fetchsync("push", env=env)
    assert set(robot_column(status(env)).values()) == {"in sync"}
    assert table(status(env, "--no-robot"))[0] == ["repository", "branch", "sha"]

    src = ws / "src"
    (src / "alpha/a.txt").write_text("edited\n")
    (src / "alpha/b.txt").write_text("edited too\n")
    robot_tree = tree_of(robot_home / "robot_ws" / "src")
    column = robot_column(status(env))
    assert column.pop("alpha") == "2 paths differ"
    assert set(column.values()) == {"in sync"}
    (src / "alpha/nested/more.txt").write_text("more\n")  # counted for the nested repository
    (src / "loose/notes.txt").unlink()  # and for the untracked directory
    column = robot_column(status(env))
    assert (column["alpha"], column["alpha/nested"], column["loose"]) == (
        "2 paths differ",
        "1 path differs",
        "1 path differs",
    )
    assert tree_of(robot_home / "robot_ws" / "src") == robot_tree  # status wrote nothing there

    rows = {r["path"]: r for r in json.loads(status(env, "--json", "--exclude", "sub").stdout)}
    assert (rows["alpha"]["robot"], rows["alpha"]["differing"]) == ("differs", 2)
    assert (rows["beta"]["robot"], rows["beta"]["differing"]) == ("in sync", 0)
    assert (rows["sub"]["robot"], rows["sub"]["differing"]) == ("excluded", None)


def test_a_push_from_elsewhere_is_compared_by_a_full_listing(ws: Path, tmp_path: Path):
    env = base_env(
        ws,
        tmp_path,
        FETCHSYNC_ROBOT="local",
        FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "robot-home"),
        FETCHSYNC_REMOTE_WORKSPACE="~/robot_ws",
    )
    fetchsync("push", env=env)
    (ws / "src/beta/README.md").write_text("edited after the push\n")
    env["XDG_STATE_HOME"] = str(tmp_path / "another-laptop")  # no state for this robot
    column = robot_column(status(env))
    assert column.pop("beta") == "1 path differs"
    assert set(column.values()) == {"in sync"}


# --------------------------------------------------------------------------- the sshd robot
@pytest.fixture
def ssh_env(ssh_home, remote_dir, ws, tmp_path) -> dict[str, str]:
    return base_env(
        ws,
        tmp_path,
        HOME=str(ssh_home.home),
        FETCHSYNC_ROBOT="robot",
        FETCHSYNC_REMOTE_WORKSPACE=str(remote_dir),
    )


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
@pytest.mark.ssh
def test_robot_column_over_ssh(ssh_env, ssh_home, ws):
    assert set(robot_column(status(ssh_env)).values()) == {"not pushed yet"}
    fetchsync("push", env=ssh_env)
    assert set(robot_column(status(ssh_env)).values()) == {"in sync"}
    (ws / "src/gamma/README.md").write_text("edited\n")
    (ws / "src/gamma/new.txt").write_text("new\n")
    rows = {r["path"]: r for r in json.loads(status(ssh_env, "--json").stdout)}
    assert (rows["gamma"]["robot"], rows["gamma"]["differing"]) == ("differs", 2)
    assert {r["robot"] for p, r in rows.items() if p != "gamma"} == {"in sync"}


@pytest.mark.ssh
def test_an_unreachable_robot_is_a_column_not_a_failure(ssh_env, ssh_home):
    with open(ssh_home.config, "a") as fh:
        fh.write(f"\nHost deadrobot\n    HostName 127.0.0.1\n    Port {_closed_port()}\n")
    proc = status(ssh_env, "--robot", "deadrobot")
    assert proc.returncode == 0
    assert set(robot_column(proc).values()) == {"unreachable"}
    err = without_where(proc.stderr.decode())
    assert len(err) == 1 and err[0].startswith("fetchsync: robot deadrobot unreachable:")
    rows = json.loads(status(ssh_env, "--robot", "deadrobot", "--json").stdout)
    assert {(r["robot"], r["differing"]) for r in rows} == {("unreachable", None)}


@pytest.mark.ssh
def test_a_robot_that_does_not_answer_is_unreachable_after_the_timeout(
    proxied_home, fault_proxy, remote_dir, ws, tmp_path
):
    env = base_env(
        ws,
        tmp_path,
        HOME=str(proxied_home.home),
        FETCHSYNC_ROBOT="robot",
        FETCHSYNC_REMOTE_WORKSPACE=str(remote_dir),
    )
    fault_proxy.blackhole()
    # the same call without the robot, just before: what starting the CLI and reading the
    # workspace take on this machine now (seconds when parallel tests load it), which is
    # not the robot's timeout
    t0 = time.monotonic()
    status(env, "--no-robot")
    start_up = time.monotonic() - t0
    t0 = time.monotonic()
    proc = status(env, "--timeout", "1")
    assert time.monotonic() - t0 - start_up < 8
    assert set(robot_column(proc).values()) == {"unreachable"}
    assert b"no answer within 1 s" in proc.stderr


def test_a_workspace_without_src_is_a_usage_error(tmp_path: Path):
    env = base_env(tmp_path / "nowhere", tmp_path)
    proc = fetchsync("workspace-status", env=env, check=False)
    assert proc.returncode == 2 and b"is not a directory" in proc.stderr
