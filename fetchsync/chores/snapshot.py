"""Diagnostics snapshots: run a set of commands on the robot and pack their output.

A snapshot is a list of :class:`Collector` (a name, a shell command, a timeout,
whether it needs sudo, and whether it is a system, ROS 1 or ROS 2 command),
run in parallel over one SSH connection, one channel each, and written into
one ``.tar.gz`` with a ``manifest.json``. :data:`DEFAULT_COLLECTORS` is the
default set; :func:`select_collectors` applies ``--only``, ``--skip``,
``--extra`` and a configuration file (:func:`load_config`). :data:`PROFILES`
names the sets: ``generic`` (the default) and ``fetch``, fetch_tools'
``debug-snapshot`` collection (:data:`FETCH_COLLECTORS`, with its 10 s bag of
:data:`FETCH_BAG_TOPICS`). The archive is a ``.tar.gz`` or, as fetch_tools
made, a ``.zip``.

A collector may name what it needs on the robot (``needs``: a shell test, such
as a file that must exist); when that is absent the collector is ``skipped``
and its manifest entry says what was missing, so a robot without, say, Fetch's
``read_board`` or a ``robot.service`` gives a complete snapshot of the rest. A
``tar`` collector prints a tar stream whose files land under ``NAME/`` (the
bag, ``~/.ros/log``).

How a command runs on the robot, from the outside in::

    sudo -S -p '' -- timeout -k 2 T bash -c 'exec </dev/null; source ROS; COMMAND'

- ``timeout`` (coreutils) bounds every command on the robot itself and kills
  its whole process group, children included, so a command that hangs leaves
  nothing behind; when the robot has no ``timeout``, the local deadline
  closes the channel, which only stops commands that write or read.
- ``sudo`` only for collectors that need it, only when the login user is not
  root, and with ``-S``: the password travels on the channel's stdin, never
  in an argument or the command string; the command's own stdin is
  ``/dev/null`` so it can never read a password sudo did not consume.
- ROS commands run in ``bash`` with the distribution's ``setup.bash`` (and the
  remote workspace's overlay, when known) sourced, like an interactive login.

A command that is not installed (exit 127, "command not found") is
``missing``, one that ran past its timeout is ``timeout``: neither fails the
snapshot. Only a lost link does, after the archive of what was collected is
written.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import io
import json
import logging
import os
import re
import shlex
import shutil
import socket
import tarfile
import tempfile
import threading
import time
import zipfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, BinaryIO

from fetchsync import __version__
from fetchsync.errors import ConfigError, FetchsyncError, LinkLostError, RemoteError, UsageError
from fetchsync.link.transport import Channel, Transport

log = logging.getLogger(__name__)

KINDS = ("system", "ros", "ros1", "ros2")
"""``ros`` runs on either ROS version; ``ros1`` / ``ros2`` only on that one."""

OK, FAILED, MISSING, TIMEOUT, SKIPPED = "ok", "failed", "missing", "timeout", "skipped"
STATUSES = (OK, FAILED, MISSING, TIMEOUT, SKIPPED)

DEFAULT_JOBS = 8
MAX_JOBS = 10
"""OpenSSH's default MaxSessions: channels one connection may hold open at once."""
DEFAULT_TIMEOUT = 10.0
KILL_GRACE = 2
"""Seconds between ``timeout``'s TERM and its KILL."""
MAX_OUTPUT = 64 << 20
"""Bytes kept per stream; the rest is dropped and the entry marked ``truncated``."""
DEFAULT_ROS_ROOT = "/opt/ros"
DEFAULT_BAG_DURATION = 10.0
BAG_NAME = "rosbag"
MANIFEST = "manifest.json"
MANIFEST_FORMAT = 1

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}\Z")
_TOPIC = re.compile(r"/?[A-Za-z~][A-Za-z0-9_/~]*\Z")
_NOT_FOUND = re.compile(rb"command not found|: not found\b")
_ABSENT_MARK = "fetchsync-absent: "
_ABSENT = re.compile(rb"^fetchsync-absent: ([^\n]*)", re.MULTILINE)
# Local deadline beyond the remote `timeout`: its KILL grace plus the round trip.
_DEADLINE_MARGIN = KILL_GRACE + 5.0
_BAG_MARGIN = 120.0  # recording stops on the robot; this bounds the transfer too


@dataclass(frozen=True)
class Collector:
    """One diagnostic command and how to run it."""

    name: str
    """File name in the archive (``NAME.txt``); letters, digits, ``_``, ``.``, ``-``."""
    command: str
    """A shell command line, run by ``sh`` (``bash`` for ROS kinds) on the robot."""
    timeout: float = DEFAULT_TIMEOUT
    needs_sudo: bool = False
    """Run through sudo when the login user is not root (dmesg, the system journal)."""
    kind: str = "system"
    """``system``, ``ros`` (either version), ``ros1`` or ``ros2``."""
    needs: str = ""
    """A shell test run first; when it fails the collector is skipped as absent."""
    absent: str = ""
    """What is absent when ``needs`` fails, for the manifest (``/var/log/syslog``)."""
    tar: bool = False
    """The command prints a tar stream; its files go into the archive under ``NAME/``."""

    def validate(self) -> None:
        """Raise ConfigError when a field is out of range."""
        if (
            not _NAME.match(self.name)
            or self.name in (BAG_NAME, "manifest")
            or self.name.endswith(".stderr")
        ):
            raise ConfigError(
                f"invalid collector name {self.name!r}: letters, digits, '_', '.', '-' "
                "(at most 64), starting with a letter or digit; not ending in .stderr, not "
                f"{BAG_NAME!r} or 'manifest'"
            )
        if not self.command.strip() or "\0" in self.command:
            raise ConfigError(f"collector {self.name!r} has an empty or invalid command")
        if not (0 < self.timeout <= 3600):
            raise ConfigError(f"collector {self.name!r}: timeout must be within (0, 3600] seconds")
        if self.kind not in KINDS:
            raise ConfigError(
                f"collector {self.name!r}: kind must be one of {', '.join(KINDS)}, not {self.kind!r}"
            )

    def runs_on(self, ros_version: int | None) -> bool:
        if self.kind == "system":
            return True
        if ros_version is None:
            return False
        return self.kind == "ros" or self.kind == f"ros{ros_version}"


def _c(
    name: str,
    command: str,
    timeout: float = DEFAULT_TIMEOUT,
    *,
    sudo: bool = False,
    kind: str = "system",
    needs: str = "",
    absent: str = "",
    tar: bool = False,
) -> Collector:
    return Collector(
        name=name,
        command=command,
        timeout=timeout,
        needs_sudo=sudo,
        kind=kind,
        needs=needs,
        absent=absent,
        tar=tar,
    )


