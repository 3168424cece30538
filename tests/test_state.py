"""The laptop's state (fetchsync.sync.state): what a process that ends leaves for the next."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from fetchsync.sync.state import State, Synced

WRITER = """
import os, sys
from pathlib import Path
from fetchsync.sync.state import State, Synced
state = State(Path(sys.argv[1]))
state.commit(upserts=[("f%d" % i, Synced("f", 0o644, "%032x" % i, "", i), None) for i in range(500)],
             meta={"gen": "7"})
os._exit(0)  # as the CLI ends: no collector, no interpreter teardown
"""


def test_what_a_process_committed_is_there_for_the_next_even_unclosed(tmp_path: Path) -> None:
    """A process that ends without closing the state (killed after its commit) leaves
    every row and the generation for the next opening."""
    path = tmp_path / "s.sqlite"
    subprocess.run([sys.executable, "-c", WRITER, str(path)], check=True)
    state = State(path)
    try:
        entries = state.entries()
        assert len(entries) == 500 and entries["f42"] == Synced("f", 0o644, "%032x" % 42, "", 42)
        assert state.get("gen") == "7"
    finally:
        state.close()
