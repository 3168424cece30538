"""Durability of a save: a batch of one new content fsyncs its temporary, no syncfs first.

A watch agent's save (one file written in place, one new file) reaches the robot as a
batch of one write; the endpoint makes that temporary durable with an ``fsync`` of its
descriptor (store.FSYNC_EACH) instead of a ``syncfs`` of the whole file system before
the rename: on a journaled ext4 that is ~1 ms of a wifi save's critical path, and a
syncfs would wait for whatever else the robot writes. The rules of
tests/test_durability.py still hold, checked the same ways: the syscall order under
strace (the rename after a sync of that temporary's content, the reply after a sync of
the rename), and a power cut right after the push's success on a loop-device ext4.
"""

from __future__ import annotations

from pathlib import Path

import test_durability as td
from helpers import local_env, tree_of
from test_durability import cut_power, local_src, push, robot_src, traced_push

env = td.env  # the fixtures: the local robot's environment, a loop-device ext4
disk = td.disk


def _save(src: Path, n: int) -> None:
    """An editor's in-place save of one file: new bytes at its end."""
    data = src / "my_pkg/data.txt"
    data.write_text(data.read_text() + f"// save {n}\n")


def test_a_save_fsyncs_its_temporary_before_the_rename_and_syncs_before_its_reply(env, tmp_path):
    push(env)
    src = local_src(env)
    for n, change in enumerate(
        (
            lambda: _save(src, 1),
            lambda: (src / "my_pkg/src/new.cpp").write_text("// a new file alone\n"),
        )
    ):
        change()
        _r, v = traced_push(env, tmp_path / f"trace{n}")
        assert v.violations == []
        assert v.temp_renames == 1
        # one syncfs (after the rename, before the reply): the content went by fsync
        assert v.syncfs == 1 and v.syncs >= 2
        assert tree_of(src) == tree_of(robot_src(env))


def test_a_batch_of_two_writes_still_syncs_the_file_system_before_the_renames(env, tmp_path):
    push(env)
    src = local_src(env)
    _save(src, 1)
    (src / "my_pkg/src/node.cpp").write_text("// edited too\n")
    _r, v = traced_push(env, tmp_path / "trace")
    assert v.violations == [] and v.temp_renames == 2 and v.syncfs == 2
    assert tree_of(src) == tree_of(robot_src(env))


def test_power_cut_right_after_a_save_keeps_it(tmp_path, disk):
    """Each push is one write (a save, a new file alone), cut right after its success."""
    env = local_env(tmp_path, FETCHSYNC_LOCAL_ROBOT_HOME=str(disk.mount / "robot"))
    src = local_src(env)
    push(env)
    changes = (
        lambda: _save(src, 1),
        lambda: (src / "my_pkg/src/new.cpp").write_text("// a new file alone\n"),
        lambda: _save(src, 3),
    )
    for n, change in enumerate(changes):
        change()
        disk.settle()
        r = push(env)
        assert r["files"] == 1
        assert cut_power(disk, tmp_path, f"cut{n}") == tree_of(src), f"push {n} lost data"