def _file(name: str, path: str, *, sudo: bool = False) -> Collector:
    """``cat PATH``, skipped when the robot has no such file."""
    q = shlex.quote(path)
    return _c(name, f"cat {q}", sudo=sudo, needs=f"[ -e {q} ]", absent=path)


def _unit(name: str) -> tuple[Collector, Collector]:
    """fetch_tools' pair for a systemd unit: its file and ``service NAME status``."""
    path = f"/lib/systemd/system/{name}.service"
    return (
        _file(f"{name}.service", path),
        _c(f"{name}.service_status", f"service {name} status", needs=f"[ -e {path} ]", absent=path),
    )


def _read_board(name: str, address: str) -> Collector:
    """Fetch's board query: ``read_board`` on PATH, else fetch_drivers' through rosrun."""
    return _c(
        name,
        "if command -v read_board >/dev/null 2>&1; then read_board "
        f"{address}; else rosrun fetch_drivers read_board {address}; fi",
        15,
        kind="ros1",
        needs="command -v read_board || rospack find fetch_drivers",
        absent="read_board (fetch_drivers)",
    )


# The last day of ~/.ros/log, as a tar stream (find -type f: the `latest` links stay out).
_ROS_LOG = (
    'cd "$HOME/.ros" && find log -type f -mtime -1 -print0 | tar --null --no-recursion -T - -cf -'
)


DEFAULT_COLLECTORS: tuple[Collector, ...] = (
    _c("date", "date -R"),
    _c("uname", "uname -a"),
    _c("os_release", "cat /etc/os-release"),
    _c("uptime", "uptime"),
    _c("meminfo", "cat /proc/meminfo"),
    _c("df", "df -h"),
    _c("top", "top -b -n 1"),
    _c("dmesg", "dmesg", sudo=True),
    _c("journal", "journalctl -b --no-pager -n 10000", 20, sudo=True),
    _c("ip_addr", "ip addr"),
    _c("ip_route", "ip route"),
    _c("hosts", "cat /etc/hosts"),
    _c("lsusb", "lsusb -v", 20),
    _c("lspci", "lspci -vv", 20),
    _c("dpkg_ros", "COLUMNS=200 dpkg -l 'ros-*'"),
    _c("dpkg_all", "COLUMNS=200 dpkg -l", 20),
    # ROS 1 and ROS 2 share names, so --only/--skip mean the same on both.
    _c("ros_nodes", "rosnode list", 15, kind="ros1"),
    _c("ros_topics", "rostopic list -v", 15, kind="ros1"),
    _c("ros_services", "rosservice list -n", 15, kind="ros1"),
    _c("ros_params", "rosparam get /", 15, kind="ros1"),
    _c("ros_nodes", "ros2 node list", 15, kind="ros2"),
    _c("ros_topics", "ros2 topic list -t", 15, kind="ros2"),
    _c("ros_services", "ros2 service list -t", 15, kind="ros2"),
    _c("ros_params", "ros2 param list", 30, kind="ros2"),
    _c("ros_doctor", "ros2 doctor --report", 60, kind="ros2"),
    _c(
        "ros_log",
        _ROS_LOG,
        30,
        kind="ros2",
        needs='[ -d "$HOME/.ros/log" ]',
        absent="~/.ros/log",
        tar=True,
    ),
)

FETCH_BAG_TOPICS = ("/robot_state", "/diagnostics", "/diagnostics_agg", "/battery_state")
"""What fetch_tools' debug-snapshot recorded, for 10 s."""

FETCH_COLLECTORS: tuple[Collector, ...] = (
    # fetch_tools' debug-snapshot, its file names kept (Fetch's support knows them).
    _c("dpkg_fetch", "COLUMNS=200 dpkg -l 'ros-*-fetch-*'", 20),
    _c("dpkg_ros", "COLUMNS=200 dpkg -l 'ros-*'", 20),
    _c("dpkg_all", "COLUMNS=200 dpkg -l", 20),
    _c("lsusb", "lsusb -v", 20),
    _c("lspci", "lspci -vv", 20),
    _c("roswtf", "roswtf", 60, kind="ros1"),
    _c("rosnode_list", "rosnode list", 15, kind="ros1"),
    _c("rostopic_list", "rostopic list", 15, kind="ros1"),
    _c("rossrv_list", "rosservice list", 15, kind="ros1"),
    _c("rosparam_list", "rosparam list", 15, kind="ros1"),
    _c("rosparam_dump", "rosparam get /", 15, kind="ros1"),
    _c("dmesg", "dmesg", sudo=True),
    _file("syslog", "/var/log/syslog"),
    _c("date", "date"),
    _c("meminfo", "cat /proc/meminfo"),
    _c("ip_route", "ip route"),
    _c("ifconfig", "ifconfig -a"),
    _c("iwconfig", "iwconfig"),
    _file("network_interfaces", "/etc/network/interfaces"),
    # root's only (mode 600) since Ubuntu 22.04: through sudo when there is a password
    _c(
        "netplan_full",
        "cat /etc/netplan/*.yaml",
        sudo=True,
        needs="ls /etc/netplan/*.yaml",
        absent="/etc/netplan/*.yaml",
    ),
    _c("hosts", "cat /etc/hosts"),
    _c("env", "env"),
    *_unit("roscore"),
    *_unit("robot"),
    _c(
        "robot.journalctl",
        "journalctl -u robot --no-pager",
        20,
        needs="[ -e /lib/systemd/system/robot.service ]",
        absent="/lib/systemd/system/robot.service",
    ),
    *_unit("ps3joy"),
    *_unit("ps4joy"),
    _read_board("read_board_charger", "0x3f"),
    _read_board("read_board_mainboard", "0x00"),
    _read_board("read_board_wheel_left", "0x11"),
    _read_board("read_board_wheel_right", "0x12"),
    _read_board("read_board_gripper", "0x80"),
    _c("battery_state", "rostopic echo -n 1 /battery_state", 15, kind="ros1"),
    _c("robot_state", "rostopic echo -n 1 /robot_state", 15, kind="ros1"),
    _c("top", "top -n 1 -b"),
    _file("robot_log", "/var/log/ros/robot.log", sudo=True),
)

PROFILES: dict[str, tuple[Collector, ...]] = {
    "generic": DEFAULT_COLLECTORS,
    "fetch": FETCH_COLLECTORS,
}
"""The collector sets by name; ``generic`` is the default."""


# --- the set -----------------------------------------------------------------------------------


