"""Who and where: the robot, the login user and the workspace on both ends.

The contract of fetch_tools is kept, with fetchsync's own variables first::

    robot             --robot > FETCHSYNC_ROBOT > FETCH_ROBOT > host of ROS_MASTER_URI
    user              --user > FETCHSYNC_USER > FETCH_USER > ssh config User > $USER
    workspace         --workspace > FETCHSYNC_WORKSPACE > FETCH_WORKSPACE
                      > the workspace around the current directory > ~/$ROS_DISTRO
    remote workspace  --remote-workspace > FETCHSYNC_REMOTE_WORKSPACE
                      > FETCH_REMOTE_WORKSPACE > the workspace with $HOME written as ``~``

An empty variable counts as unset. A workspace around the current directory
is the nearest directory at or above it that has ``src/`` and a mark of a
workspace (:data:`WORKSPACE_MARKERS`), as catkin and colcon leave them. Each step is its own function so it can be
resolved and tested alone; :func:`resolve_target` puts them together. Nothing
here touches the network: host names (``fetch7.local`` included) are left to
the system resolver and the SSH configuration. paramiko is imported only when
an ssh config has to be read for the user.
"""

from __future__ import annotations

import ipaddress
import os
import posixpath
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Union
from urllib.parse import urlsplit

from fetchsync.errors import ConfigError

if TYPE_CHECKING:
    import paramiko


def import_paramiko() -> Any:
    """paramiko, imported without invoke, which ``paramiko.config`` imports only for an
    ssh config's ``Match exec`` lines: invoke brings asyncio, yaml and unittest.mock,
    ~90 of paramiko's ~330 ms of CPU here, paid by every connection that is not made
    through a connection master (a first push, the master itself). A config that has
    such a line gets invoke at its parsing (:func:`allow_match_exec`). One thread at a
    time: a fleet's robots connect at once."""
    import sys

    with _PARAMIKO_LOCK:
        if "paramiko" not in sys.modules and "invoke" not in sys.modules:
            sys.modules["invoke"] = None  # type: ignore[assignment]  # import of invoke fails
            try:
                _load_paramiko()
            finally:
                if sys.modules.get("invoke", 0) is None:
                    del sys.modules["invoke"]
    import paramiko

    return paramiko


_PARAMIKO_LOCK = threading.Lock()


def _load_paramiko() -> None:
    """Import paramiko; its ``__init__``'s ``from importlib import metadata`` (for its
    ``__version__``, the only use) gets :func:`_metadata_stand_in`: its own code's
    imports go through an ``__import__`` of its own (its module's ``__builtins__``), so
    no other thread ever sees the stand-in."""
    import builtins
    import importlib.util
    import sys
    import types

    stand_in = _metadata_stand_in()
    spec = importlib.util.find_spec("paramiko") if stand_in is not None else None
    if spec is None or spec.loader is None:
        import paramiko  # noqa: F401  # as it comes

        return
    real = builtins.__import__

    def importer(
        name: str, globals: Any = None, locals: Any = None, fromlist: Any = (), level: int = 0
    ) -> Any:
        if name == "importlib" and level == 0 and tuple(fromlist or ()) == ("metadata",):
            return types.SimpleNamespace(metadata=stand_in)
        return real(name, globals, locals, fromlist, level)

    module = importlib.util.module_from_spec(spec)
    module.__dict__["__builtins__"] = dict(builtins.__dict__, __import__=importer)
    sys.modules["paramiko"] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop("paramiko", None)
        raise
    finally:
        module.__dict__["__builtins__"] = builtins.__dict__


