"""paramiko, imported without ``invoke`` unless an ssh config needs it.

paramiko's ``config`` module imports ``invoke`` (a dependency of paramiko)
at import time, only to run the commands of ``Match exec`` lines: ~0.15 s of
every call that connects, for a feature few configs use. :func:`load`
imports paramiko with ``invoke`` held back; :func:`needs_exec` gives it back
to paramiko for a config that has such a line, before that config is read.
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
    try:
        return importlib.import_module("paramiko")
    finally:
        if held_back and sys.modules.get("invoke", False) is None:
            del sys.modules["invoke"]


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
