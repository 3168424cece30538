"""Accounts on a robot: the laptop side of ``fetchsync create-account``.

An admin account on the robot (root directly, anyone else through ``sudo``)
runs :mod:`fetchsync.robot.account_robot` as root. That program's text, the request
and the passwords go over the SSH channel's stdin; the command line the robot
runs holds only a bootstrap that reads them (``BOOTSTRAP``). So no password
appears in a command line on either machine, in a remote command string or
in a log.

With sudo, stdin starts with the admin password, which ``sudo -S`` reads one
byte at a time up to the newline, leaving the rest to the bootstrap. Padding
lines follow: were sudo to reject the password after all, its remaining tries
read those and never the request. An admin whose sudo needs no password
(NOPASSWD) is asked none; should sudo not read one it was sent anyway, the
bootstrap skips everything before its ``BEGIN`` line.

The skeleton is looked up by :func:`find_skeleton`: ``--skeleton DIR``, then
``~/.fetchsync/robot_skeleton``, ``~/.fetch/robot_skeleton`` (fetch_tools'),
then the built-in one (``skeleton/`` of a checkout, or where the wheel put it:
``<prefix>/share/fetchsync/skeleton``).
"""

from __future__ import annotations

import base64
import binascii
import json
import logging
import os
import re
import shlex
import site
import sys
import sysconfig
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fetchsync.errors import (
    ConfigError,
    ConnectError,
    LinkLostError,
    ProtocolError,
    RemoteError,
    UsageError,
)
from fetchsync.link.transport import Channel, Transport

log = logging.getLogger(__name__)

GROUPS = ("adm", "audio", "cdrom", "sudo", "dip", "plugdev", "lpadmin", "sambashare")
"""fetch_tools' groups for a robot user; those the robot lacks are left out."""

DEFAULT_ADMIN = "fetch"
INIT_SCRIPT = "initialize.sh"
SKELETON_SEARCH = ("~/.fetchsync/robot_skeleton", "~/.fetch/robot_skeleton")
SKELETON_DATA_DIR = ("share", "fetchsync", "skeleton")
MAX_SKELETON_BYTES = 8 * 1024 * 1024
PUBLIC_KEYS = ("id_ed25519.pub", "id_ecdsa.pub", "id_rsa.pub")

BEGIN = b"FETCHSYNC-ACCOUNT-BEGIN\n"
_SUDO_PADDING = 3  # sudo's default passwd_tries
_PROGRAM = Path(__file__).resolve().parent.parent / "robot" / "account_robot.py"
_RESULT_PREFIX = b"FETCHSYNC-ACCOUNT-RESULT "
_USER_NAME = re.compile(r"[a-z_][a-z0-9_-]{0,31}\Z")
_KEY_TYPES = re.compile(r"(ssh-|ecdsa-|sk-)[A-Za-z0-9@.-]+\Z")

# Runs as `python3 -c BOOTSTRAP`: skip what precedes BEGIN (a password sudo
# did not ask for), then execute the program whose length comes next.
BOOTSTRAP = (
    "import sys\n"
    "b = sys.stdin.buffer\n"
    "while True:\n"
    "    line = b.readline()\n"
    "    if not line:\n"
    "        sys.exit('fetchsync: no account program on stdin')\n"
    f"    if line == {BEGIN!r}:\n"
    "        break\n"
    "del line\n"
    "n = int(b.readline())\n"
    "exec(compile(b.read(n), 'fetchsync-account', 'exec'))\n"
)


@dataclass(frozen=True)
class SkeletonFile:
    """One directory or file of a skeleton, relative to the new home."""

    path: str
    kind: str  # "dir" or "file"
    mode: int
    data: bytes = b""


@dataclass(frozen=True)
class Skeleton:
    """A home-directory skeleton: files to copy and the ``initialize.sh`` to run once."""

    source: Path
    files: tuple[SkeletonFile, ...]
    init: bytes | None