def parse_extra(spec: str) -> Collector:
    """``NAME=COMMAND`` (a system command, default timeout) -> Collector."""
    name, sep, command = spec.partition("=")
    if not sep:
        raise UsageError(f"--extra {spec!r}: expected NAME=COMMAND")
    collector = Collector(name=name.strip(), command=command.strip())
    try:
        collector.validate()
    except ConfigError as exc:
        raise UsageError(f"--extra {spec!r}: {exc.message}") from exc
    return collector


@dataclass(frozen=True)
class SnapshotConfig:
    """What a configuration file says: collectors to add (or replace), ``only``, ``skip``."""

    collectors: tuple[Collector, ...] = ()
    only: tuple[str, ...] = ()
    skip: tuple[str, ...] = ()
    defaults: bool = True
    """False: start from an empty set instead of :data:`DEFAULT_COLLECTORS`."""


_CONFIG_KEYS = {"collectors", "only", "skip", "defaults"}
_COLLECTOR_KEYS = {"name", "command", "timeout", "needs_sudo", "kind"}


def load_config(path: str | os.PathLike[str]) -> SnapshotConfig:
    """Read a JSON (``.json``) or TOML (any other name; Python >= 3.11) configuration file.

    TOML::

        skip = ["lspci"]              # names to leave out; `only = [...]` keeps just those
        defaults = true               # false: only the collectors below

        [[collectors]]
        name = "charger"
        command = "rosrun fetch_drivers read_board 0x3f"
        kind = "ros1"                 # system (default), ros, ros1, ros2
        timeout = 20                  # seconds, default 10
        needs_sudo = false
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"cannot read the snapshot configuration {p}: {exc.strerror}") from exc
    data: Any
    try:
        if p.suffix.lower() == ".json":
            data = json.loads(raw.decode("utf-8"))
        else:
            try:
                import tomllib
            except ModuleNotFoundError as exc:  # Python 3.10
                raise ConfigError(
                    f"cannot read {p}: TOML needs Python 3.11 or newer",
                    hint="write it as JSON with a .json name",
                ) from exc
            data = tomllib.loads(raw.decode("utf-8"))
    except ConfigError:
        raise
    except ValueError as exc:  # JSONDecodeError, TOMLDecodeError, UnicodeDecodeError
        raise ConfigError(f"cannot parse the snapshot configuration {p}: {exc}") from exc
    return _config_from(data, where=str(p))


def _config_from(data: Any, *, where: str) -> SnapshotConfig:
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table (JSON object) at the top")
    unknown = set(data) - _CONFIG_KEYS
    if unknown:
        raise ConfigError(
            f"{where}: unknown keys {', '.join(sorted(unknown))} "
            f"(known: {', '.join(sorted(_CONFIG_KEYS))})"
        )
    collectors = []
    for i, item in enumerate(data.get("collectors", [])):
        if not isinstance(item, dict):
            raise ConfigError(f"{where}: collectors[{i}] is not a table")
        bad = set(item) - _COLLECTOR_KEYS
        if bad or "name" not in item or "command" not in item:
            raise ConfigError(
                f"{where}: collectors[{i}] needs name and command and may have "
                f"timeout, needs_sudo, kind (got {', '.join(sorted(item))})"
            )
        try:
            c = Collector(
                name=str(item["name"]),
                command=str(item["command"]),
                timeout=float(item.get("timeout", DEFAULT_TIMEOUT)),
                needs_sudo=_bool(item.get("needs_sudo", False), where, "needs_sudo"),
                kind=str(item.get("kind", "system")),
            )
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{where}: collectors[{i}]: {exc}") from exc
        c.validate()
        collectors.append(c)
    return SnapshotConfig(
        collectors=tuple(collectors),
        only=_names(data.get("only", []), where),
        skip=_names(data.get("skip", []), where),
        defaults=_bool(data.get("defaults", True), where, "defaults"),
    )


def _bool(value: Any, where: str, key: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{where}: {key} must be true or false")
    return value


def _names(value: Any, where: str) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ConfigError(f"{where}: only and skip must be lists of names")
    return tuple(value)


def select_collectors(
    *,
    config: SnapshotConfig | None = None,
    only: Iterable[str] = (),
    skip: Iterable[str] = (),
    extra: Iterable[Collector] = (),
    base: Sequence[Collector] = DEFAULT_COLLECTORS,
) -> tuple[Collector, ...]:
    """The set to run: base (unless the config drops it), the config's, ``only``, ``skip``, extras.

    A collector with the name (and ROS version) of an earlier one replaces it.
    ``only`` keeps just the named ones; the command line's extras are always
    kept, so ``--only uname --extra x=...`` runs both. Naming a collector
    that does not exist is an error, so a typo does not silently drop it.
    """
    config = config or SnapshotConfig()
    chosen: list[Collector] = list(base) if config.defaults else []
    for c in config.collectors:
        chosen = _put(chosen, c)
    known = {c.name for c in chosen}
    wanted = set(config.only) | set(only)
    dropped = set(config.skip) | set(skip)
    extras = list(extra)
    unknown = (wanted | dropped) - known - {c.name for c in extras}
    if unknown:
        raise UsageError(
            f"no collector named {', '.join(sorted(unknown))}",
            hint=f"known: {', '.join(sorted(known))}",
        )
    if wanted:
        chosen = [c for c in chosen if c.name in wanted]
    chosen = [c for c in chosen if c.name not in dropped]
    for c in extras:
        chosen = _put(chosen, c)
    return tuple(chosen)


def _put(chosen: list[Collector], new: Collector) -> list[Collector]:
    """``chosen`` with ``new`` in the place of those it replaces, else at the end."""
    out: list[Collector] = []
    placed = False
    for old in chosen:
        # The ROS 1 and ROS 2 variants of one name coexist; any other same name is replaced.
        if old.name == new.name and {old.kind, new.kind} != {"ros1", "ros2"}:
            if not placed:
                out.append(new)
                placed = True
            continue
        out.append(old)
    if not placed:
        out.append(new)
    return out


# --- the robot -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class RosInstall:
    version: int
    distro: str
    prefix: str
    """``/opt/ros/<distro>``; its ``setup.bash`` sets the environment up."""


@dataclass(frozen=True)
class RobotInfo:
    """What one probe learns about the robot before anything else runs."""

    uid: int
    user: str
    has_timeout: bool
    sudo: str | None
    """``nopasswd``, ``password``, ``missing``, or None when not asked (root, or no need)."""
    ros: RosInstall | None
    ros_found: tuple[RosInstall, ...] = ()


def probe_command(*, ros_root: str = DEFAULT_ROS_ROOT, check_sudo: bool) -> str:
    """The one shell script :func:`probe` runs (wrapped for ``sh``)."""
    script = (
        'echo "uid=$(id -u)"; echo "user=$(id -un)"\n'
        'command -v timeout >/dev/null 2>&1 && echo "timeout=yes"\n'
        f'if [ "$(id -u)" != 0 ] && [ {1 if check_sudo else 0} = 1 ]; then\n'
        '  if ! command -v sudo >/dev/null 2>&1; then echo "sudo=missing"\n'
        '  elif sudo -n true </dev/null >/dev/null 2>&1; then echo "sudo=nopasswd"\n'
        '  else echo "sudo=password"; fi\n'
        "fi\n"
        f"for f in {shlex.quote(ros_root.rstrip('/') or '/')}/*/setup.bash; do\n"
        '  [ -f "$f" ] || continue; d=${f%/setup.bash}\n'
        '  if [ -e "$d/bin/ros2" ]; then echo "ros=2 $d"\n'
        '  elif [ -e "$d/bin/roscore" ] || [ -e "$d/bin/rosversion" ] || [ -d "$d/share/catkin" ]\n'
        '  then echo "ros=1 $d"; fi\n'
        "done\n"
        'echo "ros_distro=${ROS_DISTRO:-}"\n'
        # ROS already on the login PATH (sourced by ~/.bashrc, a source build): used when
        # nothing is under the ROS root. Not rosversion: pip's rospkg installs one anywhere.
        'command -v ros2 >/dev/null 2>&1 && echo "ros_path=2"\n'
        "for t in roscore rosbag rostopic rosnode; do\n"
        '  if command -v $t >/dev/null 2>&1; then echo "ros_path=1"; break; fi\n'
        "done\n"
    )
    return "sh -c " + shlex.quote(script)


def parse_probe(text: str) -> RobotInfo:
    """Read :func:`probe_command`'s output (a login shell may print noise around it)."""
    values: dict[str, str] = {}
    found: list[RosInstall] = []
    on_path: set[int] = set()
    for line in text.splitlines():
        key, sep, value = line.partition("=")
        if not sep:
            continue
        if key == "ros_path" and value.strip() in ("1", "2"):
            on_path.add(int(value.strip()))
        elif key == "ros":
            version, _, prefix = value.partition(" ")
            if version in ("1", "2") and prefix.startswith("/"):
                found.append(
                    RosInstall(int(version), prefix.rstrip("/").rsplit("/", 1)[-1], prefix)
                )
        elif key in ("uid", "user", "timeout", "sudo", "ros_distro"):
            values[key] = value.strip()
    try:
        uid = int(values["uid"])
    except (KeyError, ValueError) as exc:
        raise RemoteError("the robot's probe printed no user id (is its shell POSIX?)") from exc
    found.sort(key=lambda r: r.distro)
    preferred = [r for r in found if r.distro == values.get("ros_distro")]
    candidates = preferred or found
    ros = candidates[-1] if candidates else None
    if ros is None and on_path:
        # Nothing to source: the login environment already has it (prefix "").
        ros = RosInstall(max(on_path), values.get("ros_distro", ""), "")
    return RobotInfo(
        uid=uid,
        user=values.get("user", ""),
        has_timeout=values.get("timeout") == "yes",
        sudo=values.get("sudo") or None,
        ros=ros,
        ros_found=tuple(found),
    )


