"""Where fetchsync's own things are, by name only: the runtime directory's path (the
sockets of connection masters, agents and residents), the ``local`` robot's home, and
which robot (and login) a target's state and agent belong to.

Light on purpose (``os`` and ``pathlib`` only): the console entry's fast path of a
plain push (:mod:`fetchsync.agent.quick`) finds a resident's socket through it without
importing the link's modules (logging, dataclasses, threads). Nothing here creates or
checks a directory: :func:`fetchsync.link.mux.runtime_dir` does, before a socket is
made there; a socket merely asked is trusted only for its peer's uid.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from fetchsync.config import Target

MAX_SOCKET_PATH = 100  # AF_UNIX paths are limited to 108 bytes on Linux


def runtime_path(*, short: bool) -> Path:
    """``$XDG_RUNTIME_DIR/fetchsync``, or with ``short`` or without that variable
    ``fetchsync-UID`` in the temporary directory (``$TMPDIR``, else ``/tmp``)."""
    base = os.environ.get("XDG_RUNTIME_DIR")
    if base and not short:
        return Path(base) / "fetchsync"
    import tempfile  # ~3-7 ms of a push's start when site has not imported it: only here

    return Path(tempfile.gettempdir()) / f"fetchsync-{os.getuid()}"


def robot_id(target: Target) -> str:
    """Which robot (and login) a target's state and agent belong to."""
    if target.is_local:
        return f"local:{local_robot_home()}"
    return f"{target.user or ''}@{target.host}"


def local_robot_home() -> Path:
    """The home directory of the built-in ``local`` robot.

    The ``local`` robot is a directory on this machine that stands in for a
    robot's home: ``~`` in a remote path means this directory.
    """
    env = os.environ.get("FETCHSYNC_LOCAL_ROBOT_HOME")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(
        os.path.expanduser("~"), ".local", "share"
    )
    return Path(base) / "fetchsync" / "local-robot"
