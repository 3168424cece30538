"""Slices: in a burst, files written and closed leave before the burst ends (coalescer.py).

Driven by scripted items and invented times (binary fractions, as in
test_agent_coalescer.py), then once end to end: a watch agent with a real watcher
over the local robot, a burst going on, a file held open half-written in it.
"""

from __future__ import annotations

import functools
import threading
import time
from pathlib import Path
from typing import Any, Iterator

import helpers
import pytest

from fetchsync.agent.coalescer import (
    CLOSED,
    CREATED,
    DELETED,
    MODIFIED,
    MOVED,
    Batch,
    Change,
    Coalescer,
    Rescan,
)


def burst(**kw: float) -> Coalescer:
    """A coalescer whose bursts start at the fourth item (quiet 0.25, burst window 0.5,
    slices a cap apart)."""
    return Coalescer(
        quiet=kw.get("quiet", 0.25),
        cap=kw.get("cap", 4.0),
        burst=int(kw.get("burst", 4)),
        burst_quiet=kw.get("burst_quiet", 0.5),
        slice_every=kw.get("slice_every"),
    )


def f(path: str, kind: str = CREATED) -> Change:
    return Change(path, kind)  # type: ignore[arg-type]


def d(path: str, kind: str = CREATED) -> Change:
    return Change(path, kind, is_dir=True)  # type: ignore[arg-type]


def written(c: Coalescer, path: str, at: float) -> None:
    """A new file as a writer makes it: created, written, closed."""
    for kind in (CREATED, MODIFIED, CLOSED):
        c.add(f(path, kind), at)


def take(c: Coalescer, at: float) -> Batch:
    batch = c.take(at)
    assert batch is not None
    return batch


def test_a_closed_file_leaves_in_a_slice_while_the_burst_goes_on() -> None:
    c = burst(slice_every=0.25)
    written(c, "a", 10.0)
    written(c, "b", 10.0)  # the fourth item: a burst
    assert c.due(10.0) == 0.25  # the slice, quiet after its first close
    assert c.take(10.125) is None
    s = take(c, 10.25)
    assert s.paths == {"a", "b"} and not s.dirs and s.rescan is None and s.sliced
    written(c, "c", 10.375)
    c.add(f("d"), 10.375)  # created, not written yet
    assert c.due(10.375) == 0.25
    assert take(c, 10.625).paths == {"c"}
    # the batch keeps its own windows: 0.5 after its last item, and holds the rest
    assert c.due(10.625) == 0.25
    assert take(c, 10.875).paths == {"d"}
    assert not c.pending


def test_slices_come_at_most_once_per_cap() -> None:
    c = burst(cap=1.0)
    written(c, "a", 10.0)
    written(c, "b", 10.0)
    assert take(c, 10.25).paths == {"a", "b"}
    written(c, "c", 10.375)
    assert c.due(10.375) == 0.5  # the batch's window; the next slice not before 11.25
    assert take(c, 10.875).paths == {"c"}
    slices = []
    for k in range(40):  # a long burst of closed files, one every 1/16 s
        t = 11.0 + k / 16
        while c.due(t) == 0.0:
            batch = c.take(t)
            if batch is not None:
                slices.append((t, batch))
        written(c, f"p{k}", t)
    # a slice a quiet window into each cap, the cap's cut (the rest of its closes) at its end
    assert [t for t, _ in slices] == [11.25, 12.0, 12.25, 13.0, 13.25]
    assert [len(b.paths) for _, b in slices] == [4, 12, 4, 12, 4]


def test_outside_a_burst_there_are_no_slices() -> None:
    c = burst(burst=16)
    c.add(f("tmp"), 10.0)
    c.add(f("tmp", CLOSED), 10.0)  # an editor's temporary, about to be renamed
    assert c.due(10.0) == 0.25  # the batch's quiet window, not a slice
    c.add(f("tmp", MOVED), 10.125)
    c.add(f("file"), 10.125)
    batch = take(c, 10.375)
    assert batch.paths == {"file"}  # the temporary cancelled out: nothing shipped of it


def test_a_file_not_closed_yet_is_never_in_a_slice() -> None:
    c = burst()
    c.add(f("held"), 10.0)
    c.add(f("held", MODIFIED), 10.0)  # half written, still open
    for k in range(8):
        written(c, f"p{k}", 10.0 + k / 8)
        batch = c.take(10.0 + k / 8 + 0.25)
        assert batch is None or "held" not in batch.paths
    c.add(f("held", CLOSED), 11.0)
    assert "held" in take(c, 11.5).paths


def test_a_file_touched_after_its_close_leaves_the_slice() -> None:
    c = burst(slice_every=0.25)
    written(c, "a", 10.0)
    written(c, "b", 10.0)
    c.add(f("a", MODIFIED), 10.125)  # opened again and written: not complete
    assert take(c, 10.25).paths == {"b"}
    assert take(c, 10.625).paths == {"a"}


def test_slices_hold_no_deletion_and_no_directory() -> None:
    c = burst()
    c.add(d("new"), 10.0)
    c.add(f("old.txt", DELETED), 10.0)
    c.add(d("gone", DELETED), 10.0)
    written(c, "new/a", 10.0)
    s = take(c, 10.25)
    assert s.paths == {"new/a"} and not s.dirs
    batch = take(c, 10.5)
    assert batch.dirs == {"new", "gone"} and batch.paths == {"old.txt"}