def probe(
    transport: Transport,
    *,
    ros_root: str = DEFAULT_ROS_ROOT,
    check_sudo: bool = True,
    timeout: float = 30.0,
) -> RobotInfo:
    """Ask the robot who we are, whether it has ``timeout`` and sudo, and which ROS."""
    job = _Job(
        name="probe",
        kind="system",
        command="probe",
        remote=probe_command(ros_root=ros_root, check_sudo=check_sudo),
        deadline=timeout,
    )
    with tempfile.TemporaryDirectory(prefix="fetchsync-probe-") as tmp:
        result = _run(transport, job, Path(tmp), has_timeout=False)
        if result.link_lost:
            raise LinkLostError(result.error or "the link to the robot was lost")
        text = result.stdout.read_text(errors="replace") if result.stdout else ""
        if result.status != OK:
            raise RemoteError(
                f"cannot probe the robot ({result.status}): "
                f"{result.stderr_text() or result.error or 'no output'}"
            )
    return parse_probe(text)


# --- sudo ----------------------------------------------------------------------------------------


PasswordSource = Callable[[int], "str | None"]
"""Asked for the sudo password (the argument counts earlier refusals); None: no password."""


@dataclass(frozen=True)
class SudoPlan:
    """How collectors that need sudo run: ``mode`` is ``none``, ``nopasswd`` or ``password``."""

    mode: str
    password: bytes | None = field(default=None, repr=False)
    note: str | None = None

    def prefix(self) -> str:
        if self.mode == "nopasswd":
            return "sudo -n -- "
        if self.mode == "password":
            # -S: the password comes on stdin; -p '': no prompt mixed into stderr.
            return "sudo -S -p '' -- "
        return ""

    def stdin(self) -> bytes:
        return self.password + b"\n" if self.mode == "password" and self.password else b""


def plan_sudo(
    transport: Transport,
    info: RobotInfo,
    *,
    needed: Sequence[str],
    policy: str,
    password: PasswordSource | None,
) -> SudoPlan:
    """Decide how the ``needed`` collectors run; ``policy`` is ``auto``, ``always`` or ``never``.

    Without a password (none given, no terminal), ``always`` is an error and
    ``auto`` runs them without sudo, saying so in the plan's note. A password
    is tried once on the robot before use, so a wrong one costs one refused
    attempt, not one per collector; one refused every time it was asked for is
    an error whatever the policy: the user meant sudo to be used.
    """
    without = f"ran {', '.join(needed)} without sudo"
    if not needed or info.uid == 0:
        return SudoPlan("none")
    if policy == "never":
        return SudoPlan("none", note=f"{without} (--no-sudo)")
    if info.sudo == "missing":
        if policy == "always":
            raise ConfigError(f"--sudo: the robot has no sudo command for {info.user}")
        return SudoPlan("none", note=f"{without}: the robot has no sudo command")
    if info.sudo == "nopasswd":
        return SudoPlan("nopasswd")
    refusal = ""
    for attempt in range(3):
        pw = password(attempt) if password is not None else None
        if pw is None:
            break
        if "\n" in pw or "\r" in pw or "\0" in pw:
            raise UsageError("the sudo password cannot contain a line break or NUL")
        plan = SudoPlan("password", password=pw.encode("utf-8"))
        refused = _check_password(transport, plan)
        if refused is None:
            return plan
        log.info("sudo on the robot refused the password (attempt %d)", attempt + 1)
        refusal = refused
    if refusal:
        raise ConfigError(
            f"sudo on the robot refused the password for {info.user}: {refusal}",
            hint="check FETCHSYNC_SUDO_PASSWORD, or pass --no-sudo",
        )
    if policy == "always":
        raise UsageError(
            "--sudo needs the robot's sudo password and there is no terminal to ask it",
            hint="set FETCHSYNC_SUDO_PASSWORD",
        )
    return SudoPlan(
        "none",
        note=f"{without} (sudo wants a password: pass --sudo in a terminal, "
        "or set FETCHSYNC_SUDO_PASSWORD)",
    )


