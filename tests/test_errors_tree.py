"""One exception tree: every error fetchsync raises on purpose is a FetchsyncError,
the robot-side ones included, so the CLI maps each to one line and its exit code."""

from __future__ import annotations

import inspect

import fetchsync.errors as E
import fetchsync.protocol.errors as PE
from fetchsync.protocol.store import StoreError


def test_one_root_on_both_ends() -> None:
    assert E.FetchsyncError is PE.FetchsyncError
    assert E.ProtocolError is PE.ProtocolError
    for module in (E, PE):
        for name, obj in vars(module).items():
            if inspect.isclass(obj) and issubclass(obj, BaseException):
                assert issubclass(obj, E.FetchsyncError), name
    assert issubclass(StoreError, E.ProtocolError)


def test_exit_codes() -> None:
    assert E.ProtocolError("x").exit_code == 7
    assert PE.PathError("x").exit_code == 7
    assert E.MassDeletionError("x").exit_code == E.StateError("x").exit_code == 5
    assert str(E.ProtocolError("bad", hint="upgrade the robot")) == "bad (upgrade the robot)"


def test_the_engine_and_state_raise_the_trees_errors() -> None:
    from fetchsync.sync import engine, state

    assert engine.MassDeletionError is E.MassDeletionError
    assert state.StateError is E.StateError
