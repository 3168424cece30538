"""``bench/scale.py`` at a small size runs to the end: push, no-op push, watch start-up and one edit.

The reduced, CI form of the 100,000-file scale benchmark (issue 5): 1,000
files (several batches each way) over the real sshd. It asserts that every step completes, that the
robot's tree equals the local one after each, and that the table with the
targets prints; never a timing or a memory figure (a shared CI machine makes
them meaningless). The full run is by hand: see bench/README.md.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from helpers import run_bench


@pytest.mark.slow
@pytest.mark.ssh
def test_scale_small_completes_and_verifies(tmp_path: Path) -> None:
    stdout, raw = run_bench("scale.py", "--files", "1000", "--size-mb", "6", tmp_path=tmp_path)
    assert (
        "| step | time | fetchsync peak RSS | robot endpoint peak RSS | target | verdict |"
        in stdout
    )
    assert "verification: PASS" in stdout
    assert raw["failures"] == []
    assert raw["verification"] == {
        "initial push": [],
        "no-op push": [],
        "watch, after one edit": [],
        "watch from empty, after one edit": [],
    }
    assert (
        raw["initial"]["returncode"] == 0 and raw["initial"]["files"] == raw["workspace"]["files"]
    )
    assert raw["noop"]["returncode"] == 0 and raw["noop"]["files"] == 0
    watch = raw["watch"]
    assert watch["status_state"] == "live"
    assert watch["edit_seconds"] is not None
    # the measurements were taken (figures exist), whatever they are
    assert raw["initial"]["client_peak_kib"] > 0 and raw["initial"]["endpoint_peak_kib"] > 0
    assert watch["agent_peak_live_kib"] > 0 and watch["inotify_watches"] > 0
    first = raw["watch_initial"]  # the agent's own first, full sync into an empty robot
    assert first["status_state"] == "live" and first["edit_seconds"] is not None


# What the scale benchmark led to change, tested at a size CI can afford.


def test_state_commit_keeps_a_signature_only_while_the_hash_is_unchanged(tmp_path: Path) -> None:
    """``State.commit`` streams its rows into one upsert (no per-row lookup, no row lists):
    a row without a signature keeps the stored one for the same content, drops it for new."""
    from fetchsync.sync.state import State, Synced

    st = State(tmp_path / "s.sqlite")
    st.commit(
        upserts=[
            ("same", Synced("f", 0o644, "h1", "", 20000, 1, 2, 3), b"SIG-same"),
            ("edited", Synced("f", 0o644, "h2", "", 20000, 1, 2, 3), b"SIG-edited"),
        ]
    )
    # a chmod and a new stat for "same" (content unchanged), new content for "edited"
    st.commit(
        upserts=(
            (p, s, None)
            for p, s in [
                ("same", Synced("f", 0o600, "h1", "", 20000, 5, 6, 7)),
                ("edited", Synced("f", 0o644, "h3", "", 20001, 5, 6, 8)),
                ("new", Synced("d", 0o755, "", "")),
            ]
        )
    )
    assert st.signature("same") == b"SIG-same"
    assert st.signature("edited") is None
    assert st.signed_paths() == {"same"}
    assert st.entries()["same"] == Synced("f", 0o600, "h1", "", 20000, 5, 6, 7)
    assert st.entries()["edited"].hash == "h3"
    st.commit(upserts=[("same", Synced("f", 0o600, "h1", "", 20000), b"SIG-2")], deletes=["new"])
    assert st.signature("same") == b"SIG-2"
    assert sorted(st.entries()) == ["edited", "same"]
    st.close()


def test_the_watcher_does_not_walk_excluded_directories(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A ``.git`` (or any excluded directory) is neither watched nor listed when watches are
    added: watchdog's own walk listed every directory of it (git's 256 object directories)."""
    from fetchsync.agent import watcher as W

    root = tmp_path / "src"
    for pkg in ("a", "b"):
        (root / pkg / "src").mkdir(parents=True)
        for i in range(20):
            (root / pkg / ".git" / "objects" / f"{i:02x}").mkdir(parents=True)
    (root / "a" / "build" / "deep").mkdir(parents=True)
    (root / ".fetchsyncignore").write_text("build/\n")
    listed: list[str] = []
    real = os.scandir

    def scandir(path: object = ".") -> object:
        listed.append(os.fsdecode(path))  # type: ignore[arg-type]
        return real(path)  # type: ignore[arg-type]

    monkeypatch.setattr(W.os, "scandir", scandir)
    w = W.Watcher(str(root), sink=lambda item, at: None)
    w.start()
    try:
        assert not w.degraded
    finally:
        w.stop()
    rel = {os.path.relpath(p, root) for p in listed}
    assert {"a", "a/src", "b", "b/src"} <= rel  # the walk happened
    assert not [p for p in rel if ".git" in p.split(os.sep) or "build" in p.split(os.sep)]
