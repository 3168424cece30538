"""Resolution of robot, user and workspaces: every precedence step and every error."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from fetchsync.config import (
    Target,
    check_remote_workspace,
    home_relative,
    is_loopback,
    resolve_remote_workspace,
    resolve_robot,
    resolve_target,
    resolve_user,
    resolve_workspace,
    ros_master_host,
    ssh_config_user,
)
from fetchsync.errors import ConfigError

HOME = "/home/alice"


def env(**values: str) -> dict[str, str]:
    """An environment with a HOME and USER of its own, so the real ones never leak in."""
    base = {"HOME": HOME, "USER": "alice"}
    base.update(values)
    return base


@pytest.fixture
def no_ssh_config(tmp_path: Path) -> Path:
    path = tmp_path / "empty_ssh_config"
    path.write_text("")
    return path


# -- robot -------------------------------------------------------------------


def test_robot_option_wins_over_everything() -> None:
    e = env(FETCHSYNC_ROBOT="a", FETCH_ROBOT="b", ROS_MASTER_URI="http://c:11311")
    assert resolve_robot("opt", environ=e) == "opt"


def test_robot_fetchsync_variable_wins_over_fetch_variable() -> None:
    e = env(FETCHSYNC_ROBOT="a", FETCH_ROBOT="b", ROS_MASTER_URI="http://c:11311")
    assert resolve_robot(environ=e) == "a"


def test_robot_fetch_variable_wins_over_ros_master_uri() -> None:
    e = env(FETCH_ROBOT="b", ROS_MASTER_URI="http://c:11311")
    assert resolve_robot(environ=e) == "b"


def test_robot_from_ros_master_uri() -> None:
    assert resolve_robot(environ=env(ROS_MASTER_URI="http://fetch7.local:11311")) == "fetch7.local"


def test_empty_variables_count_as_unset() -> None:
    e = env(FETCHSYNC_ROBOT="", FETCH_ROBOT="  ", ROS_MASTER_URI="http://c:11311/")
    assert resolve_robot(environ=e) == "c"


def test_mdns_names_are_accepted() -> None:
    assert resolve_robot("fetch7.local", environ=env()) == "fetch7.local"


def test_no_robot_is_a_config_error_saying_how_to_set_it() -> None:
    with pytest.raises(ConfigError) as info:
        resolve_robot(environ=env())
    message = str(info.value)
    assert "--robot" in message and "FETCHSYNC_ROBOT" in message
    assert "\n" not in message


@pytest.mark.parametrize(
    "uri",
    [
        "http://localhost:11311",
        "http://127.0.0.1:11311",
        "http://[::1]:11311",
        "http://127.1.2.3:11311/",
        "localhost:11311",
    ],
)
def test_ros_master_uri_on_this_machine_is_refused(uri: str) -> None:
    with pytest.raises(ConfigError, match="ROS_MASTER_URI") as info:
        resolve_robot(environ=env(ROS_MASTER_URI=uri))
    assert "--robot" in str(info.value)


@pytest.mark.parametrize(
    "name", ["localhost", "LOCALHOST", "127.0.0.1", "::1", "[::1]", "localhost."]
)
def test_loopback_robot_option_is_refused(name: str) -> None:
    with pytest.raises(ConfigError, match="this machine"):
        resolve_robot(name, environ=env())


def test_loopback_from_variable_names_the_variable() -> None:
    with pytest.raises(ConfigError, match="FETCH_ROBOT"):
        resolve_robot(environ=env(FETCH_ROBOT="127.0.0.1"))


def test_local_is_the_builtin_local_robot() -> None:
    assert resolve_robot("local", environ=env()) == "local"
    assert resolve_robot(environ=env(FETCHSYNC_ROBOT="local")) == "local"


@pytest.mark.parametrize("name", ["-oProxyCommand=x", "a b", "user@robot", "a/b"])
def test_malformed_robot_names_are_refused(name: str) -> None:
    with pytest.raises(ConfigError, match="invalid robot name"):
        resolve_robot(name, environ=env())


@pytest.mark.parametrize("uri", ["http://:11311", "http://"])
def test_ros_master_uri_without_host_is_a_config_error(uri: str) -> None:
    with pytest.raises(ConfigError, match="ROS_MASTER_URI"):
        resolve_robot(environ=env(ROS_MASTER_URI=uri))


def test_ros_master_host_forms() -> None:
    assert ros_master_host("http://fetch7.local:11311") == "fetch7.local"
    assert ros_master_host("http://Fetch7:11311/") == "fetch7"
    assert ros_master_host("fetch7:11311") == "fetch7"
    assert ros_master_host("http://[fe80::1]:11311") == "fe80::1"


def test_is_loopback() -> None:
    assert is_loopback("127.0.0.53")
    assert is_loopback("foo.localhost")
    assert not is_loopback("fetch7.local")
    assert not is_loopback("10.0.0.7")


# -- user --------------------------------------------------------------------


@pytest.fixture
def ssh_config_with_user(tmp_path: Path) -> Path:
    path = tmp_path / "ssh_config"
    path.write_text("Host fetch7\n    User fetch\nHost *\n    Port 22\n")
    return path


def test_user_option_wins(ssh_config_with_user: Path) -> None:
    e = env(FETCHSYNC_USER="a", FETCH_USER="b")
    assert resolve_user("opt", host="fetch7", environ=e, ssh_config=ssh_config_with_user) == "opt"


def test_user_fetchsync_variable_wins_over_fetch_variable(ssh_config_with_user: Path) -> None:
    e = env(FETCHSYNC_USER="a", FETCH_USER="b")
    assert resolve_user(host="fetch7", environ=e, ssh_config=ssh_config_with_user) == "a"


def test_user_fetch_variable_wins_over_ssh_config(ssh_config_with_user: Path) -> None:
    e = env(FETCH_USER="b")
    assert resolve_user(host="fetch7", environ=e, ssh_config=ssh_config_with_user) == "b"


def test_user_from_ssh_config(ssh_config_with_user: Path) -> None:
    assert resolve_user(host="fetch7", environ=env(), ssh_config=ssh_config_with_user) == "fetch"


def test_user_from_environment_when_ssh_config_has_none(ssh_config_with_user: Path) -> None:
    assert resolve_user(host="other", environ=env(), ssh_config=ssh_config_with_user) == "alice"


def test_user_falls_back_to_the_login_name(no_ssh_config: Path) -> None:
    import getpass

    e = {"HOME": HOME}
    assert resolve_user(host="fetch7", environ=e, ssh_config=no_ssh_config) == getpass.getuser()


def test_default_ssh_config_is_read_from_home(tmp_path: Path) -> None:
    (tmp_path / ".ssh").mkdir()
    (tmp_path / ".ssh" / "config").write_text("Host fetch7\n  User fromhome\n")
    e = {"HOME": str(tmp_path), "USER": "alice"}
    assert resolve_user(host="fetch7", environ=e) == "fromhome"
    assert ssh_config_user("fetch7", environ={"HOME": str(tmp_path / "none")}) is None


def test_parsed_ssh_config_is_accepted() -> None:
    import paramiko

    config = paramiko.SSHConfig.from_text("Host fetch*\n  User robo\n")
    assert resolve_user(host="fetch3", environ=env(), ssh_config=config) == "robo"


def test_unreadable_ssh_config_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="ssh config"):
        resolve_user(host="fetch7", environ=env(), ssh_config=tmp_path / "missing")


def test_unparsable_ssh_config_is_a_config_error(tmp_path: Path) -> None:
    path = tmp_path / "bad"
    path.write_text("Host x\n  =novalue\n")
    with pytest.raises(ConfigError, match="ssh config"):
        resolve_user(host="fetch7", environ=env(), ssh_config=path)


@pytest.mark.parametrize("name", ["-oX", "a b", "a@b"])
def test_malformed_user_is_refused(name: str, no_ssh_config: Path) -> None:
    with pytest.raises(ConfigError, match="invalid user"):
        resolve_user(name, host="fetch7", environ=env(), ssh_config=no_ssh_config)


def test_config_module_does_not_import_paramiko() -> None:
    import subprocess

    code = "import sys, fetchsync.config; print('paramiko' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# -- workspace ---------------------------------------------------------------


def test_workspace_option_wins() -> None:
    e = env(FETCHSYNC_WORKSPACE="/a", FETCH_WORKSPACE="/b", ROS_DISTRO="noetic")
    assert resolve_workspace("/opt/ws", environ=e) == Path("/opt/ws")


def test_workspace_fetchsync_variable_wins_over_fetch_variable() -> None:
    e = env(FETCHSYNC_WORKSPACE="/a", FETCH_WORKSPACE="/b", ROS_DISTRO="noetic")
    assert resolve_workspace(environ=e) == Path("/a")


def test_workspace_fetch_variable_wins_over_ros_distro() -> None:
    assert resolve_workspace(environ=env(FETCH_WORKSPACE="/b", ROS_DISTRO="noetic")) == Path("/b")


def test_workspace_defaults_to_home_ros_distro() -> None:
    assert resolve_workspace(environ=env(ROS_DISTRO="noetic")) == Path("/home/alice/noetic")


def test_workspace_without_ros_distro_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="ROS_DISTRO") as info:
        resolve_workspace(environ=env())
    assert "--workspace" in str(info.value)


def test_workspace_is_made_absolute_and_need_not_exist(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert resolve_workspace("ws/../ws2", environ=env()) == tmp_path / "ws2"
    assert resolve_workspace(Path("~/x"), environ=env()) == Path("/home/alice/x")


# -- remote workspace --------------------------------------------------------


WS = Path("/home/alice/noetic")


def test_remote_workspace_option_wins() -> None:
    e = env(FETCHSYNC_REMOTE_WORKSPACE="~/a", FETCH_REMOTE_WORKSPACE="~/b")
    assert resolve_remote_workspace("~/opt", workspace=WS, environ=e) == "~/opt"


def test_remote_workspace_fetchsync_variable_wins_over_fetch_variable() -> None:
    e = env(FETCHSYNC_REMOTE_WORKSPACE="~/a", FETCH_REMOTE_WORKSPACE="~/b")
    assert resolve_remote_workspace(workspace=WS, environ=e) == "~/a"


def test_remote_workspace_fetch_variable_wins_over_default() -> None:
    e = env(FETCH_REMOTE_WORKSPACE="/opt/robot_ws")
    assert resolve_remote_workspace(workspace=WS, environ=e) == "/opt/robot_ws"


def test_remote_workspace_defaults_to_workspace_under_tilde() -> None:
    assert resolve_remote_workspace(workspace=WS, environ=env()) == "~/noetic"
    deep = Path("/home/alice/ws/catkin")
    assert resolve_remote_workspace(workspace=deep, environ=env()) == "~/ws/catkin"


def test_remote_workspace_outside_home_stays_absolute() -> None:
    assert resolve_remote_workspace(workspace=Path("/opt/ws"), environ=env()) == "/opt/ws"
    # /home/alicex is not under /home/alice
    assert home_relative(Path("/home/alicex/ws"), environ=env()) == "/home/alicex/ws"


def test_workspace_that_is_home_gives_a_refused_remote_workspace() -> None:
    with pytest.raises(ConfigError, match="home directory"):
        resolve_remote_workspace(workspace=Path(HOME), environ=env())


@pytest.mark.parametrize(
    "bad, why",
    [
        ("", "empty"),
        ("  ", "empty"),
        ("/", "file system"),
        ("//", "file system"),
        ("/./", "file system"),
        ("~", "home directory"),
        ("~/", "home directory"),
        ("~/.", "home directory"),
        ("~/../bob", r"'\.\.'"),
        ("/opt/ws/..", r"'\.\.'"),
        ("~/ws/../../etc", r"'\.\.'"),
        ("~/ws\0x", "NUL"),
        ("~bob/ws", "~user"),
        ("noetic", "relative"),
    ],
)
def test_bad_remote_workspaces_are_refused(bad: str, why: str) -> None:
    with pytest.raises(ConfigError, match=why):
        check_remote_workspace(bad)


def test_bad_remote_workspace_from_variable_names_the_variable() -> None:
    with pytest.raises(ConfigError, match="FETCH_REMOTE_WORKSPACE"):
        resolve_remote_workspace(workspace=WS, environ=env(FETCH_REMOTE_WORKSPACE="/"))


def test_remote_workspace_is_normalised_but_tilde_kept() -> None:
    assert check_remote_workspace("~/noetic/") == "~/noetic"
    assert check_remote_workspace("~//a/./b") == "~/a/b"
    assert check_remote_workspace("/opt//ws/") == "/opt/ws"
    assert check_remote_workspace("~/..foo") == "~/..foo"


# -- the whole target --------------------------------------------------------


def test_resolve_target_for_a_robot(ssh_config_with_user: Path) -> None:
    e = env(ROS_MASTER_URI="http://fetch7:11311", ROS_DISTRO="noetic")
    target = resolve_target(environ=e, ssh_config=ssh_config_with_user)
    assert target == Target(
        robot="fetch7",
        host="fetch7",
        user="fetch",
        workspace=Path("/home/alice/noetic"),
        remote_workspace="~/noetic",
        is_local=False,
    )


def test_resolve_target_options_win(no_ssh_config: Path) -> None:
    e = env(
        FETCHSYNC_ROBOT="r",
        FETCHSYNC_USER="u",
        FETCHSYNC_WORKSPACE="/w",
        FETCHSYNC_REMOTE_WORKSPACE="~/rw",
    )
    target = resolve_target(
        robot="fetch1.local",
        user="bob",
        workspace="/opt/ws",
        remote_workspace="/srv/ws",
        environ=e,
        ssh_config=no_ssh_config,
    )
    assert (target.robot, target.host, target.user) == ("fetch1.local", "fetch1.local", "bob")
    assert (target.workspace, target.remote_workspace) == (Path("/opt/ws"), "/srv/ws")


def test_resolve_target_for_the_local_robot() -> None:
    target = resolve_target(robot="local", user="ignored", environ=env(ROS_DISTRO="noetic"))
    assert target.is_local and target.host == "local" and target.user is None
    assert target.remote_workspace == "~/noetic"


def test_target_is_frozen() -> None:
    target = resolve_target(robot="local", environ=env(ROS_DISTRO="noetic"))
    with pytest.raises(AttributeError):
        target.robot = "other"  # type: ignore[misc]


def test_resolve_target_errors_propagate() -> None:
    with pytest.raises(ConfigError, match="robot"):
        resolve_target(environ=env(ROS_DISTRO="noetic"))
    with pytest.raises(ConfigError, match="workspace"):
        resolve_target(robot="local", environ=env())


def test_deferred_ssh_user_is_left_to_the_transport(tmp_path):
    env = {
        "HOME": str(tmp_path),
        "FETCHSYNC_ROBOT": "fetch1",
        "FETCHSYNC_WORKSPACE": str(tmp_path / "ws"),
    }
    assert resolve_target(environ=env, defer_ssh_user=True).user is None
    assert resolve_target(environ=dict(env, FETCH_USER="bob"), defer_ssh_user=True).user == "bob"
    assert resolve_target(user="amy", environ=env, defer_ssh_user=True).user == "amy"