def _check_password(transport: Transport, plan: SudoPlan) -> str | None:
    """None when sudo accepts the plan's password, else sudo's last line of complaint."""
    job = _Job(
        name="sudo-check",
        kind="system",
        command="true",
        remote=plan.prefix() + "true",
        deadline=20.0,
        stdin=plan.stdin(),
        sudo=True,
    )
    with tempfile.TemporaryDirectory(prefix="fetchsync-sudo-") as tmp:
        result = _run(transport, job, Path(tmp), has_timeout=False)
        if result.link_lost:
            raise LinkLostError(result.error or "the link to the robot was lost")
        if result.status == OK:
            return None
        lines = [ln for ln in result.stderr_text().splitlines() if ln.strip()]
        return lines[-1].strip() if lines else f"exit {result.exit_code}"


# --- running -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Job:
    name: str
    kind: str
    command: str
    """As the user wrote it (what the manifest shows)."""
    remote: str
    """What the robot runs: wrappers included, never a secret."""
    deadline: float
    """Local seconds before the channel is closed."""
    timeout: float | None = None
    """The remote ``timeout`` given, to tell its exit 124/137 from the command's own."""
    stdin: bytes = field(default=b"", repr=False)
    sudo: bool = False
    tar: bool = False
    """stdout is a tar stream whose files go into the archive (the bag)."""


@dataclass
class CommandResult:
    """What one collector produced; ``stdout``/``stderr`` are files in a work directory."""

    name: str
    kind: str
    command: str
    status: str
    exit_code: int | None = None
    duration: float = 0.0
    stdout: Path | None = None
    stderr: Path | None = None
    bytes: int = 0
    stderr_bytes: int = 0
    truncated: bool = False
    sudo: bool = False
    error: str | None = None
    link_lost: bool = False
    tar: bool = False
    files: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    def stderr_text(self) -> str:
        if self.stderr is None or not self.stderr.exists():
            return ""
        return self.stderr.read_text(errors="replace").strip()

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name,
            "kind": self.kind,
            "command": self.command,
            "status": self.status,
            "exit_code": self.exit_code,
            "duration": round(self.duration, 3),
            "bytes": self.bytes,
            "stderr_bytes": self.stderr_bytes,
            "sudo": self.sudo,
            "files": list(self.files),
        }
        if self.truncated:
            out["truncated"] = True
        if self.error:
            out["error"] = self.error
        out.update(self.extra)
        return out


class _Drain(threading.Thread):
    """Copies one stream of a channel into a file, up to MAX_OUTPUT bytes."""

    def __init__(self, recv: Callable[[int], bytes], path: Path, *, head: int = 4096) -> None:
        super().__init__(daemon=True, name=f"fetchsync-snapshot-{path.name}")
        self.recv = recv
        self.path = path
        self.size = 0
        self.truncated = False
        self.head = b""  # the first bytes, to recognise "command not found"
        self._head_size = head
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            with open(self.path, "wb") as f:
                self._copy(f)
        except LinkLostError as exc:
            self.error = exc
        except Exception as exc:  # noqa: BLE001 - reported in the result, never lost
            self.error = exc

    def _copy(self, f: BinaryIO) -> None:
        while True:
            data = self.recv(1 << 16)
            if not data:
                return
            if len(self.head) < self._head_size:
                self.head += data[: self._head_size - len(self.head)]
            room = MAX_OUTPUT - self.size
            if room > 0:
                f.write(data[:room])
            if len(data) > room:
                self.truncated = True
            self.size += min(len(data), max(room, 0))


def _run(transport: Transport, job: _Job, workdir: Path, *, has_timeout: bool) -> CommandResult:
    result = CommandResult(
        name=job.name, kind=job.kind, command=job.command, status=FAILED, sudo=job.sudo, tar=job.tar
    )
    start = time.monotonic()
    try:
        chan: Channel = transport.exec(job.remote)
    except FetchsyncError as exc:
        result.error = str(exc)
        result.link_lost = isinstance(exc, LinkLostError)
        return result
    suffix = ".tar" if job.tar else ".out"
    out = _Drain(chan.recv, workdir / f"{job.name}{suffix}")
    err = _Drain(chan.recv_stderr, workdir / f"{job.name}.err")
    out.start()
    err.start()
    timed_out = False
    status: int | None = None
    try:
        if job.stdin:
            chan.send_all(job.stdin)
        chan.shutdown_write()
        end = start + job.deadline
        for drain in (out, err):
            drain.join(max(0.0, end - time.monotonic()))
            if drain.is_alive():
                timed_out = True
                break
        if not timed_out:
            status = chan.exit_status(max(0.5, end - time.monotonic()))
            timed_out = status is None
    except LinkLostError as exc:
        result.error, result.link_lost = str(exc), True
    except FetchsyncError as exc:
        result.error = str(exc)
    finally:
        # Closing also wakes drains blocked on a command that outlived its deadline.
        chan.close()
        out.join(5)
        err.join(5)
    result.duration = time.monotonic() - start
    result.stdout, result.stderr = out.path, err.path
    result.bytes, result.stderr_bytes = out.size, err.size
    result.truncated = out.truncated or err.truncated
    result.exit_code = status
    for drain in (out, err):
        if drain.error is not None and result.error is None:
            result.error = str(drain.error)
            result.link_lost = isinstance(drain.error, LinkLostError)
    if timed_out:
        result.status = TIMEOUT
        result.error = result.error or f"no exit within {job.deadline:g} s; the channel was closed"
    elif status is None:
        result.status = FAILED
    else:
        result.status = classify(
            status, err.head, timeout=job.timeout if has_timeout else None, elapsed=result.duration
        )
        absent = _ABSENT.search(err.head)
        if absent:
            result.status = SKIPPED
            result.error = "not on the robot: " + absent.group(1).decode("utf-8", "replace")
        elif result.status == MISSING and not result.error:
            result.error = "not installed on the robot"
    return result


