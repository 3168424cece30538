"""Coalescing: which touched paths travel to the robot together, and when.

The watcher reports paths one at a time, as the kernel saw them; a save is a
handful of events, a ``git checkout`` thousands. The coalescer turns that
stream into batches, each one request to the robot:

- **quiet window**: a batch is due once no item arrived for ``quiet``
  seconds, so an editor's save sequence (write a temporary, rename it over
  the file, delete the backup) lands in one batch, as its final content;
- **a save is due at once**: when the newest item is a file written and
  closed (``closed``, IN_CLOSE_WRITE) that existed before the batch, the
  save is complete and the batch does not wait for the quiet window (an
  in-place save, vim's, VS Code's, ``echo >>``: wifi save -> robot p50 drops
  by the window's 5 ms, a third of the 13 ms target). A file created in the
  batch may be an editor's temporary about to be renamed, one deleted first
  is a ``git checkout``'s, and any later item (a chmod, a deletion) brings
  the window back; only a batch begun ``burst_quiet`` after the last one
  ends so (a formatter's or checkout's stream is not cut file by file);
- **bursts**: once a batch holds ``burst`` items, its quiet window widens to
  ``burst_quiet``: a few milliseconds without an event in the middle of a
  ``git checkout`` are a hiccup (the writer's own pauses, the scheduler),
  not its end, and ending the batch there would only add a round trip. The
  batch after a burst is one from its first item if that item came within
  ``burst_quiet`` of the burst's last (the burst goes on past the cap);
- **a new directory is a burst's start**: a batch holding a directory created or
  moved in waits ``burst_quiet`` too. Its files follow it, but the kernel reports them
  only once the watch on the new directory is in place, often more than ``quiet``
  later: cut there, a burst went as a push of the directory and the few files written
  by then, and all the rest in a second push after the first one's answer.
  bench/burstab.py traces of 40 500-file bursts into a new directory on wifi (load
  2-7): 17 were cut so; of the 19 whose writer was done within 80 ms, the 8 cut so took
  301-654 ms from the first write to all on the robot (median 502, mostly 2 pushes),
  the 11 others 270-533 (median 331, one push). Interleaved A/B, 8 rounds in alternating order, load
  1.9-3.8: 266-440 ms (median 348), one push in 8 of 8, vs 305-582 (median 358), one
  push in 5 of 8 (two cut so: 404, 413 ms); per round -197 -137 +28 -61 +47 +37 -106 +58.
  A ``mkdir`` alone reaches the robot ``burst_quiet - quiet`` (20 ms) later;
- **cap**: a batch is due at most ``cap`` seconds after its first item, even
  while items keep coming, so a long burst is synced in slices as it goes;
- **size**: a batch is due at once when it holds ``max_paths`` paths;
- **one entry per path**: a path touched many times appears once. A path
  that was created (or moved in) and then deleted or moved away within the
  batch cancels out: it did not exist before and does not now (an editor's
  temporary, a ``mktemp`` directory);
- **a directory change means "rescan below"**: it subsumes every change to a
  path below it, before or after it in the batch;
- **a** :class:`Rescan` **subsumes everything**: the consumer rescans the
  whole tree, so no path is kept.

Pure: no threads, no I/O, no clock of its own. Every call takes ``now``
(seconds of a monotonic clock, ``time.monotonic()`` in the agent), so tests
drive it with scripted items and invented times.

The consumer re-stats what a batch names and compares it with what it last
synced; kinds are only used here, to cancel temporaries, and are not part of
a :class:`Batch`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Literal, Union

__all__ = [
    "BURST",
    "BURST_QUIET",
    "CAP",
    "CLOSED",
    "CREATED",
    "DELETED",
    "KINDS",
    "MAX_PATHS",
    "MODIFIED",
    "MOVED",
    "QUIET",
    "Batch",
    "Change",
    "Coalescer",
    "Item",
    "Rescan",
]

CREATED: Final = "created"
MODIFIED: Final = "modified"
CLOSED: Final = "closed"  # written and closed (IN_CLOSE_WRITE): modified, and complete
DELETED: Final = "deleted"
MOVED: Final = "moved"  # moved away: gone from this path by a rename
KINDS = (CREATED, MODIFIED, CLOSED, DELETED, MOVED)
Kind = Literal["created", "modified", "closed", "deleted", "moved"]

# A save's events arrive within a millisecond or two of each other; 5 ms of
# silence ends the save without adding noticeably to the 50 ms budget from
# save to robot. The cap keeps a long burst (a checkout, a build writing
# into src/) from holding everything back until it ends.
QUIET = 0.005
CAP = 0.1
MAX_PATHS = 10_000
# A save is up to a dozen events (vim's is about ten); a burst is more.
BURST = 64
BURST_QUIET = 0.025

_GONE = (DELETED, MOVED)
_NEW = (CREATED, DELETED)


@dataclass(frozen=True)
class Change:
    """A path under the watched root was touched.

    ``path`` is relative to the root, POSIX (``pkg/src/node.cpp``), never
    empty. ``kind`` is what the kernel reported; a rename is two changes,
    ``moved`` at the source and ``created`` at the destination. ``is_dir``
    says the path was a directory (a symlink is not one): the consumer then
    rescans everything below it, because the kernel reports a directory
    moved in, out or deleted as one event, not one per file in it.
    """

    path: str
    kind: Kind
    is_dir: bool = False

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown change kind {self.kind!r}")
        p = self.path
        if not p or p.startswith("/") or p.endswith("/"):
            raise ValueError(f"not a relative path: {p!r}")


@dataclass(frozen=True)
class Rescan:
    """Changes may have been missed: the consumer rescans the whole tree.

    ``reason`` is for the log: the watch started, the kernel's event queue
    overflowed, a directory could not be watched, the ignore rules changed.
    """

    reason: str


Item = Union[Change, Rescan]


@dataclass(frozen=True)
class Batch:
    """What changed, to be synced in one go.

    ``dirs`` are directories to rescan below (each disjoint from the others);
    ``paths`` are other touched paths, none below a directory of ``dirs``.
    When ``rescan`` is set (its reason), the whole tree is to be rescanned
    and both sets are empty. ``first_at`` and ``last_at`` are the times of
    the first and last item merged into the batch, ``items`` their number.
    """

    paths: frozenset[str]
    dirs: frozenset[str]
    rescan: str | None
    first_at: float
    last_at: float
    items: int = 0


class _Entry:
    """What a pending batch knows about one path."""

    __slots__ = ("first", "is_dir", "last")

    def __init__(self, kind: str, is_dir: bool) -> None:
        self.first = kind
        self.last = kind
        self.is_dir = is_dir

    @property
    def void(self) -> bool:
        """Created and gone within the batch: there is nothing to sync."""
        return self.first == CREATED and self.last in _GONE


def _under(path: str, dirs: set[str] | frozenset[str]) -> bool:
    """Whether a proper ancestor of ``path`` is in ``dirs``."""
    j = path.rfind("/")
    while j > 0:
        if path[:j] in dirs:
            return True
        j = path.rfind("/", 0, j)
    return False


class Coalescer:
    """Merge timestamped items into batches; see the module docstring for the rules.

    ::

        c = Coalescer(quiet=0.005, cap=0.1)
        c.add(Change("a.txt", "modified"), now)
        wait = c.due(now)              # seconds until the batch is due, None if none pending
        batch = c.take(now)            # the batch once due, else None
    """

    def __init__(
        self,
        *,
        quiet: float = QUIET,
        cap: float = CAP,
        max_paths: int = MAX_PATHS,
        burst: int = BURST,
        burst_quiet: float = BURST_QUIET,
    ) -> None:
        if min(quiet, cap, burst_quiet) < 0:
            raise ValueError("quiet, cap and burst_quiet must not be negative")
        if max_paths < 1 or burst < 1:
            raise ValueError("max_paths and burst must be at least 1")
        self.quiet = quiet
        self.cap = cap
        self.max_paths = max_paths
        self.burst = burst
        self.burst_quiet = max(quiet, burst_quiet)
        self._reset()
        self._ended_at: float | None = None  # when the last batch taken ended, if a burst
        self._taken_at: float | None = None  # when the last batch taken ended

    def _reset(self) -> None:
        self._entries: dict[str, _Entry] = {}
        self._dirs: set[str] = set()
        self._rescan: str | None = None
        self._first_at: float | None = None
        self._last_at = 0.0
        self._items = 0
        self._bursting = False
        self._saved = False  # the newest item completed the save of an existing file
        self._fresh = True  # the batch began after a pause of burst_quiet or more
        self._new_dir = False  # it holds a directory created or moved in: a burst starts

    def add(self, item: Item, now: float) -> None:
        """Merge ``item``, which happened at ``now``."""
        if self._first_at is None:
            self._first_at = now
            self._last_at = now
            ended = self._ended_at
            self._bursting = ended is not None and now - ended <= self.burst_quiet
            # a save starts after a pause: not a batch cut from a stream going on
            taken = self._taken_at
            self._fresh = taken is None or now - taken > self.burst_quiet
        else:
            # Items may come from several threads with their own timestamps.
            self._first_at = min(self._first_at, now)
            self._last_at = max(self._last_at, now)
        self._items += 1
        self._saved = False
        if isinstance(item, Rescan):
            if self._rescan is None:
                self._rescan = item.reason
                self._entries.clear()
                self._dirs.clear()
            return
        if self._rescan is not None:
            return
        path = item.path
        if self._dirs and _under(path, self._dirs):
            return
        entry = self._entries.get(path)
        if entry is None:
            self._entries[path] = _Entry(item.kind, item.is_dir)
            self._saved = item.kind == CLOSED and not item.is_dir
        else:
            # not after a creation (a temporary) nor a deletion (a git checkout's rewrite)
            self._saved = item.kind == CLOSED and not item.is_dir and entry.first not in _NEW
            entry.last = item.kind
            # Sticky: a directory replaced by a file still needs the robot's
            # subtree there rescanned (and removed).
            entry.is_dir = entry.is_dir or item.is_dir
        if item.is_dir:
            # Changes recorded below it before it are dropped in take().
            self._dirs.add(path)
            self._new_dir = self._new_dir or item.kind == CREATED

    @property
    def pending(self) -> bool:
        """Whether any item is waiting to be taken."""
        return self._first_at is not None

    @property
    def full(self) -> bool:
        """Whether the pending batch reached ``max_paths`` (it is due at once)."""
        return len(self._entries) >= self.max_paths

    def due(self, now: float) -> float | None:
        """Seconds from ``now`` until the pending batch is due; 0.0 if it is, None if none."""
        if self._first_at is None:
            return None
        if self.full:
            return 0.0
        bursting = self._bursting or self._items >= self.burst or self._new_dir
        if self._saved and self._fresh and not bursting:
            return 0.0
        quiet = self.burst_quiet if bursting else self.quiet
        at = min(self._last_at + quiet, self._first_at + self.cap)
        return max(0.0, at - now)

    def take(self, now: float, *, force: bool = False) -> Batch | None:
        """The pending batch if it is due at ``now`` (or ``force``), and start a new one.

        None when nothing is pending, the batch is not due yet, or everything
        in it cancelled out (which also starts a new batch).
        """
        wait = self.due(now)
        if wait is None or (wait > 0 and not force):
            return None
        assert self._first_at is not None
        first_at, last_at, items, rescan = self._first_at, self._last_at, self._items, self._rescan
        burst = self._bursting or items >= self.burst or self._new_dir
        self._ended_at = last_at if burst else None
        self._taken_at = last_at
        paths: list[str] = []
        dirs: list[str] = []
        if rescan is None:
            live_dirs = {p for p in self._dirs if not self._entries[p].void}
            for path, entry in self._entries.items():
                if entry.void or _under(path, self._dirs):
                    continue
                (dirs if path in live_dirs else paths).append(path)
        self._reset()
        if rescan is None and not paths and not dirs:
            return None
        return Batch(frozenset(paths), frozenset(dirs), rescan, first_at, last_at, items)