def test_a_new_directory_is_still_rescanned_after_its_files_were_sliced() -> None:
    c = burst()
    c.add(d("pkg"), 10.0)
    for k in range(4):
        written(c, f"pkg/f{k}", 10.0)  # below a directory to rescan: subsumed in the batch
    assert take(c, 10.25).paths == {f"pkg/f{k}" for k in range(4)}
    batch = take(c, 10.5)
    assert batch.dirs == {"pkg"}  # what no event named below it is found by the rescan


def test_a_sliced_file_deleted_later_is_deleted_on_the_robot() -> None:
    c = burst()
    written(c, "a", 10.0)
    written(c, "b", 10.0)
    assert take(c, 10.25).paths == {"a", "b"}
    c.add(f("a", DELETED), 10.375)  # created in the batch, but on the robot by now
    assert take(c, 10.875).paths == {"a"}


def test_a_new_directory_holding_a_sliced_file_deleted_later_is_rescanned() -> None:
    c = burst()
    c.add(d("tmpdir"), 10.0)
    written(c, "tmpdir/x", 10.0)
    c.add(f("other"), 10.0)
    assert take(c, 10.25).paths == {"tmpdir/x"}
    c.add(d("tmpdir", DELETED), 10.375)  # on the robot now: not a temporary cancelling out
    assert take(c, 10.875).dirs == {"tmpdir"}


def test_a_directory_moved_away_takes_its_settled_files_out_of_the_slice() -> None:
    c = burst()
    c.add(d("a"), 9.0)
    c.take(9.25)
    written(c, "a/x", 10.0)
    written(c, "b", 10.0)
    c.add(d("a", MOVED), 10.125)
    assert take(c, 10.25).paths == {"b"}


def test_a_rescan_takes_the_slice_with_it() -> None:
    c = burst()
    written(c, "a", 10.0)
    written(c, "b", 10.0)
    c.add(Rescan("queue overflow"), 10.125)
    batch = take(c, 10.625)
    assert batch.rescan == "queue overflow" and not batch.paths


def test_a_forced_take_is_the_whole_batch() -> None:
    c = burst()
    written(c, "a", 10.0)
    written(c, "b", 10.0)
    c.add(f("c"), 10.0)
    batch = c.take(10.25, force=True)
    assert batch is not None and batch.paths == {"a", "b", "c"}


# -- end to end ------------------------------------------------------------------


def wait_until(cond: Any, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def same(local: Path, robot: Path) -> bool:
    try:
        return helpers.tree_of(local) == helpers.tree_of(robot)
    except OSError:  # a temporary of the robot's, gone while listed
        return False


@pytest.fixture
def watching(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[Path, Path]]:
    """A watch agent (its watcher and its sync loop) over the local robot, live: the
    workspace's and the robot's ``src``. The batch of a burst is due only 2 s after its
    last item (or 60 s after its first), so what reaches the robot while a burst goes
    on came in slices (one every 0.1 s at most)."""
    from fetchsync.agent import service, watcher
    from fetchsync.config import Target
    from fetchsync.sync import engine as sync

    helpers.make_workspace(tmp_path / "ws")
    monkeypatch.setenv("FETCHSYNC_LOCAL_ROBOT_HOME", str(tmp_path / "robot-home"))
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    monkeypatch.setattr(
        watcher, "Coalescer", functools.partial(Coalescer, burst_quiet=2.0, slice_every=0.1)
    )
    target = Target(
        robot="local",
        host="local",
        user=None,
        workspace=tmp_path / "ws",
        remote_workspace="~/robot_ws",
        is_local=True,
    )
    agent = service.Agent(target, rules=sync.build_rules(), cap=60.0)
    threads = [
        threading.Thread(target=agent._watch, daemon=True),
        threading.Thread(target=agent._sync_loop, daemon=True),
    ]
    for t in threads:
        t.start()
    src, robot = tmp_path / "ws" / "src", tmp_path / "robot-home" / "robot_ws" / "src"
    try:
        wait_until(lambda: agent.status()["state"] == "live", "the agent to be live")
        yield src, robot
    finally:
        agent.stop()
        for t in threads:
            t.join(10)
        agent._disconnect()


def test_a_burst_reaches_the_robot_while_it_goes_on_never_a_file_half_written(
    watching: tuple[Path, Path],
) -> None:
    src, robot = watching
    (src / "burst").mkdir()
    stop = threading.Event()
    made: list[str] = []

    def writer() -> None:  # a burst: 100 new files at once, then one every few milliseconds
        k = 0
        while not stop.is_set():
            name = f"gen_{k:05d}.txt"
            (src / "burst" / name).write_bytes(b"generated %d\n" % k)
            made.append(name)
            k += 1
            if k > 100:
                time.sleep(0.003)

    t = threading.Thread(target=writer, daemon=True)
    t.start()
    whole = b"first half\n" * 100 + b"second half\n" * 100
    copy = robot / "my_pkg" / "held.txt"
    try:
        wait_until(lambda: len(made) > 100, "the burst to start")
        # the burst is one by now: its batch waits for its end (2 s without an event)
        held = open(src / "my_pkg" / "held.txt", "wb")  # noqa: SIM115 - two halves
        held.write(whole[: len(whole) // 2])
        held.flush()
        later = made[-1]
        arrived = False
        deadline = time.monotonic() + 30
        while not arrived and time.monotonic() < deadline:
            assert not copy.exists(), "a file still being written reached the robot"
            arrived = any((robot / "burst" / n).exists() for n in made if n > later)
            time.sleep(0.002)
    finally:
        stop.set()
        t.join(10)
    assert arrived, "nothing written during the burst reached the robot before its end"
    assert not copy.exists()
    held.write(whole[len(whole) // 2 :])
    held.close()
    wait_until(lambda: same(src, robot), "the robot to match")
    assert copy.read_bytes() == whole