@dataclass(frozen=True)
class AccountRequest:
    """What the robot is asked to do. ``password`` None keeps an existing one."""

    user: str
    fullname: str
    groups: tuple[str, ...]
    key: str | None
    skeleton: Skeleton | None
    env: dict[str, str]
    password: str | None = field(default=None, repr=False)
    workspace: str | None = None
    """The account's workspace on the robot as push resolves it (``~`` kept), or None."""
    ros_snippet: str = "fetchsync"
    """``fetchsync`` records the workspace in ``~/.bashrc.d/30-workspace.sh`` (read by the
    built-in skeleton's 40-ros.sh); ``fetch_tools`` writes fetch_tools' ``40-ros-setup.sh``."""

    def to_json(self) -> bytes:
        sk = self.skeleton
        payload = {
            "user": self.user,
            "fullname": self.fullname,
            "groups": list(self.groups),
            "key": self.key,
            "password": self.password,
            "skeleton": [
                {
                    "path": f.path,
                    "type": f.kind,
                    "mode": f.mode,
                    "data": base64.b64encode(f.data).decode("ascii"),
                }
                for f in (sk.files if sk else ())
            ],
            "init": (
                base64.b64encode(sk.init).decode("ascii")
                if sk is not None and sk.init is not None
                else None
            ),
            "env": self.env,
            "workspace": self.workspace,
            "ros_snippet": self.ros_snippet,
        }
        return json.dumps(payload).encode("utf-8")