def _metadata_stand_in() -> Any:
    """For paramiko's ``__version__ = importlib.metadata.version("paramiko")``, the one
    use of importlib.metadata at its import: the version from the name of paramiko's
    own ``paramiko-VERSION.dist-info`` beside it, as importlib.metadata finds it for an
    installed paramiko. importlib.metadata itself (with email, zipfile, csv) and its
    scan of every sys.path entry cost ~30 ms of CPU of each first push here (issue 24).
    None (paramiko is imported as it comes) unless exactly one such directory is there."""
    import importlib.util
    import types

    try:
        spec = importlib.util.find_spec("paramiko")
        if spec is None or spec.origin is None:
            return None
        site = os.path.dirname(os.path.dirname(spec.origin))
        found = [
            n[len("paramiko-") : -len(".dist-info")]
            for n in os.listdir(site)
            if n.startswith("paramiko-") and n.endswith(".dist-info")
        ]
    except (ImportError, OSError, ValueError):
        return None
    if len(found) != 1:
        return None
    version = found[0]

    def paramiko_version(name: str) -> str:
        if name != "paramiko":
            raise LookupError(name)  # only paramiko's import asks this stand-in
        return version

    stand_in = types.ModuleType("importlib.metadata")
    stand_in.version = paramiko_version  # type: ignore[attr-defined]
    return stand_in


def allow_match_exec(config: paramiko.SSHConfig) -> paramiko.SSHConfig:
    """``config``, able to run its ``Match exec`` lines: invoke imported if it has any
    (see :func:`import_paramiko`); paramiko looks for it only when it runs one."""
    import paramiko.config

    if paramiko.config.invoke is None and any(
        match.get("type") == "exec"
        for entry in getattr(config, "_config", ())
        for match in entry.get("matches", ())
    ):
        try:
            import invoke
        except ImportError as exc:  # paramiko raises it when it runs the line, as without us
            paramiko.config.invoke_import_error = exc
        else:
            paramiko.config.invoke = invoke
    return config


LOCAL_ROBOT = "local"
"""The built-in robot: this machine, as the user who runs fetchsync (no SSH server)."""

SSHConfigSource = Union[str, "os.PathLike[str]", "paramiko.SSHConfig"]

ROBOT_VARS = ("FETCHSYNC_ROBOT", "FETCH_ROBOT")
USER_VARS = ("FETCHSYNC_USER", "FETCH_USER")
WORKSPACE_VARS = ("FETCHSYNC_WORKSPACE", "FETCH_WORKSPACE")
REMOTE_WORKSPACE_VARS = ("FETCHSYNC_REMOTE_WORKSPACE", "FETCH_REMOTE_WORKSPACE")

_LOCALHOST_NAMES = frozenset(
    {"localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback"}
)


class Target:
    """One robot and the workspace mirrored to it.

    ``host`` is what the transport connects to (an ssh config alias, a name or
    an address); it is ``"local"`` for the built-in local robot, whose ``user``
    is None. ``remote_workspace`` keeps ``~`` unexpanded: the robot expands it.

    Immutable, compared and hashed by its fields, as a frozen dataclass, written out:
    ``dataclasses`` imports ``inspect`` (ast, dis, tokenize: ~6 ms of CPU), which the
    console entry's fast path of a push needs nothing else of.
    """

    __match_args__ = ("robot", "host", "user", "workspace", "remote_workspace", "is_local")
    robot: str
    host: str
    user: str | None
    workspace: Path
    remote_workspace: str
    is_local: bool

    def __init__(
        self,
        robot: str,
        host: str,
        user: str | None,
        workspace: Path,
        remote_workspace: str,
        is_local: bool,
    ) -> None:
        values = (robot, host, user, workspace, remote_workspace, is_local)
        for name, value in zip(self.__match_args__, values):
            object.__setattr__(self, name, value)

    def _values(self) -> tuple[Any, ...]:
        return tuple(getattr(self, name) for name in self.__match_args__)

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return self._values() == other._values()

    def __hash__(self) -> int:
        return hash(self._values())

    def __repr__(self) -> str:
        fields = ", ".join(f"{n}={v!r}" for n, v in zip(self.__match_args__, self._values()))
        return f"Target({fields})"

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"cannot assign to field {name!r}: a Target is immutable")

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"cannot delete field {name!r}: a Target is immutable")


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
    if remote_workspace is None:  # robots.toml's [robots.NAME] counts as its option
        from fetchsync.robots import robot_settings

        remote_workspace = robot_settings(robot_name, environ=environ).get("remote_workspace")
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
    return robot_with_source(robot, environ=environ)[0]