def classify(
    exit_code: int, stderr_head: bytes, *, timeout: float | None = None, elapsed: float = 0.0
) -> str:
    """``ok``, ``missing`` (127, or "not found"), ``timeout`` (``timeout``'s 124/137) or ``failed``."""
    if exit_code == 0:
        return OK
    if exit_code == 127 or _NOT_FOUND.search(stderr_head):
        return MISSING
    # 124: timeout's TERM ended it; 137: its KILL had to. Only trusted past the time limit,
    # so a command that itself exits 124 quickly is not mistaken for one that hung.
    if timeout is not None and exit_code in (124, 137) and elapsed >= timeout:
        return TIMEOUT
    return FAILED


def remote_command(
    collector: Collector, *, info: RobotInfo, sudo: SudoPlan, overlay: str | None = None
) -> str:
    """The command line the robot runs for ``collector``; it never holds a password."""
    script = collector.command
    if collector.needs:
        # Absent: a line the classifier knows, and no output to keep.
        script = (
            f"if ! {{ {collector.needs}; }} >/dev/null 2>&1; then "
            f"echo {shlex.quote(_ABSENT_MARK + (collector.absent or collector.needs))} >&2; "
            f"exit 0; fi; {script}"
        )
    shell = "sh"
    if collector.kind != "system":
        if info.ros is None:
            raise ValueError(f"{collector.name} needs ROS and the robot has none")
        script = _ros_env_script(info.ros, overlay) + script
        shell = "bash"
    use_sudo = collector.needs_sudo and sudo.mode != "none"
    if use_sudo:
        # sudo -S does not read stdin when it needs no password (root, a cached
        # ticket): the command must not inherit what we sent it.
        script = "exec </dev/null; " + script
    line = f"{shell} -c {shlex.quote(script)}"
    if info.has_timeout:
        line = f"timeout -k {KILL_GRACE} {collector.timeout:g} {line}"
    if use_sudo:
        # timeout inside sudo: it must be allowed to kill what runs as root.
        line = sudo.prefix() + line
    return line


def _ros_env_script(ros: RosInstall, overlay: str | None) -> str:
    """bash that sources the distribution and, when given, the workspace overlay on the robot.

    The distribution is the one :func:`probe` chose, so the ROS version the
    collectors and the bag were picked for is the one they run under. The
    overlay is the first of ``devel/``, ``devel_isolated/``, ``install/`` with
    a ``setup.bash``. Sourcing noise goes to /dev/null, not into the
    collectors' stderr. (``run``'s ``fetchsync.chores.remote`` builds a similar
    environment; it was not in the repository yet when this was written.)
    """
    parts = (
        [f"source {shlex.quote(ros.prefix + '/setup.bash')} >/dev/null 2>&1"] if ros.prefix else []
    )
    if overlay:
        ws = _shell_path(overlay)
        parts.append(
            f"for _f in {ws}/devel/setup.bash {ws}/devel_isolated/setup.bash "
            f'{ws}/install/setup.bash; do if [ -f "$_f" ]; then source "$_f" >/dev/null 2>&1; '
            "break; fi; done; unset _f"
        )
    return "; ".join(parts) + "; " if parts else ""


def _shell_path(path: str) -> str:
    """``~/x`` -> ``"$HOME"/'x'``; anything else quoted as it is."""
    if path == "~":
        return '"$HOME"'
    if path.startswith("~/"):
        return '"$HOME"/' + shlex.quote(path[2:])
    return shlex.quote(path)


def bag_command(
    ros: RosInstall,
    topics: Sequence[str],
    duration: float,
    *,
    has_timeout: bool,
    overlay: str | None = None,
) -> str:
    """Record ``topics`` for ``duration`` s into a temporary directory; print it as a tar stream."""
    quoted = " ".join(shlex.quote(t) for t in topics)
    d = f"{duration:g}"
    if ros.version == 1:
        record = f"rosbag record -q --duration={d} -O snapshot.bag {quoted}"
        if has_timeout:
            record = f"timeout -s INT -k 10 {duration + 30:g} {record}"
    else:
        # ros2 bag record has no stop-after option in every distribution; SIGINT
        # is how it closes the bag cleanly (timeout exits 124 then: expected).
        record = f"timeout -s INT -k 10 {d} ros2 bag record -o snapshot_bag {quoted}"
    script = (
        _ros_env_script(ros, overlay)
        + "d=$(mktemp -d) || exit 1; trap 'rm -rf \"$d\"' EXIT; "
        + f'(cd "$d" && {record}) </dev/null >&2; rc=$?; '
        + 'tar -C "$d" -cf - . || exit 1; '
        + ("exit $rc" if ros.version == 1 else '[ "$rc" = 124 ] && rc=0; exit $rc')
    )
    return "bash -c " + shlex.quote(script)


def check_topics(topics: Iterable[str]) -> tuple[str, ...]:
    out = []
    for t in topics:
        if not _TOPIC.match(t):
            raise UsageError(f"--bag {t!r} is not a ROS topic name")
        out.append(t)
    return tuple(out)


# --- the snapshot ---------------------------------------------------------------------------------


@dataclass
class Snapshot:
    """A finished snapshot: where the archive is and what its manifest says."""

    archive: Path
    size: int
    manifest: dict[str, Any]
    notes: list[str]
    link_lost: str | None = None

    def counts(self) -> dict[str, int]:
        """Commands per status (``ok``, ``failed``, ``missing``, ``timeout``, ``skipped``)."""
        return dict(self.manifest["summary"])

    def to_json(self) -> dict[str, Any]:
        return {"archive": str(self.archive), "size": self.size, **self.manifest}


ARCHIVE_FORMATS = ("tar", "zip")
_SUFFIX = {"tar": ".tar.gz", "zip": ".zip"}


def archive_name(robot: str, when: _dt.datetime, *, archive_format: str = "tar") -> str:
    """``snapshot-<robot>-<YYYYmmdd-HHMMSS>.tar.gz`` (``.zip``), the robot name made file-safe."""
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", robot).strip("._") or "robot"
    return f"snapshot-{safe}-{when.strftime('%Y%m%d-%H%M%S')}{_SUFFIX[archive_format]}"