@dataclass
class AccountReport:
    """What the robot did, as it reported it."""

    user: str
    robot: str
    created: bool
    home: str
    password_set: bool
    groups_added: list[str]
    groups_absent: list[str]
    key: str  # "added", "present" or "none"
    skeleton_added: list[str]
    initialize: str  # "ran", "already", "failed" or "none"
    skeleton: str = ""
    error: str | None = None
    workspace: str = ""
    """The workspace the account's shells use, as recorded on the robot ("" when none)."""
    workspace_record: str = ""
    """written, updated, kept, yours (a file not ours, left alone), initialize.sh, unresolved."""
    workspace_was: str = ""
    workspace_file: str = ""

    @classmethod
    def from_robot(cls, data: dict[str, Any], *, robot: str) -> AccountReport:
        return cls(
            user=str(data.get("user", "")),
            robot=robot,
            created=bool(data.get("created")),
            home=str(data.get("home", "")),
            password_set=bool(data.get("password_set")),
            groups_added=[str(g) for g in data.get("groups_added", [])],
            groups_absent=[str(g) for g in data.get("groups_absent", [])],
            key=str(data.get("key", "none")),
            skeleton_added=[str(p) for p in data.get("skeleton_added", [])],
            initialize=str(data.get("initialize", "none")),
            error=data.get("error"),
            workspace=str(data.get("workspace") or ""),
            workspace_record=str(data.get("workspace_record") or ""),
            workspace_was=str(data.get("workspace_was") or ""),
            workspace_file=str(data.get("workspace_file") or ""),
        )

    def to_json(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class RobotAccount:
    """What the admin session found before changing anything."""

    admin_is_root: bool
    exists: bool
    uid: int | None
    home: str | None


def check_user_name(name: str) -> str:
    if not _USER_NAME.match(name):
        raise UsageError(
            f"invalid user name {name!r}: lower-case letters, digits, '_' and '-', "
            "starting with a letter or '_', at most 32"
        )
    return name


def check_fullname(fullname: str) -> str:
    if ":" in fullname or any(ord(c) < 32 for c in fullname):
        raise UsageError("the full name may not contain ':' or control characters")
    return fullname


def check_password(password: str, *, what: str) -> str:
    if not password:
        raise UsageError(f"the {what} is empty")
    if any(c in password for c in "\n\r\0"):
        raise UsageError(f"the {what} may not contain a line break or a NUL")
    return password


# --- the skeleton ---------------------------------------------------------------------------


def builtin_skeleton() -> Path | None:
    """The built-in skeleton: ``skeleton/`` of a checkout, else where the wheel installed it."""
    for candidate in builtin_skeleton_candidates():
        if (candidate / INIT_SCRIPT).is_file():
            return candidate
    return None


def builtin_skeleton_candidates() -> list[Path]:
    candidates = []
    checkout = Path(__file__).resolve().parents[2]
    if (checkout / "pyproject.toml").is_file():
        candidates.append(checkout / "skeleton")
    prefixes = [sysconfig.get_path("data"), sys.prefix, sys.base_prefix]
    user_base = getattr(site, "USER_BASE", None)
    if user_base:
        prefixes.append(user_base)
    for prefix in prefixes:
        path = Path(prefix).joinpath(*SKELETON_DATA_DIR)
        if path not in candidates:
            candidates.append(path)
    return candidates


def find_skeleton(option: str | os.PathLike[str] | None = None) -> Path:
    """The skeleton directory: the option, then the users' own, then the built-in one."""
    if option is not None:
        path = Path(os.path.expanduser(os.fspath(option)))
        if not path.is_dir():
            raise ConfigError(f"the skeleton {path} is not a directory")
        return path
    for place in SKELETON_SEARCH:
        path = Path(os.path.expanduser(place))
        if path.is_dir():
            return path
    builtin = builtin_skeleton()
    if builtin is None:
        raise ConfigError(
            "the built-in skeleton is missing from this installation", hint="pass --skeleton DIR"
        )
    return builtin


def is_legacy_skeleton(path: Path) -> bool:
    """True for fetch_tools' skeleton: ``~/.fetch/robot_skeleton``, or a copy of the one in
    fetch_tools' sources (``resources/robot_skeleton``). Those get fetch_tools' own ROS
    set-up, ``~/.bashrc.d/40-ros-setup.sh``, which their ``.bashrc`` reads."""
    resolved = Path(os.path.abspath(path))
    legacy = Path(os.path.abspath(os.path.expanduser(SKELETON_SEARCH[1])))
    return resolved == legacy or (
        resolved.name == "robot_skeleton" and resolved.parent.name == "resources"
    )


def load_skeleton(root: Path) -> Skeleton:
    """Read a skeleton directory: ``initialize.sh`` at its top apart, the rest as files.

    Links to files are read as files; links to directories and special files
    are left out. Refuses a skeleton larger than ``MAX_SKELETON_BYTES``.
    """
    files: list[SkeletonFile] = []
    init: bytes | None = None
    total = 0
    try:
        for dirpath, dirnames, filenames in os.walk(root):
            dirnames.sort()
            rel_dir = Path(dirpath).relative_to(root)
            for name in list(dirnames):
                full = Path(dirpath) / name
                if full.is_symlink():
                    log.warning("skeleton: leaving out %s, a link to a directory", full)
                    dirnames.remove(name)
                    continue
                files.append(
                    SkeletonFile((rel_dir / name).as_posix(), "dir", full.stat().st_mode & 0o7777)
                )
            for name in sorted(filenames):
                full = Path(dirpath) / name
                if not full.is_file():
                    log.warning("skeleton: leaving out %s, not a regular file", full)
                    continue
                data = full.read_bytes()
                total += len(data)
                if total > MAX_SKELETON_BYTES:
                    raise ConfigError(
                        f"the skeleton {root} is larger than "
                        f"{MAX_SKELETON_BYTES // (1024 * 1024)} MiB"
                    )
                rel = (rel_dir / name).as_posix()
                if rel == INIT_SCRIPT:
                    init = data
                else:
                    files.append(SkeletonFile(rel, "file", full.stat().st_mode & 0o7777, data))
    except OSError as exc:
        raise ConfigError(f"cannot read the skeleton {root}: {exc.strerror or exc}") from exc
    return Skeleton(source=root, files=tuple(files), init=init)


# --- the public key -------------------------------------------------------------------------


def find_public_key(option: str | os.PathLike[str] | None = None) -> Path | None:
    """The public key to install: ``--key FILE`` (its ``.pub`` when given the private
    key), else the first of ``~/.ssh/id_ed25519.pub``, ``id_ecdsa.pub``, ``id_rsa.pub``."""
    if option is not None:
        path = Path(os.path.expanduser(os.fspath(option)))
        pub = path.with_name(path.name + ".pub")
        if path.suffix != ".pub" and pub.is_file():
            return pub
        if not path.is_file():
            raise ConfigError(f"the key {path} does not exist")
        return path
    ssh_dir = Path(os.path.expanduser("~/.ssh"))
    for name in PUBLIC_KEYS:
        if (ssh_dir / name).is_file():
            return ssh_dir / name
    return None


def read_public_key(path: Path) -> str:
    """The key as one ``type base64 [comment]`` line, checked."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace").strip()
    except OSError as exc:
        raise ConfigError(f"cannot read the key {path}: {exc.strerror}") from exc
    lines = [line for line in text.splitlines() if line.strip() and not line.startswith("#")]
    bad = ConfigError(f"{path} is not an OpenSSH public key", hint="pass --key FILE.pub")
    if len(lines) != 1:
        raise bad
    parts = lines[0].split(None, 2)
    if len(parts) < 2 or not _KEY_TYPES.match(parts[0]):
        raise bad
    try:
        base64.b64decode(parts[1], validate=True)
    except (binascii.Error, ValueError) as exc:
        raise bad from exc
    return " ".join(parts)


# --- the admin session ----------------------------------------------------------------------


class AdminSession:
    """Root on the robot through an admin login: directly or through ``sudo -S``."""

    def __init__(
        self, transport: Transport, *, admin: str, robot: str, python: str = "python3"
    ) -> None:
        self.transport = transport
        self.admin = admin
        self.robot = robot
        self.python = python

    def probe(self, user: str) -> RobotAccount:
        """Whether the admin is root, and whether ``user`` exists (no root needed)."""
        command = f"id -u; getent passwd {shlex.quote(user)} || true"
        out, err, status = _run(self.transport.exec(command), b"")
        lines = out.decode("utf-8", "replace").splitlines()
        uid_line = next((line for line in lines if line.strip().isdigit()), None)
        if status != 0 or uid_line is None:
            raise RemoteError(
                f"cannot look up {user} on {self.robot} as {self.admin}: "
                f"{err.decode('utf-8', 'replace').strip() or f'exit {status}'}"
            )
        entry = next((line.split(":") for line in lines if line.startswith(user + ":")), None)
        if entry is None or len(entry) < 7:
            return RobotAccount(
                admin_is_root=uid_line.strip() == "0", exists=False, uid=None, home=None
            )
        return RobotAccount(
            admin_is_root=uid_line.strip() == "0",
            exists=True,
            uid=int(entry[2]) if entry[2].isdigit() else None,
            home=entry[5],
        )

    def sudo_asks_password(self) -> bool:
        """False when the admin's sudo needs no password (NOPASSWD)."""
        _out, _err, status = _run(self.transport.exec("sudo -k -n true"), b"")
        return status != 0

    def check_sudo(self, password: str) -> None:
        """Make sure ``sudo`` takes ``password`` for the admin (cached credentials ignored)."""
        chan = self.transport.exec("sudo -k -S -p '' -v")
        _out, err, status = _run(chan, password.encode("utf-8") + b"\n")
        if status == 0:
            return
        text = err.decode("utf-8", "replace")
        who = f"{self.admin} on {self.robot}"
        if status == 127 or "not found" in text:
            raise RemoteError(
                f"sudo is not installed on {self.robot}", hint="log in as root: --admin-user root"
            )
        if "not in the sudoers" in text or "not allowed" in text or "may not run sudo" in text:
            raise ConnectError(f"{who} may not use sudo", hint="pass --admin-user with an admin")
        if "incorrect password" in text or "Sorry, try again" in text or "no password" in text:
            raise ConnectError(
                f"sudo refused the password of {who}",
                hint="check FETCHSYNC_ADMIN_PASSWORD or what you typed",
            )
        detail = text.strip().splitlines()[-1] if text.strip() else f"exit {status}"
        raise RemoteError(f"sudo failed for {who}: {detail}")

    def apply(
        self,
        request: AccountRequest,
        *,
        sudo: bool,
        sudo_password: str | None,
        on_stderr: Callable[[bytes], None],
    ) -> AccountReport:
        """Run the account program as root (through sudo with ``sudo``); stream its
        stderr; return its report."""
        program = _PROGRAM.read_bytes()
        head = b""
        command = f"{shlex.quote(self.python)} -c {shlex.quote(BOOTSTRAP)}"
        if sudo:
            command = "sudo -k -S -p '' " + command
        if sudo and sudo_password is not None:
            head = sudo_password.encode("utf-8") + b"\n" + b"-\n" * _SUDO_PADDING
        stdin = (
            head
            + BEGIN
            + str(len(program)).encode("ascii")
            + b"\n"
            + program
            + request.to_json()
            + b"\n"
        )
        out, err, status = _run(self.transport.exec(command), stdin, on_stderr=on_stderr)
        del stdin, head
        result = _parse_result(out)
        if result is None:
            detail = err.decode("utf-8", "replace").strip()
            raise RemoteError(
                f"the account program on {self.robot} gave no result "
                f"(exit {status})" + (f": {detail[-500:]}" if detail else "")
            )
        if "traceback" in result:
            log.debug("robot traceback:\n%s", result["traceback"])
        return AccountReport.from_robot(result, robot=self.robot)


def _parse_result(out: bytes) -> dict[str, Any] | None:
    for line in reversed(out.splitlines()):
        if line.startswith(_RESULT_PREFIX):
            try:
                data = json.loads(line[len(_RESULT_PREFIX) :].decode("utf-8"))
            except ValueError as exc:
                raise ProtocolError(f"unreadable result from the account program: {exc}") from exc
            if not isinstance(data, dict):
                raise ProtocolError("unreadable result from the account program")
            return data
    return None


def _run(
    chan: Channel, stdin: bytes, *, on_stderr: Callable[[bytes], None] | None = None
) -> tuple[bytes, bytes, int]:
    """Feed ``stdin``, close it, collect stdout and stderr (streamed to ``on_stderr``)."""
    err_chunks: list[bytes] = []

    def drain() -> None:
        while True:
            data = chan.recv_stderr(65536)
            if not data:
                return
            err_chunks.append(data)
            if on_stderr is not None:
                on_stderr(data)

    reader = threading.Thread(target=drain, name="fetchsync-account-stderr", daemon=True)
    reader.start()
    try:
        try:
            chan.send_all(stdin)
            chan.shutdown_write()
        except LinkLostError as exc:
            # The command may have ended without reading it all (sudo refused):
            # what it printed says more than the closed channel.
            log.debug("the robot stopped reading stdin: %s", exc)
        out = bytearray()
        while True:
            data = chan.recv(65536)
            if not data:
                break
            out += data
        status = chan.exit_status()
        reader.join(timeout=5)
    finally:
        chan.close()
    return bytes(out), b"".join(err_chunks), -1 if status is None else status


__all__ = [
    "BOOTSTRAP",
    "DEFAULT_ADMIN",
    "GROUPS",
    "AccountReport",
    "AccountRequest",
    "AdminSession",
    "RobotAccount",
    "Skeleton",
    "SkeletonFile",
    "builtin_skeleton",
    "check_fullname",
    "check_password",
    "check_user_name",
    "find_public_key",
    "find_skeleton",
    "is_legacy_skeleton",
    "load_skeleton",
    "read_public_key",
]