def robot_with_source(
    robot: str | None = None, *, environ: Mapping[str, str] = os.environ
) -> tuple[str, str]:
    """:func:`resolve_robot`, and where the name came from (``--robot``, a variable's name)."""
    source, value = _first(robot, "--robot", environ, ROBOT_VARS)
    if value is None:
        uri = _get(environ, "ROS_MASTER_URI")
        if uri is None:
            raise ConfigError(
                "no robot given: pass --robot NAME or set FETCHSYNC_ROBOT=NAME "
                "(ROS_MASTER_URI=http://NAME:11311 works too; --robot local is the built-in local robot)"
            )
        source, value = f"ROS_MASTER_URI={uri}", ros_master_host(uri)
    if "," in value or value.startswith("@"):  # a list or a group: one robot, or refused
        from fetchsync.robots import one_robot

        value = one_robot(value, source, environ=environ)
    if value == LOCAL_ROBOT:
        return value, source
    _check_robot_name(value, source)
    if is_loopback(value):
        raise ConfigError(
            f"the robot resolves to this machine ({value}, from {source}): "
            "pass --robot NAME or set FETCHSYNC_ROBOT=NAME (--robot local is the built-in local robot)"
        )
    return value, source


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
    return user_with_source(user, host=host, environ=environ, ssh_config=ssh_config)[0]


def user_with_source(
    user: str | None = None,
    *,
    host: str,
    environ: Mapping[str, str] = os.environ,
    ssh_config: SSHConfigSource | None = None,
) -> tuple[str, str]:
    """:func:`resolve_user`, and where the name came from."""
    source, value = _first(user, "--user", environ, USER_VARS)
    if value is None:
        value = ssh_config_user(host, ssh_config=ssh_config, environ=environ)
        source = f"the ssh config's User for {host}"
    if value is None:
        value, source = _get(environ, "USER") or _user(), "$USER"
    if value.startswith("-") or any(c.isspace() or c in "@/\0" for c in value):
        raise ConfigError(f"invalid user name {value!r}: pass --user NAME")
    return value, source


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
    paramiko = import_paramiko()  # only now: an explicit --user never pays for its import

    if ssh_config is None or isinstance(ssh_config, (str, os.PathLike)):
        path = Path(ssh_config) if ssh_config is not None else _home(environ) / ".ssh" / "config"
        if ssh_config is None and not path.is_file():
            return None
        try:
            config = allow_match_exec(paramiko.SSHConfig.from_path(str(path)))
        except OSError as exc:
            raise ConfigError(f"cannot read the ssh config {path}: {exc.strerror}") from exc
        except paramiko.SSHException as exc:
            raise ConfigError(f"cannot parse the ssh config {path}: {exc}") from exc
    else:
        config = ssh_config
    found = config.lookup(host).get("user")
    return str(found) if found else None


_NOT_NOTED = (b"match", b"canonicalizehostname")


def login_name(target: Target, *, environ: Mapping[str, str] = os.environ) -> str | None:
    """The user the connection to ``target`` logs in as (None for the local robot).

    A user left to the transport (see ``defer_ssh_user``) is looked up as it
    would: the ssh config's User, else ours. The config's answer is noted in the
    cache by the config's content, host, home and login name, so a later call
    reads the note instead of importing paramiko (~40 ms, a quarter of a no-op
    push through a connection master). A config with ``Match`` (its answer
    depends on more than the file) or hostname canonicalisation is never noted.
    """
    if target.is_local:
        return None
    if target.user is not None:
        return target.user
    path = _home(environ) / ".ssh" / "config"
    try:
        content = path.read_bytes()
    except FileNotFoundError:
        content = None
    except OSError:
        content = b""  # unreadable: ssh_config_user says why
    found: str | None
    if content is None:
        found = None
    elif any(
        line.strip().lower().startswith(word)
        for line in content.splitlines()
        for word in _NOT_NOTED
    ):
        found = ssh_config_user(target.host, ssh_config=path, environ=environ)
    else:
        found = _noted_user(target.host, path, content, environ)
    return found or _get(environ, "USER") or _user()


