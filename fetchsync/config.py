"""Who and where: the robot, the login user and the workspace on both ends.

The contract of fetch_tools is kept, with fetchsync's own variables first::

    robot             --robot > FETCHSYNC_ROBOT > FETCH_ROBOT > host of ROS_MASTER_URI
    user              --user > FETCHSYNC_USER > FETCH_USER > ssh config User > $USER
    workspace         --workspace > FETCHSYNC_WORKSPACE > FETCH_WORKSPACE > ~/$ROS_DISTRO
    remote workspace  --remote-workspace > FETCHSYNC_REMOTE_WORKSPACE
                      > FETCH_REMOTE_WORKSPACE > the workspace with $HOME written as ``~``

An empty variable counts as unset. Each step is its own function so it can be
resolved and tested alone; :func:`resolve_target` puts them together. Nothing
here touches the network: host names (``fetch7.local`` included) are left to
the system resolver and the SSH configuration. paramiko is imported only when
an ssh config has to be read for the user.
"""

from __future__ import annotations

import getpass
import ipaddress
import os
import posixpath
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Union
from urllib.parse import urlsplit

from fetchsync.errors import ConfigError
from fetchsync.transport import LOCAL_ROBOT

if TYPE_CHECKING:
    import paramiko

SSHConfigSource = Union[str, "os.PathLike[str]", "paramiko.SSHConfig"]

ROBOT_VARS = ("FETCHSYNC_ROBOT", "FETCH_ROBOT")
USER_VARS = ("FETCHSYNC_USER", "FETCH_USER")
WORKSPACE_VARS = ("FETCHSYNC_WORKSPACE", "FETCH_WORKSPACE")
REMOTE_WORKSPACE_VARS = ("FETCHSYNC_REMOTE_WORKSPACE", "FETCH_REMOTE_WORKSPACE")

_LOCALHOST_NAMES = frozenset(
    {"localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback"}
)


@dataclass(frozen=True)
class Target:
    """One robot and the workspace mirrored to it.

    ``host`` is what the transport connects to (an ssh config alias, a name or
    an address); it is ``"local"`` for the built-in local robot, whose ``user``
    is None. ``remote_workspace`` keeps ``~`` unexpanded: the robot expands it.
    """

    robot: str
    host: str
    user: str | None
    workspace: Path
    remote_workspace: str
    is_local: bool


def resolve_target(
    *,
    robot: str | None = None,
    user: str | None = None,
    workspace: str | os.PathLike[str] | None = None,
    remote_workspace: str | None = None,
    environ: Mapping[str, str] = os.environ,
    ssh_config: SSHConfigSource | None = None,
    defer_ssh_user: bool = False,
) -> Target:
    """Resolve every part of the target from options, environment and ssh config.

    With ``defer_ssh_user``, a user given by no option or variable is left
    ``None``: the SSH transport then applies the rest of the same order (the
    ssh config's User, then ours) when it connects. That saves reading the ssh
    config, and importing paramiko, in calls that never open an SSH connection
    themselves (a connection master already holds one).
    """
    robot_name = resolve_robot(robot, environ=environ)
    is_local = robot_name == LOCAL_ROBOT
    if is_local or defer_ssh_user and _first(user, "--user", environ, USER_VARS)[1] is None:
        login = None
    else:
        login = resolve_user(user, host=robot_name, environ=environ, ssh_config=ssh_config)
    local_ws = resolve_workspace(workspace, environ=environ)
    remote_ws = resolve_remote_workspace(remote_workspace, workspace=local_ws, environ=environ)
    return Target(
        robot=robot_name,
        host=robot_name,
        user=login,
        workspace=local_ws,
        remote_workspace=remote_ws,
        is_local=is_local,
    )


