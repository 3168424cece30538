"""Errors of the protocol layer (standard library only; runs on the robot)."""


class ProtocolError(Exception):
    """The peer sent something that breaks the wire protocol.

    A broken transport or a malformed frame is an exception; a failure on one
    file is data in a response, never this.
    """

    exit_code = 7


class PathError(ProtocolError):
    """A path on the wire is not relative, normalised and inside the root."""


class DeltaError(ProtocolError):
    """A delta does not apply to the base it was made for."""
