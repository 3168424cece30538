"""The environment handed to the processes a call leaves running.

A call may be given secrets in its environment (FETCHSYNC_SUDO_PASSWORD for a build's
rosdep or a snapshot, the account passwords of create-account: a script exports them
for its session). The processes a plain call leaves behind, detached and for minutes
(the connection master, the resident), need none of them, and a secret must not sit in
the environment of another process.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Mapping


def is_secret(name: str) -> bool:
    """Whether the environment variable ``name`` holds one of fetchsync's secrets."""
    return name.startswith("FETCHSYNC_") and "PASSWORD" in name


def inheritable(environ: Mapping[str, str]) -> dict[str, str]:
    """``environ`` without fetchsync's secrets: for a process that outlives the call."""
    return {k: v for k, v in environ.items() if not is_secret(k)}
