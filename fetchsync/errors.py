"""The one exception tree of fetchsync.

Every error a user can cause or meet is a :class:`FetchsyncError`; the CLI
turns it into a one-line message and an exit code, never a traceback.
Third-party and OS exceptions are mapped at the boundary with ``raise ... from``.

    FetchsyncError
    ├── ConfigError            bad or missing configuration (robot, user, paths)
    ├── UsageError             bad input on the command line
    ├── TransportError         the link to the robot
    │   ├── ConnectError       could not connect / authenticate
    │   │   └── HostKeyError   unknown or changed host key
    │   └── LinkLostError      the link died mid-session (timeout, reset)
    ├── ProtocolError          the peer spoke something we do not understand
    ├── RemoteError            the robot-side endpoint reported a failure
    ├── SyncError              a push or pull could not complete
    │   └── ConflictError      --strict and the robot holds edits we have not seen
    └── AbortedError           the user declined a confirmation

The robot-side code (``fetchsync.protocol``) has its own small tree in
``fetchsync.protocol.errors`` (it must run with only the standard library);
``ProtocolError`` is shared by both.
"""

from __future__ import annotations

from fetchsync.protocol.errors import ProtocolError


class FetchsyncError(Exception):
    """Base of all fetchsync errors. ``exit_code`` is what the CLI exits with."""

    exit_code = 1

    def __init__(self, message: str, *, hint: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.hint = hint

    def __str__(self) -> str:
        if self.hint:
            return f"{self.message} ({self.hint})"
        return self.message


class ConfigError(FetchsyncError):
    exit_code = 2


class UsageError(FetchsyncError):
    exit_code = 2


class TransportError(FetchsyncError):
    exit_code = 3


class ConnectError(TransportError):
    pass


class HostKeyError(ConnectError):
    pass


class LinkLostError(TransportError):
    pass


class RemoteError(FetchsyncError):
    exit_code = 4


class SyncError(FetchsyncError):
    exit_code = 5


class ConflictError(SyncError):
    exit_code = 6


class AbortedError(FetchsyncError):
    exit_code = 1


__all__ = [
    "AbortedError",
    "ConfigError",
    "ConflictError",
    "ConnectError",
    "FetchsyncError",
    "HostKeyError",
    "LinkLostError",
    "ProtocolError",
    "RemoteError",
    "SyncError",
    "TransportError",
    "UsageError",
]
