"""The root of fetchsync's one exception tree, and the protocol layer's errors.

Standard library only, Python 3.6: this module runs on the robot too. The rest of
the tree (configuration, transport, sync, ...) is in :mod:`fetchsync.errors`, which
re-exports these; the CLI maps every :class:`FetchsyncError` to one line and its
``exit_code``, so a robot's malformed answer needs no handling of its own.
"""

from typing import Optional


class FetchsyncError(Exception):
    """Base of all fetchsync errors. ``exit_code`` is what the CLI exits with."""

    exit_code = 1

    def __init__(self, message: str, *, hint: "Optional[str]" = None) -> None:
        super().__init__(message)
        self.message = message
        self.hint = hint

    def __str__(self) -> str:
        if self.hint:
            return "%s (%s)" % (self.message, self.hint)
        return self.message


class ProtocolError(FetchsyncError):
    """The peer sent something that breaks the wire protocol.

    A broken transport or a malformed frame is an exception; a failure on one
    file is data in a response, never this.
    """

    exit_code = 7


class PathError(ProtocolError):
    """A path on the wire is not relative, normalised and inside the root."""


class DeltaError(ProtocolError):
    """A delta does not apply to the base it was made for."""
