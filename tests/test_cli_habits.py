"""The CLI's habits: where each answer goes, ``fetchsync config``, the workspace around
the current directory, ``run`` without a local workspace, one robot at a time, help.

Parsing through click's CliRunner; where a push goes and ``run`` without a workspace
end to end, the real CLI against the real sshd (the robot)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner
from helpers import clean_env, fetchsync, make_workspace, ssh_env, without_where

from fetchsync.cli import cli
from fetchsync.config import (
    Target,
    current_directory,
    login_name,
    resolve_workspace,
    workspace_around,
    workspace_with_source,
)
from fetchsync.errors import ConfigError

ARROW = "\u2192"
HOME = "/home/alice"


def invoke(args: list[str], env: dict[str, str], cwd: Path | None = None):
    """The CLI in this process with exactly ``env`` (CliRunner adds, so unset the rest)."""
    unset = {k: None for k in os.environ if k not in env}
    old = os.getcwd()
    if cwd is not None:
        os.chdir(cwd)
    try:
        return CliRunner().invoke(cli, args, env={**unset, **env, "PWD": str(cwd or old)})
    finally:
        os.chdir(old)


# -- the workspace around the current directory ---------------------------------


def catkin_ws(root: Path, *marks: str) -> Path:
    (root / "src" / "my_pkg" / "src").mkdir(parents=True)
    (root / "src" / "my_pkg" / "package.xml").write_text("<package/>\n")
    for mark in marks:
        (root / mark).mkdir(parents=True, exist_ok=True)
    return root


@pytest.mark.parametrize("mark", ["devel", "install", "build", ".catkin_tools", "log"])
def test_a_workspace_around_the_current_directory_is_found(tmp_path: Path, mark: str) -> None:
    ws = catkin_ws(tmp_path / "ws", mark)
    if mark == "log":  # colcon's log/ is a mark by its COLCON_IGNORE
        (ws / "log" / "COLCON_IGNORE").write_text("")
    deep = ws / "src" / "my_pkg" / "src"
    assert workspace_around(deep) == ws
    assert workspace_around(ws) == ws


def test_catkin_workspace_file_and_toplevel_link_are_marks(tmp_path: Path) -> None:
    ws = catkin_ws(tmp_path / "a")
    (ws / ".catkin_workspace").write_text("")
    assert workspace_around(ws / "src") == ws
    other = catkin_ws(tmp_path / "b")
    # catkin_init_workspace's link, dangling on a laptop without ROS
    (other / "src" / "CMakeLists.txt").symlink_to("/opt/ros/none/toplevel.cmake")
    assert workspace_around(other / "src" / "my_pkg") == other


def test_no_mark_or_a_package_is_no_workspace(tmp_path: Path) -> None:
    bare = catkin_ws(tmp_path / "bare")  # src/ alone: any project has one
    assert workspace_around(bare / "src") is None
    # a package with src/ and build/ of its own is not the workspace
    pkg = catkin_ws(tmp_path / "ws", "devel") / "src" / "my_pkg"
    (pkg / "build").mkdir()
    assert workspace_around(pkg / "src") == tmp_path / "ws"


def test_order_variables_then_current_directory_then_ros_distro(tmp_path: Path) -> None:
    ws = catkin_ws(tmp_path / "ws", "devel")
    here = str(ws / "src")
    e = {"HOME": HOME, "ROS_DISTRO": "noetic"}
    assert workspace_with_source(None, environ=e, cwd=here) == (
        ws,
        "the current directory, inside that workspace",
    )
    assert resolve_workspace(None, environ={**e, "FETCH_WORKSPACE": "/x"}, cwd=here) == Path("/x")
    assert resolve_workspace("/opt", environ=e, cwd=here) == Path("/opt")
    assert resolve_workspace(None, environ=e, cwd=str(tmp_path)) == Path(HOME, "noetic")
    with pytest.raises(ConfigError, match="cd into a workspace"):
        resolve_workspace(None, environ={"HOME": HOME}, cwd=str(tmp_path))


def test_the_current_directory_keeps_a_symlinked_path(tmp_path: Path, monkeypatch) -> None:
    real = catkin_ws(tmp_path / "real", "devel")
    link = tmp_path / "link"
    link.symlink_to(real)
    monkeypatch.chdir(link)
    assert current_directory({"PWD": str(link)}) == str(link)
    assert current_directory({"PWD": str(tmp_path)}) == os.getcwd()  # a stale PWD is not used


def test_push_inside_a_workspace_pushes_it(tmp_path: Path) -> None:
    ws = make_workspace(tmp_path / "ws")
    (ws / "devel").mkdir()
    robot = tmp_path / "robot-home"
    env = clean_env(
        FETCHSYNC_LOCAL_ROBOT_HOME=str(robot),
        XDG_STATE_HOME=str(tmp_path / "state"),
        HOME=str(tmp_path),
        ROS_DISTRO="noetic",
    )
    result = invoke(
        ["push", "--robot", "local", "--remote-workspace", "~/robot_ws"],
        env,
        cwd=ws / "src" / "my_pkg",
    )
    assert result.exit_code == 0, result.output
    assert f"push ~/ws/src {ARROW} local:~/robot_ws/src" in result.output
    assert (robot / "robot_ws" / "src" / "my_pkg" / "package.xml").exists()


# -- fetchsync config -------------------------------------------------------------


def test_config_names_each_setting_and_its_source(tmp_path: Path) -> None:
    ws = catkin_ws(tmp_path / "ws", "devel")
    env = clean_env(
        HOME=str(tmp_path), FETCH_ROBOT="freight0", ROS_DISTRO="noetic", FETCHSYNC_PERSIST="30"
    )
    result = invoke(["config", "--user", "fetch", "--json"], env, cwd=ws / "src")
    assert result.exit_code == 0, result.output
    rows = {r["name"]: r for r in json.loads(result.output)}
    assert (rows["robot"]["value"], rows["robot"]["source"]) == ("freight0", "FETCH_ROBOT")
    assert (rows["user"]["value"], rows["user"]["source"]) == ("fetch", "--user")
    assert rows["workspace"]["value"] == "~/ws"
    assert rows["workspace"]["source"] == "the current directory, inside that workspace"
    assert rows["remote workspace"]["value"] == "~/ws"
    assert rows["persist"]["value"] == "30 s" and rows["persist"]["source"] == "FETCHSYNC_PERSIST"
    assert rows["build tool"]["value"].startswith("auto")
    assert rows["a push goes"]["value"] == f"~/ws/src {ARROW} fetch@freight0:~/ws/src"
    order = rows["workspace"]["order"]
    assert (
        order.index("FETCH_WORKSPACE")
        < order.index("current directory")
        < order.index("ROS_DISTRO")
    )


def test_config_text_shows_the_order_and_what_is_missing(tmp_path: Path) -> None:
    env = clean_env(HOME=str(tmp_path), ROS_MASTER_URI="http://fetch7.local:11311")
    result = invoke(["config", "--remote-workspace", "~/noetic"], env, cwd=tmp_path)
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert any(
        line.split()[:2] == ["robot", "fetch7.local"] and "ROS_MASTER_URI" in line for line in lines
    )
    assert any(line.startswith("workspace ") and "not set" in line for line in lines)
    assert any(
        line.startswith("remote workspace") and "from --remote-workspace" in line for line in lines
    )
    assert "Each is the first of these that is set:" in result.output


def test_the_ssh_configs_user_is_named_and_noted(tmp_path: Path) -> None:
    home = tmp_path / "home"
    (home / ".ssh").mkdir(parents=True)
    config = home / ".ssh" / "config"
    config.write_text("Host freight0\n    User fetch\n")
    target = Target(
        robot="freight0",
        host="freight0",
        user=None,
        workspace=Path("/w"),
        remote_workspace="~/w",
        is_local=False,
    )
    env = {"HOME": str(home), "USER": "alice", "XDG_CACHE_HOME": str(tmp_path / "cache")}
    code = (
        "import sys; from pathlib import Path; from fetchsync.config import Target, login_name; "
        "t = Target(robot='freight0', host='freight0', user=None, workspace=Path('/w'), "
        "remote_workspace='~/w', is_local=False); "
        "print(login_name(t), 'paramiko' in sys.modules)"
    )

    def run() -> list[str]:
        return subprocess.run(
            [sys.executable, "-c", code],
            env={**os.environ, **env},
            capture_output=True,
            text=True,
            check=True,
        ).stdout.split()

    assert run() == ["fetch", "True"]  # read by paramiko once
    assert run() == ["fetch", "False"]  # then from the note
    config.write_text("Host freight0\n    User robot\n")  # an edited config is read again
    assert run() == ["robot", "True"]
    assert login_name(target, environ={**env, "FETCHSYNC_X": ""}) == "robot"
    assert (
        login_name(
            Target(
                robot="local",
                host="local",
                user=None,
                workspace=Path("/w"),
                remote_workspace="~/w",
                is_local=True,
            ),
            environ=env,
        )
        is None
    )


# -- one robot at a time, but for push and run (tests/test_fleet.py) ------------------


@pytest.mark.parametrize("args", [["--robot", "a", "--robot", "b"], ["--robot", "a,b"]])
def test_several_robots_are_refused_in_one_line(args: list[str], tmp_path: Path) -> None:
    env = clean_env(HOME=str(tmp_path), FETCHSYNC_WORKSPACE=str(make_workspace(tmp_path / "ws")))
    for verb in (["pull", "--yes", *args], ["config", *args]):
        result = invoke(verb, env)
        assert result.exit_code == 2, (verb, result.output)
        [line] = result.output.splitlines()
        assert line == (
            "fetchsync: error: several robots (a, b, from --robot): only push, run, watch, "
            "create-account, workspace-status and snapshot take several; give one robot"
        )


def test_several_robots_in_a_variable_are_refused(tmp_path: Path) -> None:
    env = clean_env(
        HOME=str(tmp_path),
        FETCH_ROBOT="a,b",
        FETCHSYNC_WORKSPACE=str(make_workspace(tmp_path / "ws")),
    )
    result = invoke(["pull", "--yes"], env)
    assert result.exit_code == 2
    assert "several robots (a, b, from FETCH_ROBOT): only push, run, watch," in result.output


# -- push: a missing src/ ---------------------------------------------------------


def test_a_missing_src_is_a_configuration_error_without_force(tmp_path: Path) -> None:
    env = clean_env(HOME=str(tmp_path), FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "robot"))
    result = invoke(
        [
            "push",
            "--robot",
            "local",
            "--workspace",
            str(tmp_path / "nowhere"),
            "--remote-workspace",
            "~/ws",
        ],
        env,
    )
    assert result.exit_code == 2, result.output
    [line] = result.output.splitlines()
    assert "nowhere/src does not exist" in line and "--force" not in line


# -- where the answer goes, end to end ----------------------------------------------


@pytest.mark.ssh
def test_push_and_pull_say_where_they_go(ssh_home, remote_dir, tmp_path: Path) -> None:
    env = ssh_env(ssh_home.home, remote_dir, tmp_path)
    # the user comes from the ssh config (not $USER): named all the same
    env.update(USER="not-the-ssh-configs-user")
    user, ws = ssh_home.sshd.user, tmp_path / "ws"
    proc = fetchsync("push", "--json", env=env)
    json.loads(proc.stdout)  # stdout is the report only
    err = proc.stderr.decode().splitlines()
    assert err == [f"push {ws}/src {ARROW} {user}@robot:{remote_dir}/src"]
    proc = fetchsync("pull", "--yes", env=env)
    assert (
        proc.stderr.decode().splitlines()[0]
        == f"pull {user}@robot:{remote_dir}/src {ARROW} {ws}/src"
    )
    # -q, before or after the verb, silences it
    for args in (["-q", "push"], ["push", "-q"]):
        assert fetchsync(*args, env=env).stderr == b""


@pytest.mark.ssh
def test_a_failed_push_said_where_it_went_first(ssh_home, remote_dir, tmp_path: Path) -> None:
    env = ssh_env(ssh_home.home, remote_dir, tmp_path, FETCHSYNC_USER="nosuchuser")
    proc = fetchsync("push", env=env, check=False)
    err = proc.stderr.decode().splitlines()
    assert proc.returncode == 3
    assert err[0] == f"push {tmp_path}/ws/src {ARROW} nosuchuser@robot:{remote_dir}/src"
    assert len(without_where(proc.stderr.decode())) == 1


# -- run without a local workspace ----------------------------------------------------


@pytest.mark.ssh
def test_run_needs_no_local_workspace(ssh_home, remote_dir, tmp_path: Path) -> None:
    env = clean_env(
        HOME=str(ssh_home.home), FETCHSYNC_ROBOT="robot", XDG_STATE_HOME=str(tmp_path / "state")
    )
    (remote_dir / "devel").mkdir()
    (remote_dir / "devel" / "setup.bash").write_text("export FROM_THE_WORKSPACE=yes\n")
    nowhere = tmp_path / "not-a-workspace"
    nowhere.mkdir()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "fetchsync",
            "run",
            "--remote-workspace",
            str(remote_dir),
            "--",
            "printenv",
            "FROM_THE_WORKSPACE",
        ],
        cwd=nowhere,
        env=env,
        capture_output=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
    )
    assert (proc.returncode, proc.stdout, proc.stderr) == (0, b"yes\n", b""), proc.stderr
    # and with no workspace at all: only the distribution's setup
    proc = subprocess.run(
        [sys.executable, "-m", "fetchsync", "run", "--", "echo", "ok"],
        cwd=nowhere,
        env=env,
        capture_output=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
    )
    assert (proc.returncode, proc.stdout) == (0, b"ok\n"), proc.stderr


# -- help ---------------------------------------------------------------------------


def test_the_command_list_has_whole_summaries_and_no_alias() -> None:
    result = CliRunner().invoke(cli, ["--help"], terminal_width=80)
    assert result.exit_code == 0
    listing = result.output.split("Commands:")[1]
    assert "..." not in listing
    names = [
        line.split()[0]
        for line in listing.splitlines()
        if line.startswith("  ") and not line.startswith("   ")
    ]
    assert "debug-snapshot" not in names and "snapshot" in names and "config" in names
    assert "debug-snapshot" in " ".join(listing.split())  # named on snapshot's line
    # each summary is a whole sentence
    summaries = " ".join(listing.split()).split("  ")
    assert all(s.rstrip().endswith((".", ")")) for s in summaries if s.strip())
    assert CliRunner().invoke(cli, ["debug-snapshot", "--help"]).exit_code == 0


def test_status_shows_only_what_it_uses() -> None:
    out = CliRunner().invoke(cli, ["status", "--help"]).output
    assert "--accept-host-key" not in out and "--robot" in out


def test_watch_spells_build_arguments_as_push_does(tmp_path: Path) -> None:
    watch_help = CliRunner().invoke(cli, ["watch", "--help"]).output
    push_help = CliRunner().invoke(cli, ["push", "--help"]).output
    assert "--build [ARGS]" in watch_help and "--build [ARGS]" in push_help
    assert "--build-args" not in watch_help
    ws = make_workspace(tmp_path / "ws")
    env = clean_env(
        HOME=str(tmp_path), XDG_CONFIG_HOME=str(tmp_path / "config"), FETCHSYNC_WORKSPACE=str(ws)
    )
    base = ["watch", "--robot", "local", "--remote-workspace", "~/r", "--install-service"]

    def exec_start(*args: str) -> str:
        result = invoke([*base, *args], env)
        assert result.exit_code == 0, result.output
        [unit] = (tmp_path / "config" / "systemd" / "user").glob("*.service")
        return next(line for line in unit.read_text().splitlines() if line.startswith("ExecStart="))

    assert exec_start("--build=-j4 -DX=1").endswith('"--build=-j4 -DX=1"')
    assert exec_start("--build", "-j2 -DY=2").endswith('"--build=-j2 -DY=2"')
    # the old spelling still works, also right after a bare --build
    assert exec_start("--build", "--build-args=-j3 -DZ=3").endswith('"--build=-j3 -DZ=3"')
    assert exec_start("--build").endswith(" --build")
    result = invoke([*base, "--build=-j1", "--build=-j2"], env)
    assert result.exit_code == 2 and "give --build ARGS once" in result.output


def test_verbose_works_after_the_verb(tmp_path: Path) -> None:
    ws = make_workspace(tmp_path / "ws")
    env = clean_env(
        HOME=str(tmp_path),
        FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "r"),
        XDG_STATE_HOME=str(tmp_path / "state"),
        FETCHSYNC_WORKSPACE=str(ws),
        FETCHSYNC_ROBOT="local",
        FETCHSYNC_REMOTE_WORKSPACE="~/r",
    )

    def log_of(*args: str) -> list[str]:
        proc = fetchsync(*args, env=env)
        return [line for line in proc.stderr.decode().splitlines() if line.startswith("fetchsync.")]

    assert log_of("push") == []
    assert log_of("-vv", "push") != []
    assert log_of("push", "-vv") != []
    assert log_of("push", "-v", "-v") != []
    # after run's COMMAND, -v is the command's
    proc = subprocess.run(
        [sys.executable, "-m", "fetchsync", "run", "-v", "--", "echo", "-v"],
        env=env,
        capture_output=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    assert (proc.returncode, proc.stdout) == (0, b"-v\n"), proc.stderr


# -- hints ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "hint"),
    [
        (
            ["push", "--build", "--pkg", "my_pkg"],
            'to pass it to the build tool, quote it with its value: --build "--pkg my_pkg"',
        ),
        (
            ["pull", "--yes", "--build", "--pkg", "a", "b", "--json"],
            'quote it with its value: --build "--pkg a b"',
        ),
        (["watch", "--build", "--pkg", "a$b"], "quote it with its value: --build '--pkg a$b'"),
        (["push", "--build", "--cmake-args"], "write --build=--cmake-args"),
    ],
)
def test_an_unquoted_build_argument_gets_a_quoting_hint(args: list[str], hint: str) -> None:
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 2
    error = result.output.split("Error: ")[1]
    assert (
        error.startswith(f"No such option '{args[args.index('--build') + 1]}'; ") and hint in error
    )


def test_an_unknown_option_elsewhere_gets_no_build_hint() -> None:
    result = CliRunner().invoke(cli, ["push", "--pkg", "x"])
    assert result.exit_code == 2 and "No such option '--pkg'" in result.output
    assert "--build" not in result.output.split("Error:")[1]


@pytest.mark.parametrize(
    ("robot", "hint"),
    [
        ("nosuchrobot", "on its network it may be nosuchrobot.local (zeroconf)"),
        ("nosuchrobot.local", "avahi-daemon (zeroconf)"),
    ],
)
def test_an_unresolvable_robot_names_zeroconf_and_the_ssh_config(
    tmp_path: Path, robot: str, hint: str
) -> None:
    (tmp_path / ".ssh").mkdir()
    env = clean_env(HOME=str(tmp_path), FETCHSYNC_REMOTE_WORKSPACE="~/ws")
    proc = subprocess.run(
        [sys.executable, "-m", "fetchsync", "run", "--robot", robot, "true"],
        env=env,
        capture_output=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    [line] = proc.stderr.decode().splitlines()
    assert proc.returncode == 255 and line.startswith("fetchsync: error: cannot resolve host name")
    assert hint in line and f"'Host {robot}' entry with its HostName in ~/.ssh/config" in line


@pytest.mark.ssh
def test_a_refused_login_suggests_create_account_and_ssh_copy_id(
    ssh_home, remote_dir, tmp_path: Path
) -> None:
    env = ssh_env(ssh_home.home, remote_dir, tmp_path, FETCHSYNC_USER="nosuchuser")
    proc = fetchsync("push", env=env, check=False)
    [line] = without_where(proc.stderr.decode())
    assert proc.returncode == 3 and "permission denied for nosuchuser@" in line
    assert "ssh-copy-id nosuchuser@robot" in line
    assert "fetchsync create-account --robot robot --user nosuchuser" in line


@pytest.mark.ssh
def test_a_snapshot_says_whom_it_asks(ssh_home, remote_dir, tmp_path: Path) -> None:
    env = ssh_env(ssh_home.home, remote_dir, tmp_path)
    env.update(USER="not-the-ssh-configs-user")
    proc = fetchsync("snapshot", "--only", "date", "--no-sudo", "--output", str(tmp_path), env=env)
    assert proc.stderr.decode().splitlines()[0] == (
        f"snapshot {ssh_home.sshd.user}@robot:{remote_dir} {ARROW} {tmp_path}"
    )


def test_home_is_never_the_workspace_around(tmp_path: Path) -> None:
    home = catkin_ws(tmp_path / "home", "build")  # ~/src and ~/build: any developer's home
    (home / "src" / "my_pkg" / "package.xml").unlink()
    e = {"HOME": str(home), "ROS_DISTRO": "noetic"}
    assert resolve_workspace(None, environ=e, cwd=str(home / "src" / "my_pkg")) == home / "noetic"
    ws = catkin_ws(home / "noetic", "devel")
    assert resolve_workspace(None, environ=e, cwd=str(ws / "src")) == ws


def test_the_where_line_prints_no_escape_sequence(tmp_path: Path) -> None:
    ws = make_workspace(tmp_path / "ws\x1b]0;owned\x07")
    env = clean_env(
        HOME=str(tmp_path),
        FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "robot"),
        XDG_STATE_HOME=str(tmp_path / "state"),
    )
    result = invoke(
        ["push", "--robot", "local", "--workspace", str(ws), "--remote-workspace", "~/r"], env
    )
    assert result.exit_code == 0, result.output
    [line] = [x for x in result.output.splitlines() if x.startswith("push ")]
    assert "\x1b" not in line and "\x07" not in line and "\\x1b" in line
