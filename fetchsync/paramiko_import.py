"""paramiko, imported without ``invoke`` unless an ssh config needs it.

paramiko's ``config`` module imports ``invoke`` (a dependency of paramiko)
at import time, only to run the commands of ``Match exec`` lines: ~0.15 s of
every call that connects, for a feature few configs use. :func:`load`
imports paramiko with ``invoke`` held back; :func:`needs_exec` gives it back
to paramiko for a config that has such a line, before that config is read.

paramiko (>= 4) also imports ``importlib.metadata`` for its own version
string alone, ~15-20 ms more: :func:`load` hands it the version read from
its ``dist-info``, and leaves ``importlib.metadata`` to be imported by whoever
needs it. Without that file, paramiko imports it as usual.
"""

from __future__ import annotations

import importlib
import os
import re
import sys
from types import ModuleType

_MATCH_EXEC = re.compile(rb"^\s*match\b[^\n#]*\bexec\b", re.IGNORECASE | re.MULTILINE)


def load() -> ModuleType:
    """The paramiko module, imported now if it was not (without ``invoke``)."""
    if "paramiko" in sys.modules:
        return sys.modules["paramiko"]
    held_back = "invoke" not in sys.modules
    if held_back:
        sys.modules["invoke"] = None  # type: ignore[assignment]  # import invoke -> ImportError
    version = None if "importlib.metadata" in sys.modules else _installed_version("paramiko")
    if version is not None:
        stand_in = ModuleType("importlib.metadata")
        stand_in.version = lambda name: version if name == "paramiko" else _real_version(name)  # type: ignore[attr-defined]
        stand_in.fetchsync_stand_in = True  # type: ignore[attr-defined]
        sys.modules["importlib.metadata"] = stand_in
    try:
        return importlib.import_module("paramiko")
    finally:
        if held_back and sys.modules.get("invoke", False) is None:
            del sys.modules["invoke"]
        if version is not None:
            if sys.modules.get("importlib.metadata") is stand_in:
                del sys.modules["importlib.metadata"]
            if getattr(importlib, "metadata", None) is stand_in:
                del importlib.metadata  # type: ignore[attr-defined]


def _real_version(name: str) -> str:
    if getattr(sys.modules.get("importlib.metadata"), "fetchsync_stand_in", False):
        del sys.modules["importlib.metadata"]
    import importlib.metadata

    return importlib.metadata.version(name)


def _installed_version(dist: str) -> str | None:
    """``dist``'s version from the METADATA beside the package that ``import dist`` would
    load (the first directory of sys.path holding it), or None."""
    for entry in sys.path:
        folder = entry or "."
        if not os.path.isfile(os.path.join(folder, dist, "__init__.py")):
            continue
        try:
            infos = [n for n in os.listdir(folder) if n.startswith(dist + "-") and n.endswith(".dist-info")]
            if len(infos) != 1:
                return None  # none, or several: leave it to importlib.metadata
            with open(os.path.join(folder, infos[0], "METADATA"), "rb") as fh:
                for line in fh:
                    if line.startswith(b"Version:"):
                        return line[8:].strip().decode("ascii")
                    if not line.strip():
                        return None  # end of the headers
        except (OSError, UnicodeDecodeError):
            return None
        return None
    return None


def needs_exec(path: str | os.PathLike[str]) -> None:
    """Let paramiko run ``Match exec`` if the config at ``path`` has one (else nothing)."""
    try:
        with open(path, "rb") as fh:
            text = fh.read()
    except OSError:
        return  # the caller's own read reports it
    if not _MATCH_EXEC.search(text):
        return
    config = importlib.import_module("paramiko.config")
    if getattr(config, "invoke", None) is None:
        try:
            config.invoke = importlib.import_module("invoke")  # type: ignore[attr-defined]
        except ImportError:
            pass  # paramiko raises its own error on the Match exec line