def resolve_robot(robot: str | None = None, *, environ: Mapping[str, str] = os.environ) -> str:
    """The robot's name: the option, the variables, else the host of ROS_MASTER_URI."""
    source, value = _first(robot, "--robot", environ, ROBOT_VARS)
    if value is None:
        uri = _get(environ, "ROS_MASTER_URI")
        if uri is None:
            raise ConfigError(
                "no robot given: pass --robot NAME or set FETCHSYNC_ROBOT=NAME "
                "(ROS_MASTER_URI=http://NAME:11311 works too; --robot local is the built-in local robot)"
            )
        source, value = f"ROS_MASTER_URI={uri}", ros_master_host(uri)
    if value == LOCAL_ROBOT:
        return value
    _check_robot_name(value, source)
    if is_loopback(value):
        raise ConfigError(
            f"the robot resolves to this machine ({value}, from {source}): "
            "pass --robot NAME or set FETCHSYNC_ROBOT=NAME (--robot local is the built-in local robot)"
        )
    return value


def ros_master_host(uri: str) -> str:
    """The host part of a ROS master URI (``http://fetch7.local:11311`` -> ``fetch7.local``)."""
    text = uri.strip()
    if "://" not in text:
        text = "http://" + text
    try:
        host = urlsplit(text).hostname
    except ValueError as exc:
        raise ConfigError(f"cannot read a host from ROS_MASTER_URI={uri!r}: {exc}") from exc
    if not host:
        raise ConfigError(
            f"cannot read a host from ROS_MASTER_URI={uri!r}: "
            "expected http://NAME:11311, or pass --robot NAME"
        )
    return host


def is_loopback(host: str) -> bool:
    """True for names and addresses of this machine: localhost, 127.0.0.0/8, ::1."""
    name = host.strip().strip("[]").rstrip(".").lower()
    if name in _LOCALHOST_NAMES or name.endswith(".localhost"):
        return True
    try:
        addr = ipaddress.ip_address(name)
    except ValueError:
        return False
    return addr.is_loopback or addr.is_unspecified


def resolve_user(
    user: str | None = None,
    *,
    host: str,
    environ: Mapping[str, str] = os.environ,
    ssh_config: SSHConfigSource | None = None,
) -> str:
    """The login user on ``host``: option, variables, the ssh config's User, else ours."""
    _source, value = _first(user, "--user", environ, USER_VARS)
    if value is None:
        value = ssh_config_user(host, ssh_config=ssh_config, environ=environ)
    if value is None:
        value = _get(environ, "USER") or getpass.getuser()
    if value.startswith("-") or any(c.isspace() or c in "@/\0" for c in value):
        raise ConfigError(f"invalid user name {value!r}: pass --user NAME")
    return value


def ssh_config_user(
    host: str,
    *,
    ssh_config: SSHConfigSource | None = None,
    environ: Mapping[str, str] = os.environ,
) -> str | None:
    """The ``User`` the ssh config sets for ``host``, or None.

    ``ssh_config`` is a path or a parsed ``paramiko.SSHConfig``; by default
    ``~/.ssh/config`` when it exists.
    """
    import paramiko  # only now: an explicit --user never pays for its import

    if ssh_config is None or isinstance(ssh_config, (str, os.PathLike)):
        path = Path(ssh_config) if ssh_config is not None else _home(environ) / ".ssh" / "config"
        if ssh_config is None and not path.is_file():
            return None
        try:
            config = paramiko.SSHConfig.from_path(str(path))
        except OSError as exc:
            raise ConfigError(f"cannot read the ssh config {path}: {exc.strerror}") from exc
        except paramiko.SSHException as exc:
            raise ConfigError(f"cannot parse the ssh config {path}: {exc}") from exc
    else:
        config = ssh_config
    found = config.lookup(host).get("user")
    return str(found) if found else None


def resolve_workspace(
    workspace: str | os.PathLike[str] | None = None,
    *,
    environ: Mapping[str, str] = os.environ,
) -> Path:
    """The local workspace as an absolute path (it need not exist yet)."""
    given = os.fspath(workspace) if workspace is not None else None
    _source, value = _first(given, "--workspace", environ, WORKSPACE_VARS)
    if value is None:
        distro = _get(environ, "ROS_DISTRO")
        if distro is None:
            raise ConfigError(
                "no workspace given: pass --workspace DIR or set FETCHSYNC_WORKSPACE=DIR "
                "(the default ~/$ROS_DISTRO needs ROS_DISTRO, set by sourcing ROS)"
            )
        value = f"~/{distro}"
    if "\0" in value:
        raise ConfigError(f"invalid workspace path {value!r}")
    return Path(os.path.abspath(_expand_home(value, environ)))