def _noted_user(host: str, path: Path, content: bytes, environ: Mapping[str, str]) -> str | None:
    import hashlib
    import json
    import stat

    from fetchsync.protocol.loader import cache_dir

    key = json.dumps([host, hashlib.sha256(content).hexdigest(), str(_home(environ)), _user()])
    note = os.path.join(cache_dir(), "user-" + hashlib.sha256(key.encode()).hexdigest()[:32])
    try:
        fd = os.open(note, os.O_RDONLY | os.O_NOFOLLOW)
        try:
            st = os.fstat(fd)
            if st.st_uid == os.getuid() and not st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
                noted = json.loads(os.read(fd, 4096))
                if isinstance(noted, dict) and isinstance(noted.get("user"), (str, type(None))):
                    return noted["user"]  # type: ignore[no-any-return]
        finally:
            os.close(fd)
    except (OSError, ValueError):
        pass
    found = ssh_config_user(host, ssh_config=path, environ=environ)
    try:  # only a cache: a failure passes
        os.makedirs(os.path.dirname(note), exist_ok=True)
        tmp = f"{note}.{os.getpid()}.tmp"
        with os.fdopen(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "w") as fh:
            fh.write(json.dumps({"user": found}))
        os.replace(tmp, note)
    except OSError:
        pass
    return found


def resolve_workspace(
    workspace: str | os.PathLike[str] | None = None,
    *,
    environ: Mapping[str, str] = os.environ,
    cwd: str | None = None,
) -> Path:
    """The local workspace as an absolute path (it need not exist yet).

    ``cwd`` is where a workspace around is looked for (default: the current
    directory as the shell shows it, ``$PWD``).
    """
    return workspace_with_source(workspace, environ=environ, cwd=cwd)[0]


def workspace_with_source(
    workspace: str | os.PathLike[str] | None = None,
    *,
    environ: Mapping[str, str] = os.environ,
    cwd: str | None = None,
) -> tuple[Path, str]:
    """:func:`resolve_workspace`, and where it came from."""
    given = os.fspath(workspace) if workspace is not None else None
    source, value = _first(given, "--workspace", environ, WORKSPACE_VARS)
    if value is None:
        here = cwd if cwd is not None else current_directory(environ)
        around = workspace_around(here, home=_home(environ)) if here is not None else None
        if around is not None:
            return around, "the current directory, inside that workspace"
        distro = _get(environ, "ROS_DISTRO")
        if distro is None:
            raise ConfigError(
                "no workspace given: pass --workspace DIR, set FETCHSYNC_WORKSPACE=DIR or cd into "
                "a workspace (the default ~/$ROS_DISTRO needs ROS_DISTRO, set by sourcing ROS)"
            )
        source, value = f"~/$ROS_DISTRO (ROS_DISTRO={distro})", f"~/{distro}"
    if "\0" in value:
        raise ConfigError(f"invalid workspace path {value!r}")
    return Path(os.path.abspath(_expand_home(value, environ))), source


WORKSPACE_MARKERS = (
    ".catkin_workspace",
    ".catkin_tools",
    "devel",
    "install",
    "build",
    "log/COLCON_IGNORE",
    "src/CMakeLists.txt",
)
"""What, beside ``src/``, makes a directory a workspace: catkin_make's and catkin_tools'
marks (``src/CMakeLists.txt`` is catkin_init_workspace's link), the result spaces of
catkin (``devel/``) and colcon (``build/``, ``install/``), and colcon's log directory."""


