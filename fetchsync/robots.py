"""Naming robots: the groups and per-robot settings of ``robots.toml``.

``--robot a,b``, ``--robot @lab`` with ``lab = ["fetch1", "fetch2"]`` in
``~/.config/fetchsync/robots.toml`` (or under ``$XDG_CONFIG_HOME``), and the same
in ``FETCHSYNC_ROBOT``/``FETCH_ROBOT``. The file may also give a robot its own
remote workspace, which then counts as that robot's ``--remote-workspace``::

    lab = ["fetch1", "fetch2"]

    [robots.fetch2]
    remote_workspace = "~/melodic_ws"

Running a verb on several robots is :mod:`fetchsync.cli.fleet`.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from fetchsync.errors import ConfigError, UsageError

SETTINGS_TABLE = "robots"
"""The table of robots.toml holding per-robot settings (so no group is called that)."""

ROBOT_KEYS = frozenset({"remote_workspace"})

FLEET_VERBS = "push, run, watch, create-account, workspace-status and snapshot"
"""The verbs that take several robots, as the refusal of the others names them."""


def groups_file(environ: Mapping[str, str] = os.environ) -> Path:
    """``$XDG_CONFIG_HOME/fetchsync/robots.toml``, else ``~/.config/fetchsync/robots.toml``."""
    base = environ.get("XDG_CONFIG_HOME", "").strip()
    if not base:
        home = environ.get("HOME", "").strip() or os.path.expanduser("~")
        base = os.path.join(home, ".config")
    return Path(base) / "fetchsync" / "robots.toml"


def _load(environ: Mapping[str, str]) -> dict[str, Any]:
    """robots.toml as a dict ({} when there is none); a one-line error when it is unreadable."""
    path = groups_file(environ)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return {}
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc.strerror or exc}") from exc
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # Python 3.10
        try:
            import tomli as tomllib
        except ModuleNotFoundError:
            raise ConfigError(
                f"reading {path} needs Python 3.11 or the tomli package", hint="pip install tomli"
            ) from None
    try:
        table: dict[str, Any] = tomllib.loads(data.decode("utf-8"))
        return table
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from exc


def groups(*, environ: Mapping[str, str] = os.environ) -> dict[str, list[str]]:
    """The named groups of robots.toml: ``name = ["robot", ...]``."""
    path = groups_file(environ)
    out: dict[str, list[str]] = {}
    for name, value in _load(environ).items():
        if name == SETTINGS_TABLE:
            continue
        if not isinstance(value, list) or not all(isinstance(v, str) and v.strip() for v in value):
            raise ConfigError(f"{path}: group {name!r} must be a list of robot names")
        out[name] = [v.strip() for v in value]
    return out


def robot_settings(robot: str, *, environ: Mapping[str, str] = os.environ) -> dict[str, str]:
    """What robots.toml's ``[robots.NAME]`` says of ``robot`` ({} when nothing)."""
    data = _load(environ)
    table = data.get(SETTINGS_TABLE, {})
    path = groups_file(environ)
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [{SETTINGS_TABLE}] must be a table of robots")
    mine = table.get(robot, {})
    if not isinstance(mine, dict):
        raise ConfigError(f"{path}: [{SETTINGS_TABLE}.{robot}] must be a table")
    unknown = set(mine) - ROBOT_KEYS
    if unknown or not all(isinstance(v, str) and v.strip() for v in mine.values()):
        raise ConfigError(
            f"{path}: [{SETTINGS_TABLE}.{robot}] takes {', '.join(sorted(ROBOT_KEYS))} "
            "(a string)" + (f", not {', '.join(sorted(unknown))}" if unknown else "")
        )
    return {k: v.strip() for k, v in mine.items()}


def expand(
    value: str, *, source: str = "--robot", environ: Mapping[str, str] = os.environ
) -> list[str]:
    """The robots ``value`` names: comma-separated names and ``@group``s, in order, each once."""
    names: list[str] = []
    known: dict[str, list[str]] | None = None
    for word in (w.strip() for w in value.split(",")):
        if not word:
            continue
        if word.startswith("@"):
            if known is None:
                known = groups(environ=environ)
            members = known.get(word[1:])
            if members is None:
                listed = ", ".join("@" + g for g in sorted(known)) or "none"
                raise ConfigError(
                    f"unknown group {word} (from {source}); known groups in "
                    f"{groups_file(environ)}: {listed}"
                )
            names.extend(members)
        else:
            names.append(word)
    unique = list(dict.fromkeys(names))
    if not unique:
        raise ConfigError(f"no robot named (from {source})")
    return unique


def one_robot(value: str, source: str, *, environ: Mapping[str, str] = os.environ) -> str:
    """For verbs that take one robot: the one ``value`` names, or a one-line refusal (exit 2)."""
    names = expand(value, source=source, environ=environ)
    if len(names) > 1:
        raise UsageError(
            f"several robots ({', '.join(names)}, from {source}): only {FLEET_VERBS} "
            "take several; give one robot"
        )
    return names[0]