def resolve_remote_workspace(
    remote_workspace: str | None = None,
    *,
    workspace: Path,
    environ: Mapping[str, str] = os.environ,
) -> str:
    """The workspace on the robot, ``~`` unexpanded, checked by :func:`check_remote_workspace`.

    By default the local workspace with the home directory written as ``~``
    (``/home/alice/noetic`` -> ``~/noetic``); a path outside home stays absolute.
    """
    source, value = _first(remote_workspace, "--remote-workspace", environ, REMOTE_WORKSPACE_VARS)
    if value is None:
        source, value = f"the workspace {workspace}", home_relative(workspace, environ=environ)
    return check_remote_workspace(value, source=source)


def home_relative(path: Path, *, environ: Mapping[str, str] = os.environ) -> str:
    """``path`` with the home directory written as ``~`` when it is under it."""
    home = Path(os.path.abspath(_home(environ)))
    try:
        rel = Path(os.path.abspath(path)).relative_to(home)
    except ValueError:
        return Path(os.path.abspath(path)).as_posix()
    return "~" if rel == Path(".") else f"~/{rel.as_posix()}"


def check_remote_workspace(path: str, *, source: str = "--remote-workspace") -> str:
    """Return ``path`` normalised (no ``.``, duplicate or trailing slashes) or raise ConfigError.

    Refused: empty, ``/``, ``~``, a NUL, a ``..`` component, ``~user`` and
    relative paths (whose meaning would depend on the robot's login directory).
    """
    where = f"remote workspace {path!r} (from {source})"
    if "\0" in path:
        raise ConfigError(f"invalid {where}: it contains a NUL byte")
    text = path.strip()
    if not text:
        raise ConfigError(f"invalid {where}: it is empty; pass --remote-workspace ~/DIR")
    if text == "~" or text.startswith("~/"):
        prefix, rest = "~", text[1:]
    elif text.startswith("/"):
        prefix, rest = "", text
    elif text.startswith("~"):
        raise ConfigError(
            f"invalid {where}: ~user is not supported; write ~/DIR or an absolute path"
        )
    else:
        raise ConfigError(f"invalid {where}: it is relative; write ~/{text} or an absolute path")
    parts = [p for p in rest.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise ConfigError(f"invalid {where}: it contains a '..' component")
    if not parts:
        raise ConfigError(
            f"invalid {where}: that is the whole {'home directory' if prefix else 'file system'}; "
            "pass --remote-workspace ~/DIR"
        )
    return posixpath.join(prefix or "/", *parts)


def _check_robot_name(name: str, source: str) -> None:
    # The name reaches ssh configs and, in benchmarks and error hints, command lines.
    if name.startswith("-") or "/" in name or any(c.isspace() or ord(c) < 32 for c in name):
        raise ConfigError(f"invalid robot name {name!r} (from {source}): expected a host name")
    if "@" in name:
        raise ConfigError(
            f"invalid robot name {name!r} (from {source}): give the user with --user or FETCHSYNC_USER"
        )


def _first(
    given: str | None, option: str, environ: Mapping[str, str], names: tuple[str, ...]
) -> tuple[str, str | None]:
    """The first non-empty of the option and the variables, with where it came from."""
    if given is not None and given.strip():
        return option, given.strip()
    for name in names:
        value = _get(environ, name)
        if value is not None:
            return name, value
    return "", None


def _get(environ: Mapping[str, str], name: str) -> str | None:
    value = environ.get(name, "").strip()
    return value or None


def _home(environ: Mapping[str, str]) -> Path:
    home = _get(environ, "HOME")
    return Path(home) if home else Path(os.path.expanduser("~"))


def _expand_home(path: str, environ: Mapping[str, str]) -> str:
    if path == "~" or path.startswith("~/"):
        return str(_home(environ)) + path[1:]
    return os.path.expanduser(path)


__all__ = [
    "Target",
    "check_remote_workspace",
    "home_relative",
    "is_loopback",
    "resolve_remote_workspace",
    "resolve_robot",
    "resolve_target",
    "resolve_user",
    "resolve_workspace",
    "ros_master_host",
    "ssh_config_user",
]
