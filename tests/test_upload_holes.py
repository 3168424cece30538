"""A large file travels in UPLOAD pieces (engine.BIG, engine.PIECE); a piece ending in a
run of zeros leaves a hole at the part's end. The part must then reach the piece's end
(its offset plus its length), not the piece's length: the part was cut back to 8 MiB,
its content lost, and such a file (a disk image, a preallocated log, a map with a zero
tail) failed every push with 'uploaded content does not match its hash'."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from helpers import make_workspace, tree_of

from fetchsync.link.connection import Connection
from fetchsync.link.ssh import SSHTransport
from fetchsync.protocol import hashing
from fetchsync.protocol import messages as M
from fetchsync.protocol.store import Store
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State

ALG = "blake2b-128"
MiB = 1 << 20


def content() -> bytes:
    """Larger than BIG: random bytes, then zeros through several whole pieces, then a
    piece ending in zeros, then a few bytes."""
    return (
        os.urandom(sync.PIECE + MiB)
        + bytes(sync.BIG + sync.PIECE - MiB)
        + os.urandom(MiB)
        + bytes(2 * MiB)
        + b"tail\n"
    )


def test_pieces_ending_in_zeros_keep_the_parts_earlier_content(tmp_path: Path) -> None:
    data = content()
    store = Store(str(tmp_path / "ws"), algorithm=ALG)
    store.lock()
    try:
        for off in range(0, len(data), sync.PIECE):
            piece = data[off : off + sync.PIECE]
            op = M.Op(M.UPLOAD, "", upload="u1", size=off, blob=(0, len(piece)))
            assert store.apply([op], piece)[0].ok
        op = M.Op(
            M.WRITE,
            "disk.img",
            expect=M.ABSENT,
            mode=0o644,
            hash=hashing.digest(ALG, data).hex(),
            size=len(data),
            source=M.SRC_UPLOAD,
            upload="u1",
        )
        result = store.apply([op], b"")[0]
        assert result.ok, result
    finally:
        store.unlock()
    landed = Path(store.root) / "disk.img"
    assert landed.read_bytes() == data
    assert os.stat(landed).st_blocks * 512 < len(data) // 2  # the zeros stayed holes


@pytest.mark.ssh
def test_a_large_file_with_runs_of_zeros_is_pushed(
    ssh_home, remote_dir: Path, tmp_path: Path
) -> None:
    make_workspace(tmp_path / "ws")
    src = tmp_path / "ws/src"
    (src / "maps").mkdir()
    (src / "maps/disk.img").write_bytes(content())
    conn = Connection.open(SSHTransport.connect("robot", connect_timeout=10.0))
    state = State(tmp_path / "state.sqlite")
    try:
        s = sync.Syncer(
            conn,
            state,
            local_root=str(src),
            remote_workspace=str(remote_dir),
            rules=sync.build_rules(),
        )
        report = s.push()
        assert report.errors == [] and report.conflicts == []
    finally:
        conn.close()
        state.close()
    assert tree_of(src) == tree_of(remote_dir / "src")
