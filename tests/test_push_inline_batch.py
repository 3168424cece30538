"""A round's only batch, when small (a save, an edit), is packed and sent on the caller's
thread: no packer and sender threads are started for it (their starts and hand-overs
were ~0.8 ms of a wifi save's 3 ms on the laptop, bench/saveab.py). A larger only
batch, and every batch of a round of several, still goes through the threads, whose
caller checks the link while a send is blocked (engine._Batcher._stalled).

In-process pushes to the built-in ``local`` robot (the real endpoint over pipes).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Iterator

import pytest
from helpers import local_env, tree_of

from fetchsync.sync import engine


@pytest.fixture
def syncer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[engine.Syncer]:
    for k, v in local_env(tmp_path).items():
        monkeypatch.setenv(k, v)
    from fetchsync.config import resolve_target
    from fetchsync.link.connection import Connection
    from fetchsync.link.session import open_transport
    from fetchsync.protocol.ignore import IgnoreRules
    from fetchsync.sync.state import open_state

    target = resolve_target()
    transport = open_transport(target, persistent=False)
    conn = Connection.open(transport)
    s = engine.Syncer(
        conn,
        open_state(target),
        local_root=os.path.join(target.workspace, "src"),
        remote_workspace=target.remote_workspace,
        rules=IgnoreRules.build(),
    )
    try:
        yield s
    finally:
        conn.close()
        transport.close()


@pytest.fixture
def started(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The names of the threads the engine starts from now on."""
    names: list[str] = []
    real = threading.Thread.start

    def start(self: threading.Thread) -> None:
        names.append(self.name)
        real(self)

    monkeypatch.setattr(threading.Thread, "start", start)
    return names


def _src(tmp_path: Path) -> Path:
    return tmp_path / "ws" / "src"


def _robot(tmp_path: Path) -> Path:
    return tmp_path / "robot-home" / "robot_ws" / "src"


def test_a_save_is_sent_without_the_batchers_threads(tmp_path, syncer, started):
    syncer.push()
    started.clear()
    node = _src(tmp_path) / "my_pkg/src/node.cpp"
    for i in range(3):
        node.write_text(node.read_text() + f"// save {i}\n")
        report = syncer.push_paths({"my_pkg/src/node.cpp"})
        assert report.files == 1
        assert (_robot(tmp_path) / "my_pkg/src/node.cpp").read_bytes() == node.read_bytes()
    assert not [n for n in started if n in ("fetchsync-packer", "fetchsync-sender")], started


def test_a_larger_only_batch_and_a_round_of_several_go_through_the_threads(
    tmp_path, syncer, started
):
    syncer.push()
    big = _src(tmp_path) / "my_pkg/big.bin"
    big.write_bytes(os.urandom(engine.INLINE_BATCH + 1))  # one batch, over the limit
    started.clear()
    assert syncer.push_paths({"my_pkg/big.bin"}).files == 1
    assert "fetchsync-sender" in started
    many = _src(tmp_path) / "my_pkg/many"
    many.mkdir()
    for i in range(8):  # more than the first batch's 1 MiB: several batches
        (many / f"f{i}.bin").write_bytes(os.urandom(200_000))
    started.clear()
    syncer.push()
    assert "fetchsync-sender" in started
    assert tree_of(_src(tmp_path)) == tree_of(_robot(tmp_path))