def workspace_around(
    directory: str | os.PathLike[str], *, home: str | os.PathLike[str] | None = None
) -> Path | None:
    """The nearest directory at or above ``directory`` that is a workspace, or None.

    A directory holding a ``package.xml`` is a package (which may have ``src/``
    and ``build/`` of its own), never a workspace; nor are ``/`` and ``home``
    (a home with ``~/src`` and ``~/build`` is common, and could never be pushed:
    the robot's workspace would be its whole home).

    One that belongs to another user (it or its ``src/``; root's are trusted) is
    refused with a ConfigError: anyone can make ``/tmp/x/src`` and ``/tmp/x/devel``,
    and a push typed in ``/tmp/x/mine`` would send their tree to the robot (a pull
    write the robot's into theirs), as git's safe.directory refuses such a repository.
    A workspace given (``--workspace``) is the user's choice.
    """
    path = Path(os.path.abspath(directory))
    skip = {Path(os.path.abspath(home))} if home is not None else set()
    for candidate in (path, *path.parents):
        if candidate.parent == candidate:
            break
        if candidate in skip:
            continue
        if (
            (candidate / "src").is_dir()
            and not os.path.lexists(candidate / "package.xml")
            and any(os.path.lexists(candidate / mark) for mark in WORKSPACE_MARKERS)
        ):
            _owned(candidate)
            return candidate
    return None


def _owned(workspace: Path) -> None:
    """ConfigError unless ``workspace`` and its ``src/`` are ours (or root's)."""
    for each in (workspace, workspace / "src"):
        try:
            uid = os.stat(each).st_uid
        except OSError:
            continue  # gone meanwhile: the push says what it finds
        if uid not in (os.getuid(), 0):
            raise ConfigError(
                f"{workspace} looks like a workspace around the current directory, but "
                f"{each} belongs to another user (uid {uid}); refusing to push or pull it",
                hint=f"if it is the one you mean, pass --workspace {workspace}",
            )


def current_directory(environ: Mapping[str, str] = os.environ) -> str | None:
    """The current directory as the shell shows it: ``$PWD`` when it is this directory
    (symbolic links kept, so a home reached through one still reads ``~/...``), else the
    real path; None when it is gone."""
    pwd = environ.get("PWD", "")
    try:
        if os.path.isabs(pwd) and os.path.samefile(pwd, "."):
            return pwd
        return os.getcwd()
    except OSError:
        return None


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
    return remote_workspace_with_source(remote_workspace, workspace=workspace, environ=environ)[0]


def remote_workspace_with_source(
    remote_workspace: str | None = None,
    *,
    workspace: Path | None,
    environ: Mapping[str, str] = os.environ,
) -> tuple[str, str]:
    """:func:`resolve_remote_workspace`, and where it came from; with no local ``workspace``
    only an option or a variable gives one (else ConfigError)."""
    source, value = _first(remote_workspace, "--remote-workspace", environ, REMOTE_WORKSPACE_VARS)
    if value is None:
        if workspace is None:
            raise ConfigError("no remote workspace given: pass --remote-workspace DIR")
        source, value = f"the workspace {workspace}", home_relative(workspace, environ=environ)
    return check_remote_workspace(value, source=source), (
        source
        if not source.startswith("the workspace ")
        else "the local workspace, with ~ for home"
    )


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


def first_given(
    given: str | None, names: tuple[str, ...], *, environ: Mapping[str, str] = os.environ
) -> bool:
    """Whether the option or one of the variables ``names`` gives a value."""
    return _first(given, "", environ, names)[1] is not None


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
    "WORKSPACE_MARKERS",
    "Target",
    "check_remote_workspace",
    "current_directory",
    "first_given",
    "home_relative",
    "is_loopback",
    "login_name",
    "remote_workspace_with_source",
    "resolve_remote_workspace",
    "resolve_robot",
    "resolve_target",
    "resolve_user",
    "resolve_workspace",
    "robot_with_source",
    "ros_master_host",
    "ssh_config_user",
    "user_with_source",
    "workspace_around",
    "workspace_with_source",
]


def _user() -> str:
    """The login name, when $USER does not say it (getpass imports ~1 ms: only then)."""
    import getpass

    return getpass.getuser()