def take_snapshot(
    transport: Transport,
    *,
    robot: str,
    collectors: Sequence[Collector],
    output: str | os.PathLike[str] = ".",
    jobs: int = DEFAULT_JOBS,
    sudo: str = "auto",
    password: PasswordSource | None = None,
    bag_topics: Sequence[str] = (),
    bag_duration: float = DEFAULT_BAG_DURATION,
    overlay: str | None = None,
    ros_root: str = DEFAULT_ROS_ROOT,
    progress: Callable[[CommandResult], None] | None = None,
    archive_format: str = "tar",
) -> Snapshot:
    """Run ``collectors`` on the robot behind ``transport`` and write the archive.

    ``output`` is a directory (the archive gets :func:`archive_name` there) or
    a file path. ``sudo`` is ``auto`` (sudo for the collectors that need it
    when a password is to be had), ``always`` or ``never``; ``password`` is
    asked only when sudo wants one. ``overlay`` is the remote workspace whose
    setup is sourced after the distribution's. ``progress`` is called (from a
    worker thread) as each command finishes. ``archive_format`` is ``tar``
    (``.tar.gz``) or ``zip``.
    """
    if archive_format not in ARCHIVE_FORMATS:
        raise ValueError(f"archive_format must be tar or zip, not {archive_format!r}")
    if sudo not in ("auto", "always", "never"):
        raise ValueError(f"sudo must be auto, always or never, not {sudo!r}")
    if not 1 <= jobs <= MAX_JOBS:
        raise UsageError(f"--jobs must be within 1..{MAX_JOBS} (sshd's default MaxSessions)")
    if bag_topics and not 0 < bag_duration <= 3600:
        raise UsageError("--bag-duration must be within (0, 3600] seconds")
    for c in collectors:
        c.validate()
    topics = check_topics(bag_topics)
    started = _dt.datetime.now().astimezone()
    t0 = time.monotonic()
    notes: list[str] = []

    wants_sudo = sudo != "never" and any(c.needs_sudo for c in collectors)
    info = probe(transport, ros_root=ros_root, check_sudo=wants_sudo)
    ros_version = info.ros.version if info.ros else None
    runnable = [c for c in collectors if c.runs_on(ros_version)]
    names = [c.name for c in runnable]
    if len(set(names)) != len(names):
        raise UsageError(
            "two collectors share a name: "
            + ", ".join(sorted({n for n in names if names.count(n) > 1}))
        )
    plan = plan_sudo(
        transport,
        info,
        needed=[c.name for c in runnable if c.needs_sudo],
        policy=sudo,
        password=password,
    )
    if plan.note:
        notes.append(plan.note)
    bag_skipped: str | None = None
    if info.ros is None:
        bag_skipped = "ROS not found on the robot"
        if topics or any(c.kind != "system" for c in collectors):
            what = "ROS commands and the bag" if topics else "ROS commands"
            notes.append(f"ROS not found on the robot (no {ros_root}/*/setup.bash): {what} skipped")
    elif len(info.ros_found) > 1:
        notes.append(f"several ROS distributions on the robot; used {info.ros.distro}")
    if topics and info.ros is not None and info.ros.version == 2 and not info.has_timeout:
        bag_skipped = "recording a ROS 2 bag needs `timeout` (coreutils) on the robot"
        notes.append(f"bag skipped: {bag_skipped}")

    work_list = [
        _Job(
            name=c.name,
            kind=c.kind,
            command=c.command,
            remote=remote_command(c, info=info, sudo=plan, overlay=overlay),
            deadline=c.timeout + _DEADLINE_MARGIN,
            timeout=c.timeout,
            stdin=plan.stdin() if c.needs_sudo else b"",
            sudo=c.needs_sudo and plan.mode != "none",
            tar=c.tar,
        )
        for c in runnable
    ]
    if topics and bag_skipped is None and info.ros is not None:
        # First: it takes longest, and the pool starts jobs in order.
        work_list.insert(
            0,
            _Job(
                name=BAG_NAME,
                kind=f"ros{info.ros.version}",
                command=f"record {' '.join(topics)} for {bag_duration:g} s",
                remote=bag_command(
                    info.ros, topics, bag_duration, has_timeout=info.has_timeout, overlay=overlay
                ),
                deadline=bag_duration + _BAG_MARGIN,
                tar=True,
            ),
        )

    out_path = Path(output)
    if out_path.is_dir():
        out_path = out_path / archive_name(robot, started, archive_format=archive_format)
    with tempfile.TemporaryDirectory(prefix="fetchsync-snapshot-") as tmp:
        results = _run_all(
            transport,
            work_list,
            Path(tmp),
            jobs=jobs,
            has_timeout=info.has_timeout,
            progress=progress,
        )
        ordered = _in_order(collectors, results, ros_version)
        if BAG_NAME in results:
            results[BAG_NAME].extra.update(topics=list(topics), requested_duration=bag_duration)
            ordered.insert(0, results[BAG_NAME])
        elif topics:
            ordered.insert(
                0,
                CommandResult(
                    name=BAG_NAME,
                    kind="ros",
                    command=f"record {' '.join(topics)}",
                    status=SKIPPED,
                    error=bag_skipped,
                    extra={"topics": list(topics), "requested_duration": bag_duration},
                ),
            )
        manifest: dict[str, Any] = {
            "format": MANIFEST_FORMAT,
            "fetchsync_version": __version__,
            "robot": robot,
            "user": info.user,
            "created": started.isoformat(timespec="seconds"),
            "duration": round(time.monotonic() - t0, 3),
            "collected_on": socket.gethostname(),
            "ros": (
                {"version": info.ros.version, "distro": info.ros.distro, "prefix": info.ros.prefix}
                if info.ros
                else None
            ),
            "sudo": plan.mode,
            "remote_timeout": info.has_timeout,
            "notes": list(notes),
        }
        size = write_archive(
            out_path, results=ordered, manifest=manifest, archive_format=archive_format
        )

    lost = [r for r in ordered if r.link_lost]
    return Snapshot(
        archive=out_path,
        size=size,
        manifest=manifest,
        notes=notes,
        link_lost=lost[0].error if lost else None,
    )


def _run_all(
    transport: Transport,
    work: Sequence[_Job],
    workdir: Path,
    *,
    jobs: int,
    has_timeout: bool,
    progress: Callable[[CommandResult], None] | None,
) -> dict[str, CommandResult]:
    results: dict[str, CommandResult] = {}
    lock = threading.Lock()

    def run_one(job: _Job) -> None:
        r = _run(transport, job, workdir, has_timeout=has_timeout)
        with lock:
            results[job.name] = r
        if progress is not None:
            progress(r)

    with ThreadPoolExecutor(max_workers=jobs, thread_name_prefix="fetchsync-snapshot") as pool:
        for future in [pool.submit(run_one, job) for job in work]:
            future.result()
    return results


