"""The one exception tree of fetchsync.

Every error a user can cause or meet is a :class:`FetchsyncError`; the CLI
turns it into a one-line message and an exit code, never a traceback.
Third-party and OS exceptions are mapped at the boundary with ``raise ... from``.

    FetchsyncError               (exit code 1)
    ├── ConfigError            2 bad or missing configuration (robot, user, paths)
    ├── UsageError             2 bad input on the command line
    ├── TransportError         3 the link to the robot
    │   ├── ConnectError         could not connect / authenticate
    │   │   └── HostKeyError     unknown or changed host key
    │   └── LinkLostError        the link died mid-session (timeout, reset)
    ├── RemoteError            4 the robot-side endpoint reported a failure
    ├── SyncError              5 a push or pull could not complete
    │   ├── ConflictError      6 --strict and the robot holds edits we have not seen
    │   ├── MassDeletionError    a push would delete most of the robot's files
    │   └── StateError           the laptop's last-synced state cannot be opened
    ├── ProtocolError          7 the peer spoke something we do not understand
    │   ├── PathError            a path on the wire is not a relative path inside the root
    │   └── DeltaError           a delta does not apply to its base
    └── AbortedError           1 the user declined a confirmation

``FetchsyncError`` and the ``ProtocolError`` branch are defined in
:mod:`fetchsync.protocol.errors` (standard library only: it runs on the robot too)
and re-exported here, so the tree has one root on both ends.
"""

from __future__ import annotations

from fetchsync.protocol.errors import DeltaError, FetchsyncError, PathError, ProtocolError


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


class MassDeletionError(SyncError):
    """A push would delete most of the robot's files; nothing was sent."""


class StateError(SyncError):
    """The laptop's state cannot be opened (not damage: that is set aside and rebuilt)."""


class AbortedError(FetchsyncError):
    exit_code = 1


__all__ = [
    "AbortedError",
    "ConfigError",
    "ConflictError",
    "ConnectError",
    "DeltaError",
    "FetchsyncError",
    "HostKeyError",
    "LinkLostError",
    "MassDeletionError",
    "PathError",
    "ProtocolError",
    "RemoteError",
    "StateError",
    "SyncError",
    "TransportError",
    "UsageError",
]
