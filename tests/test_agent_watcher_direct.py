"""The watcher's events reach it on watchdog's emitter thread, in the kernel's order.

watchdog queues every event from its emitter thread to its observer's thread, which
calls the handler: one more thread hand-over per event on a save's way to the robot
(bench/saveab.py traced it at ~0.2 ms median, ~2 ms at p90, of a wifi save). The
watcher takes them from the emitter itself (watcher._Emitter.queue_event); the
observer's queue stays empty. Nothing here asserts a latency: that the events come from
the emitter's thread, none through the observer's queue, in order, with the ignore
rules applied as before.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import pytest

from fetchsync.agent.coalescer import CLOSED, CREATED, DELETED, MODIFIED, MOVED, Change, Item
from fetchsync.agent.watcher import Watcher
from fetchsync.protocol.ignore import IgnoreRules

pytestmark = [
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="inotify is Linux's"),
    pytest.mark.filterwarnings("ignore:Callback with id:RuntimeWarning"),
]

WAIT = 30.0


class Sink:
    def __init__(self) -> None:
        self.items: list[tuple[Item, str]] = []
        self.cond = threading.Condition()

    def __call__(self, item: Item, _at: float) -> None:
        with self.cond:
            self.items.append((item, threading.current_thread().name))
            self.cond.notify_all()

    def wait_for(self, change: Change) -> None:
        deadline = time.monotonic() + WAIT
        with self.cond:
            while not any(i == change for i, _ in self.items):
                left = deadline - time.monotonic()
                assert left > 0, f"{change} never came: {self.items}"
                self.cond.wait(left)


def test_events_come_from_the_emitter_thread_in_order_and_never_through_the_observer(tmp_path):
    root = tmp_path / "src"
    (root / "pkg").mkdir(parents=True)
    (root / "pkg/a.cpp").write_text("a\n")
    sink = Sink()
    w = Watcher(str(root), sink=sink, rules=IgnoreRules.build())
    w.start()
    try:
        observer = w._observer
        assert observer is not None
        (emitter,) = observer.emitters
        with open(root / "pkg/a.cpp", "w") as fh:  # an in-place save
            fh.write("a, saved\n")
        (root / "pkg/b.cpp").write_text("b\n")
        (root / "pkg/b.cpp").rename(root / "pkg/c.cpp")
        (root / "pkg/c.cpp").unlink()
        (root / "pkg/last.cpp").write_text("last\n")
        sink.wait_for(Change("pkg/last.cpp", CLOSED, False))
        assert observer.event_queue.empty()
        threads = {name for _, name in sink.items}
        assert threads == {emitter.name}, (threads, emitter.name)
        changes = [i for i, _ in sink.items if isinstance(i, Change)]
        order = [
            Change("pkg/a.cpp", MODIFIED, False),
            Change("pkg/a.cpp", CLOSED, False),
            Change("pkg/b.cpp", CREATED, False),
            Change("pkg/b.cpp", MOVED, False),
            Change("pkg/c.cpp", CREATED, False),
            Change("pkg/c.cpp", DELETED, False),
            Change("pkg/last.cpp", CREATED, False),
            Change("pkg/last.cpp", CLOSED, False),
        ]
        at = [changes.index(c) for c in order]  # each there, in the kernel's order
        assert at == sorted(at), changes
    finally:
        w.stop()
    assert not any(t.name == emitter.name and t.is_alive() for t in threading.enumerate())


def test_ignored_paths_stay_out_and_a_restart_delivers_again(tmp_path):
    root = tmp_path / "src"
    root.mkdir()
    (root / ".fetchsyncignore").write_text("*.log\n")
    sink = Sink()
    w = Watcher(str(root), sink=sink)
    w.start()
    try:
        (root / "x.log").write_text("ignored\n")
        (root / "y.cpp").write_text("kept\n")
        sink.wait_for(Change("y.cpp", CLOSED, False))
        assert not any(isinstance(i, Change) and i.path == "x.log" for i, _ in sink.items)
        w.restart("again")
        (root / "z.cpp").write_text("after the restart\n")
        sink.wait_for(Change("z.cpp", CLOSED, False))
        assert w._observer is not None and w._observer.event_queue.empty()
    finally:
        w.stop()


def test_the_handler_still_takes_what_reaches_the_observer(tmp_path: Path) -> None:
    """Should watchdog queue an event itself (not through queue_event), it is not lost."""
    root = tmp_path / "src"
    root.mkdir()
    sink = Sink()
    w = Watcher(str(root), sink=sink)
    w.start()
    try:
        from watchdog.events import FileModifiedEvent

        observer = w._observer
        assert observer is not None
        (emitter,) = observer.emitters
        observer.event_queue.put((FileModifiedEvent(str(root / "q.cpp")), emitter.watch))
        sink.wait_for(Change("q.cpp", MODIFIED, False))
    finally:
        w.stop()