def _in_order(
    collectors: Sequence[Collector], results: dict[str, CommandResult], ros_version: int | None
) -> list[CommandResult]:
    """Results in the collectors' order, with one ``skipped`` entry per name that did not run."""
    ordered: list[CommandResult] = []
    listed: set[str] = set()
    for c in collectors:
        if c.name in listed:
            continue
        if c.name in results:
            ordered.append(results[c.name])
        else:
            why = (
                "ROS not found on the robot"
                if ros_version is None
                else f"{c.kind} only; the robot has ROS {ros_version}"
            )
            ordered.append(
                CommandResult(
                    name=c.name, kind=c.kind, command=c.command, status=SKIPPED, error=why
                )
            )
        listed.add(c.name)
    return ordered


def write_archive(
    path: Path,
    *,
    results: Sequence[CommandResult],
    manifest: dict[str, Any],
    archive_format: str = "tar",
) -> int:
    """Write the ``.tar.gz`` or ``.zip`` (a ``.part`` renamed into place); return its size.

    Everything lies under one directory named like the archive. Adds the
    per-command entries (``commands``) and the ``summary`` to ``manifest``.
    The ``.part`` is a new file of a name nobody could guess (``mkstemp``:
    ``O_EXCL``, mode 0600: the robot's logs are private until the user shares
    them): a fixed ``NAME.part`` was opened by name, so in a shared directory
    another local user's symlink of that name made the snapshot truncate and
    overwrite a file of the user's it pointed at.
    """
    top = path.name
    for suffix in (".gz", ".tgz", ".tar", ".zip"):
        top = top.removesuffix(suffix)
    top = top or "snapshot"
    now = time.time()
    part: Path | None = None
    try:
        fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
        part = Path(name)
        with os.fdopen(fd, "wb") as raw, _writer(raw, archive_format) as add:
            files: list[tuple[str, Path]] = []
            streams: list[tuple[str, Path]] = []
            for r in results:
                if r.status == SKIPPED or r.stdout is None:
                    continue
                names = _bag_names(r) if r.tar else []
                if r.tar:  # still: _bag_names clears it when the stream is unreadable
                    r.files = [f"{r.name}/{name}" for name in names]
                    streams.append((r.name, r.stdout))
                else:
                    r.files.append(f"{r.name}.txt")
                    files.append((f"{r.name}.txt", r.stdout))
                if r.stderr is not None and r.stderr_bytes:
                    r.files.append(f"{r.name}.stderr.txt")
                    files.append((f"{r.name}.stderr.txt", r.stderr))
            entries = [r.to_json() for r in results]
            manifest["commands"] = entries
            manifest["summary"] = {s: sum(e["status"] == s for e in entries) for s in STATUSES}
            data = (json.dumps(manifest, indent=2) + "\n").encode()
            add(f"{top}/{MANIFEST}", io.BytesIO(data), len(data), now)
            for name, src in files:
                with open(src, "rb") as f:
                    add(f"{top}/{name}", f, src.stat().st_size, now)
            for name, stream in streams:
                _copy_bag(add, stream, f"{top}/{name}")
        os.replace(part, path)
    except OSError as exc:
        try:
            if part is not None:
                part.unlink()
        except OSError:
            pass
        raise ConfigError(
            f"cannot write the snapshot archive {path}: {exc.strerror or exc}"
        ) from exc
    return path.stat().st_size


_Add = Callable[[str, IO[bytes], int, float], None]
"""Adds one file to an archive being written: (name, content, size, mtime)."""


@contextlib.contextmanager
def _writer(out: IO[bytes], archive_format: str) -> Iterator[_Add]:
    """An archive written into ``out``, ``tar`` (gzip) or ``zip`` (deflate), file by file."""
    if archive_format != "zip":
        with tarfile.open(fileobj=out, mode="w:gz") as tar:
            yield lambda name, f, size, mtime: _add(tar, name, f, size, mtime)
        return

    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as archive:

        def add(name: str, f: IO[bytes], size: int, mtime: float) -> None:
            when = time.localtime(max(mtime, 315532800))[:6]  # zip dates start in 1980
            info = zipfile.ZipInfo(name, date_time=when)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            with archive.open(info, "w") as dst:
                shutil.copyfileobj(f, dst, 1 << 20)

        yield add


def _bag_members(source: tarfile.TarFile) -> Iterable[tuple[str, tarfile.TarInfo]]:
    """The regular files of a bag's tar stream, with names that stay inside ``rosbag/``."""
    for member in source.getmembers():
        name = os.path.normpath(member.name).lstrip("/")
        if member.isfile() and name not in ("", ".") and not name.startswith(".."):
            yield name, member


def _bag_names(r: CommandResult) -> list[str]:
    assert r.stdout is not None
    if r.bytes == 0:
        return []
    try:
        with tarfile.open(r.stdout, "r:") as source:
            return [name for name, _m in _bag_members(source)]
    except (tarfile.TarError, OSError) as exc:
        r.error = f"the bag's tar stream is unreadable: {exc}"
        if r.status == OK:
            r.status = FAILED
        r.tar = False  # keep the raw stream as rosbag.txt for whoever debugs it
        return []


def _copy_bag(add: _Add, stream: Path, under: str) -> None:
    if stream.stat().st_size == 0:
        return
    try:
        with tarfile.open(stream, "r:") as source:
            for name, member in _bag_members(source):
                f = source.extractfile(member)
                if f is not None:
                    add(f"{under}/{name}", f, member.size, member.mtime)
    except tarfile.TarError as exc:  # cut short after its index was read: keep what came
        log.warning("the tar stream of %s ended early: %s", under, exc)


def _add(tar: tarfile.TarFile, name: str, f: IO[bytes], size: int, mtime: float) -> None:
    info = tarfile.TarInfo(name)
    info.size, info.mtime, info.mode = size, mtime, 0o644
    tar.addfile(info, f)


__all__ = [
    "ARCHIVE_FORMATS",
    "DEFAULT_COLLECTORS",
    "FETCH_BAG_TOPICS",
    "FETCH_COLLECTORS",
    "KINDS",
    "PROFILES",
    "STATUSES",
    "Collector",
    "CommandResult",
    "PasswordSource",
    "RobotInfo",
    "RosInstall",
    "Snapshot",
    "SnapshotConfig",
    "SudoPlan",
    "archive_name",
    "bag_command",
    "classify",
    "load_config",
    "parse_extra",
    "parse_probe",
    "plan_sudo",
    "probe",
    "remote_command",
    "select_collectors",
    "take_snapshot",
    "write_archive",
]
