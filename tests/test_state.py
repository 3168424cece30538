"""The laptop's state (fetchsync.state): what a process that ends leaves for the next."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from fetchsync.state import State, Synced

WRITER = """
import os, sys
from pathlib import Path
from fetchsync.state import State, Synced
state = State(Path(sys.argv[1]))
state.commit(upserts=[("f%d" % i, Synced("f", 0o644, "%032x" % i, "", i), None) for i in range(500)],
             meta={"gen": "7"})
state.close(checkpoint=sys.argv[2] == "1")
os._exit(0)  # as the CLI ends: no collector, no interpreter teardown
"""


@pytest.mark.parametrize("checkpoint", [True, False])
def test_what_a_process_committed_is_there_for_the_next_however_it_closed(tmp_path: Path,
                                                                        checkpoint: bool) -> None:
    """close(checkpoint=False) (the CLI's, just before its exit) leaves the write-ahead log
    uncopied: the next opening still finds every row and the generation."""
    path = tmp_path / "s.sqlite"
    subprocess.run([sys.executable, "-c", WRITER, str(path), "1" if checkpoint else "0"], check=True)
    wal = path.with_name(path.name + "-wal")
    if checkpoint:
        assert not wal.exists() or wal.stat().st_size == 0  # copied into the database
    else:
        assert wal.stat().st_size > 0  # left as it was: no fsync at the end of a push
    state = State(path)
    try:
        entries = state.entries()
        assert len(entries) == 500 and entries["f42"] == Synced("f", 0o644, "%032x" % 42, "", 42)
        assert state.get("gen") == "7"
    finally:
        state.close()
    assert not wal.exists() or wal.stat().st_size == 0  # and that close copied it
