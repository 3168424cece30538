"""The state's rows kept between pushes by one connection (State.entries, signed_paths):
what they answer is what a fresh read of the table answers, whoever committed since."""

from __future__ import annotations

import random
import subprocess
import sys
from pathlib import Path

import pytest

from fetchsync.sync.state import State, Synced

OTHER = """
import sys
from pathlib import Path
from fetchsync.sync.state import State, Synced
state = State(Path(sys.argv[1]))
state.commit(upserts=[("a/other", Synced("f", 0o600, "0" * 32, "", 3, 1, 2, 3), b"sig")],
             deletes=["a/0"])
state.close()
"""


def _fresh(path: Path) -> tuple[dict[str, Synced], set[str]]:
    other = State(path)
    try:
        return other.entries(), other.signed_paths()
    finally:
        other.close()


def _synced(rng: random.Random) -> Synced:
    kind = rng.choice("fffdl")
    return Synced(
        kind,
        rng.choice([0o644, 0o755, 0o600]),
        "%032x" % rng.randrange(4) if kind == "f" else "",
        "t%d" % rng.randrange(3) if kind == "l" else "",
        rng.randrange(3),
        rng.randrange(3),
        rng.randrange(3),
        rng.randrange(3),
    )


def _step(rng: random.Random, state: State) -> None:
    paths = ["a/%d" % i for i in range(12)]
    roll = rng.random()
    if roll < 0.03:
        state.reset()
        return
    upserts = [
        (p, _synced(rng), rng.choice([None, None, b"sig%d" % rng.randrange(9)]))
        for p in rng.sample(paths, rng.randrange(5))
    ]
    deletes = rng.sample(paths, rng.randrange(3))
    if roll < 0.06:
        state.commit(upserts=upserts, replace_all=True, meta={"gen": str(rng.randrange(9))})
    elif roll < 0.1:
        state.commit(meta={"deletions": "1 2"})  # meta alone
    else:
        state.commit(upserts=upserts, deletes=deletes)


@pytest.mark.parametrize("seed", range(6))
def test_kept_rows_answer_what_a_fresh_read_does(tmp_path: Path, seed: int) -> None:
    """A long-lived connection (the resident's) and others committing in any order: after
    every commit, its entries() and signed_paths() equal a new connection's read; what
    it hands out is the caller's to change."""
    rng = random.Random(seed)
    path = tmp_path / "s.sqlite"
    kept = State(path)
    others = [State(path) for _ in range(2)]
    try:
        for _ in range(150):
            writer = kept if rng.random() < 0.5 else rng.choice(others)
            _step(rng, writer)
            want_rows, want_signed = _fresh(path)
            if rng.random() < 0.5:  # either may be asked first, or alone
                assert kept.entries() == want_rows
            if rng.random() < 0.5:
                assert kept.signed_paths() == want_signed
            if rng.random() < 0.3:
                kept.entries().clear()  # the caller's own: the kept rows do not change
                kept.signed_paths().clear()
            if rng.random() < 0.1:
                kept.entries()
                kept.signed_paths()
                assert kept.entries() == want_rows and kept.signed_paths() == want_signed
    finally:
        for s in [kept, *others]:
            s.close()


def test_another_process_commit_is_seen(tmp_path: Path) -> None:
    """A commit by another process (a push made without the resident) is read again."""
    path = tmp_path / "s.sqlite"
    kept = State(path)
    try:
        kept.commit(upserts=[("a/0", Synced("f", 0o644, "1" * 32, "", 1, 1, 1, 1), b"s")])
        assert set(kept.entries()) == {"a/0"} and kept.signed_paths() == {"a/0"}
        subprocess.run([sys.executable, "-c", OTHER, str(path)], check=True)
        assert kept.entries() == _fresh(path)[0]
        assert set(kept.entries()) == {"a/other"}
        assert kept.signed_paths() == {"a/other"}
        # its own commits after that go on from the rows read again
        kept.commit(upserts=[("a/1", Synced("d", 0o755, "", ""), None)])
        assert kept.entries() == _fresh(path)[0] and kept.signed_paths() == _fresh(path)[1]
    finally:
        kept.close()


def test_unchanged_rows_are_not_read_again(tmp_path: Path) -> None:
    """What it is for: a push after a push of this same connection reads no row (only
    the data version), its own commit applied to what it kept."""
    path = tmp_path / "s.sqlite"
    kept = State(path)
    try:
        kept.commit(upserts=[(f"a/{i}", Synced("d", 0o755, "", ""), None) for i in range(9)])
        kept.entries()
        kept.signed_paths()
        kept.commit(upserts=[("a/x", Synced("f", 0o644, "2" * 32, "", 1, 1, 1, 1), b"s")])
        statements: list[str] = []
        kept.db.set_trace_callback(statements.append)
        rows, signed = kept.entries(), kept.signed_paths()
        kept.db.set_trace_callback(None)
        assert not [s for s in statements if "FROM entries" in s], statements
        assert (rows, signed) == _fresh(path)
    finally:
        kept.close()


def test_a_failed_commit_drops_what_was_kept(tmp_path: Path) -> None:
    """A commit that fails (here: a value SQLite cannot hold) leaves the table as it was;
    the kept rows are read again, not taken from the failed commit."""
    path = tmp_path / "s.sqlite"
    kept = State(path)
    try:
        kept.commit(upserts=[("a/0", Synced("d", 0o755, "", ""), None)])
        kept.entries()
        with pytest.raises(OverflowError):
            kept.commit(upserts=[("a/1", Synced("f", 0o644, "3" * 32, "", 1, 1, 1, 1 << 70), None)])
        assert kept.entries() == _fresh(path)[0] == {"a/0": Synced("d", 0o755, "", "")}
    finally:
        kept.close()
