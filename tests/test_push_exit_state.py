"""A one-shot push exits without checkpointing its state (fetchsync.cli._ONE_SHOT): the
state's writes are committed in SQLite's log and the next call reads them from it."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from click.testing import CliRunner
from helpers import fetchsync, local_env, report


def _state(tmp_path: Path) -> Path:
    (db,) = (tmp_path / "state").rglob("*.sqlite")
    return db


def test_a_push_exits_with_its_state_in_the_log_and_the_next_push_reads_it(
    tmp_path: Path,
) -> None:
    env = local_env(tmp_path)
    first = report(fetchsync("push", "--json", env=env))
    assert first["ok"] and first["files"] == 5
    db = _state(tmp_path)
    wal = Path(f"{db}-wal")
    # the exit did not checkpoint: the push's commits are in the log, not yet in the file
    assert wal.exists() and wal.stat().st_size > 0
    # a reader sees them (as the next push does), from the log
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as reader:
        (count,) = reader.execute("SELECT count(*) FROM entries").fetchone()
    assert count >= 5
    # and the next push finds nothing to send: it read what the first one recorded
    second = report(fetchsync("push", "--json", env=env))
    assert second["ok"] and second["files"] == 0 and second["bytes_sent"] < 2000


def test_a_push_run_in_process_closes_its_state(tmp_path: Path, monkeypatch) -> None:
    """Not at the end of a process (click's runner, as the tests and the fleet call it):
    the database is closed, its log checkpointed."""
    env = local_env(tmp_path)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    from fetchsync.cli import cli

    result = CliRunner().invoke(cli, ["push", "--json"], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    wal = Path(f"{_state(tmp_path)}-wal")
    assert not wal.exists() or wal.stat().st_size == 0
