"""Watching: the paths touched under a root, as they are touched, in batches.

:func:`batches` is what the sync loop iterates over::

    for batch in batches(root, rules=rules, stop_event=stop):
        if batch.rescan:
            ...                      # rescan the whole tree
        else:
            ...                      # re-stat batch.paths, rescan below batch.dirs

It yields :class:`~fetchsync.agent.coalescer.Batch` objects. The first one is
always a rescan ("started watching"): whatever changed before the watches
were in place is found by that scan, and nothing after it is missed.

What is reported are *touched paths*, not editor-level operations. The
consumer re-stats each touched path and compares it with what it last
synced, so a save by write-temporary-then-rename touches the temporary
(ignored, or cancelled out by the coalescer) and the file, which then holds
the final content. A change with ``is_dir`` set (a directory created, moved
in or out, deleted or chmodded) means "rescan below": the kernel reports a
moved directory as one event, whatever it holds.

How it works: watchdog's inotify observer (Linux) watches every directory
under the root that the ignore rules do not exclude (so ``.git`` and
``__pycache__`` cost no watch), without following symlinks; a handler turns
its events into :class:`Change` items and drops ignored paths
(:class:`IgnoreFilter`); the items are queued, with the time they were seen,
to the generator, which merges them with a
:class:`~fetchsync.agent.coalescer.Coalescer`.

Nothing is missed silently. Each of these yields a :class:`Rescan`, and all
but the ignore-rules change log a warning:

- the kernel's event queue overflowed (``IN_Q_OVERFLOW``; watchdog rebuilds
  its watches first, then the rescan runs): the warning names
  ``fs.inotify.max_queued_events``;
- a directory could not be watched because the user's inotify watches are
  used up (``ENOSPC`` from ``inotify_add_watch``; watchdog itself skips such
  directories silently): the warning names ``fs.inotify.max_user_watches``,
  its value and how to raise it. While directories are unwatched the watcher
  starts over every ``rewatch`` seconds, each time with a rescan, until every
  directory is watched again;
- a ``.fetchsyncignore`` changed so that the rules differ: the watches are
  rebuilt (a directory no longer excluded needs one) and the tree rescanned;
- the root itself was deleted, moved away or replaced (checked every
  second: inotify follows a moved directory, not its path); an error in the
  handler.

Known limits, from watchdog: its move pairing holds a ``moved from`` event
up to 0.5 s waiting for its ``moved to``; only a move out of the watched
tree waits that long (it is then reported as a deletion), and the events
behind it wait with it. A directory moved out of the tree stays watched
(inotify watches follow the directory), so changes made in it afterwards
are reported under its old path, where the consumer finds nothing to sync:
extra work, not a wrong sync.

Requires watchdog >= 7.1 (its ``InotifyFD``, through which overflows and
failed watches are seen).
"""

from __future__ import annotations

import errno
import logging
import os
import queue
import sys
import threading
import time
import warnings
from typing import Any, Callable, Generator, cast

from fetchsync.agent.coalescer import (
    CAP,
    CLOSED,
    CREATED,
    DELETED,
    MAX_PATHS,
    MODIFIED,
    MOVED,
    QUIET,
    Batch,
    Change,
    Coalescer,
    Item,
    Rescan,
)
from fetchsync.errors import ConfigError, FetchsyncError
from fetchsync.protocol.ignore import IGNORE_FILENAME, IgnoreRules, read_ignore_file

__all__ = [
    "CAP",
    "QUIET",
    "REWATCH",
    "Batch",
    "Change",
    "IgnoreFilter",
    "Rescan",
    "Watcher",
    "batches",
]

log = logging.getLogger(__name__)

# While some directories are unwatched (watch limit) or the root is gone,
# start over this often; each attempt is a full rescan, so changes there are
# late by at most this much, never lost.
REWATCH = 10.0

# How often the generator looks at its stop event when nothing happens.
_POLL = 0.1

# How often the root is checked to still be the directory being watched.
_ROOT_CHECK = 1.0

# Overflows during a storm come in runs; warn once per this many seconds.
_OVERFLOW_WARN_INTERVAL = 60.0

_SYSCTL = "/proc/sys/fs/inotify/"
_USERNS_WATCHES = "/proc/sys/user/max_inotify_watches"


def _dir_id(path: str) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


def _read_int(path: str) -> int | None:
    try:
        with open(path) as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return None


def _describe_sysctl(name: str) -> str:
    value = _read_int(_SYSCTL + name)
    return f"fs.inotify.{name} = {value if value is not None else 'unknown'}"


def _watch_limit_message(root: str, unwatched: int, first: str, *, rewatch: float) -> str:
    limit = _read_int(_SYSCTL + "max_user_watches")
    text = (
        f"inotify watch limit reached ({_describe_sysctl('max_user_watches')}, shared by all "
        f"of this user's programs)"
    )
    userns = _read_int(_USERNS_WATCHES)
    if userns is not None and (limit is None or userns < limit):
        text += f"; this user namespace allows user.max_inotify_watches = {userns}"
    where = os.path.join(root, first) if first else root
    others = f" and {unwatched - 1} other(s)" if unwatched > 1 else ""
    suggested = max(524288, 2 * limit) if limit else 524288
    return (
        f"{text}: {where}{others} not watched, so changes there are found only by a full "
        f"rescan every {rewatch:g} s. Raise the limit: "
        f"sudo sysctl fs.inotify.max_user_watches={suggested} (and put "
        f"'fs.inotify.max_user_watches={suggested}' in /etc/sysctl.d/60-fetchsync.conf "
        f"to keep it)"
    )


class IgnoreFilter:
    """Which paths are synced: the ignore rules, kept current as ``.fetchsyncignore`` files change.

    Built from :class:`~fetchsync.protocol.ignore.IgnoreRules` (defaults and
    ``--exclude`` patterns); the ``.fetchsyncignore`` files of the tree are
    read when a path below their directory is first asked about, and again
    when the watcher reports that they changed (:meth:`note`). Thread-safe:
    watchdog asks from its threads.
    """

    def __init__(self, root: str, rules: IgnoreRules | None = None) -> None:
        self.root = root
        self.base = rules if rules is not None else IgnoreRules.build()
        self._lock = threading.Lock()
        self.reset()

    def reset(self) -> None:
        """Forget every ignore file read (they are read again as needed)."""
        with self._lock:
            self._rules = self.base
            # The directories whose ignore file was read, as a tree of names
            # (None: not even the root's), so a directory event forgets a
            # whole subtree in a few steps however many were read below it.
            self._tree: dict[str, Any] | None = None
            self._files: set[str] = set()  # directories whose ignore file is in the rules

    @property
    def rules(self) -> IgnoreRules:
        """The rules as they stand, with the ignore files read so far."""
        return self._rules

    def __call__(self, path: str, is_dir: bool) -> bool:
        """Whether ``path`` (relative, POSIX) is synced, i.e. not excluded."""
        with self._lock:
            self._load_above(path)
            return not self._rules.ignored_any(path, is_dir)

    def note(self, change: Change) -> bool:
        """Update the rules for ``change``; True when they changed because an ignore file did.

        A directory change forgets what was read at and below it (another
        directory may now stand there). A change of a ``.fetchsyncignore``
        already read re-reads it.
        """
        path = change.path
        with self._lock:
            if change.is_dir:
                self._forget(path)
                return False
            slash = path.rfind("/")
            if path[slash + 1 :] != IGNORE_FILENAME:
                return False
            dirpath = path[:slash] if slash > 0 else ""
            if self._node(dirpath) is None:
                return False  # read when first needed
            before = self._rules
            self._load(dirpath)
            return self._rules != before

    # -- under the lock ------------------------------------------------------

    def _node(self, dirpath: str) -> dict[str, Any] | None:
        node = self._tree
        if node is None or not dirpath:
            return node
        for name in dirpath.split("/"):
            node = node.get(name)
            if node is None:
                return None
        return node

    def _load_above(self, path: str) -> None:
        """Read the ignore files of ``path``'s directories, top-down, up to an excluded one."""
        node = self._tree
        if node is None:
            self._load("")
            node = self._tree = {}
        names = path.split("/")
        for k in range(len(names) - 1):
            child = node.get(names[k])
            if child is None:
                dirpath = "/".join(names[: k + 1])
                if self._rules.ignored_any(dirpath, True):
                    return  # nothing below an excluded directory is synced anyway
                self._load(dirpath)
                child = node[names[k]] = {}
            node = child

    def _load(self, dirpath: str) -> None:
        try:
            text = read_ignore_file(self.root, dirpath)
        except (OSError, ValueError) as exc:
            log.warning(
                "cannot read %s: %s; treating it as empty",
                os.path.join(self.root, dirpath, IGNORE_FILENAME),
                exc,
            )
            text = None
        if text is not None:
            self._rules = self._rules.with_file(dirpath, text)
            self._files.add(dirpath)
        elif dirpath in self._files:
            self._rules = self._rules.without_file(dirpath)
            self._files.discard(dirpath)

    def _forget(self, dirpath: str) -> None:
        slash = dirpath.rfind("/")
        parent = self._node(dirpath[:slash] if slash > 0 else "")
        if parent is not None:
            parent.pop(dirpath[slash + 1 :], None)
        prefix = dirpath + "/"
        for d in [f for f in self._files if f == dirpath or f.startswith(prefix)]:
            self._rules = self._rules.without_file(d)
            self._files.discard(d)


# --------------------------------------------------------------------------
# watchdog boundary

try:  # pragma: no cover - import guard
    from watchdog.events import (
        DirAttribEvent,
        DirCreatedEvent,
        DirDeletedEvent,
        DirMovedEvent,
        FileAttribEvent,
        FileClosedEvent,
        FileCreatedEvent,
        FileDeletedEvent,
        FileModifiedEvent,
        FileMovedEvent,
        FileSystemEvent,
        FileSystemEventHandler,
    )
    from watchdog.observers.api import BaseObserver
    from watchdog.observers.inotify import InotifyEmitter, InotifyWatchGroup
    from watchdog.observers.inotify_c import (
        CallbackId,
        InotifyEvent,
        InotifyFD,
        Mask,
        WatchCallback,
        WatchDescriptor,
    )

    _WATCHDOG_ERROR: str | None = None
except ImportError as _exc:  # pragma: no cover - depends on the platform and version
    _WATCHDOG_ERROR = str(_exc)
    InotifyFD = object  # type: ignore[assignment,misc]
    BaseObserver = object  # type: ignore[assignment,misc]
    FileSystemEventHandler = object  # type: ignore[assignment,misc]
    InotifyEmitter = object  # type: ignore[assignment,misc]
    InotifyWatchGroup = object  # type: ignore[assignment,misc]

# What the kernel is asked for: no IN_OPEN, IN_ACCESS or IN_CLOSE_NOWRITE,
# which a build reading every source would otherwise flood the queue with.
_EVENT_FILTER = (
    None
    if _WATCHDOG_ERROR
    else [
        FileCreatedEvent,
        DirCreatedEvent,
        FileModifiedEvent,
        FileClosedEvent,  # IN_MODIFY, IN_CLOSE_WRITE
        FileAttribEvent,
        DirAttribEvent,  # chmod (IN_ATTRIB)
        FileDeletedEvent,
        DirDeletedEvent,
        FileMovedEvent,
        DirMovedEvent,
    ]
)

_KIND = {
    "created": CREATED,
    "modified": MODIFIED,
    "closed": CLOSED,
    "attrib": MODIFIED,
    "deleted": DELETED,
}


# A directory moved out of the tree and back in is watched again under the
# same watch descriptor; watchdog warns about that from its thread, harmlessly.
warnings.filterwarnings(
    "ignore",
    message="Callback with id .* already exists",
    category=RuntimeWarning,
    module=r"fetchsync\.agent\.watcher",
)


class _Skipped(OSError):
    """Raised to make watchdog skip an excluded directory (it skips a directory it cannot watch)."""


class _InotifyFD(InotifyFD):  # type: ignore[misc,valid-type]
    """watchdog's inotify reader, telling what watchdog does not: overflows, failed watches."""

    def __init__(self, watcher: Watcher) -> None:
        super().__init__()
        self._watcher = watcher

    def handle_event(self, event: InotifyEvent) -> None:
        super().handle_event(event)  # on overflow, watchdog rebuilds its watches here
        if event.is_queue_overflow:
            self._watcher._on_overflow()

    def add_callback(
        self, path: bytes, mask: Mask, callback: WatchCallback, id_: CallbackId
    ) -> WatchDescriptor:
        if not self._watcher._wants_watch(path):
            raise _Skipped(errno.EPERM, "excluded by the ignore rules")
        try:
            return super().add_callback(path, mask, callback, id_)  # type: ignore[no-any-return]
        except OSError as exc:
            if exc.errno == errno.ENOSPC:
                self._watcher._on_watch_limit(path)
            raise


class _WatchGroup(InotifyWatchGroup):  # type: ignore[misc,valid-type]
    """watchdog's recursive watches, added by a walk that skips what the rules exclude.

    watchdog walks every directory with ``os.walk`` (and an ``lstat`` of each
    to skip symlinks), excluded ones included although it watches none of
    them. This walk takes the kind from the directory listing (``d_type``) and
    does not descend where no watch was added: an excluded directory (a
    ``.git``, a build tree) or one that vanished meanwhile. Each directory is
    still watched before it is listed, so one created meanwhile is not missed.
    On 27,000 directories (bench/scale.py) that is about half of the watcher's
    start-up.
    """

    def _add_all_callbacks(self, path: bytes) -> None:
        self._add_callback(path)  # a failure on the root reaches the caller
        if not self.is_recursive:
            return
        watched = self._active_callbacks_by_path
        todo = [path] if path in watched else []
        while todo:
            try:
                with os.scandir(todo.pop()) as it:
                    subdirs = [e.path for e in it if _is_dir(e, self.follow_symlink)]
            except OSError:
                continue  # vanished or unreadable meanwhile
            for sub in subdirs:
                self._add_callback(sub)
                if sub in watched:
                    todo.append(sub)


def _is_dir(entry: os.DirEntry[bytes], follow: bool) -> bool:
    try:
        return entry.is_dir(follow_symlinks=follow)
    except OSError:
        return False


class _Emitter(InotifyEmitter):  # type: ignore[misc,valid-type]
    """watchdog's InotifyEmitter with :class:`_WatchGroup`, handing each event to the
    :class:`Watcher` itself, on this thread.

    watchdog queues events to its observer's thread, which calls the handler: one more
    thread hand-over for every event, in the kernel's order anyway (one emitter, one
    watch). A wifi save's IN_CLOSE_WRITE took ~0.6 ms (median, p90 1.4; the bench's
    load 3-5) from being read to the handler (FETCHSYNC_TRACE marks, bench/saveab.py);
    the observer's thread now only waits to be stopped.
    """

    def queue_event(self, event: FileSystemEvent) -> None:
        if self._event_filter is None or isinstance(event, tuple(self._event_filter)):
            cast(_InotifyFD, self._inotify_fd)._watcher._on_event(event)

    def on_thread_start(self) -> None:
        self._inotify = _WatchGroup(
            self._inotify_fd,
            os.fsencode(self.watch.path),
            is_recursive=self.watch.is_recursive,
            event_mask=self.get_event_mask_from_filter(),
            follow_symlink=self.watch.follow_symlink,
        )


class _Observer(BaseObserver):  # type: ignore[misc,valid-type]
    """watchdog's InotifyObserver, over our :class:`_InotifyFD` and :class:`_Emitter`."""

    def __init__(self, inotify_fd: _InotifyFD) -> None:
        super().__init__(_Emitter, inotify_fd=inotify_fd)
        self._inotify_fd = inotify_fd

    def on_thread_stop(self) -> None:
        super().on_thread_stop()
        self._inotify_fd.stop()
        self._inotify_fd.join()


class _Handler(FileSystemEventHandler):  # type: ignore[misc,valid-type]
    def __init__(self, watcher: Watcher) -> None:
        super().__init__()
        self._watcher = watcher

    def dispatch(self, event: FileSystemEvent) -> None:
        self._watcher._on_event(event)


# --------------------------------------------------------------------------


class Watcher:
    """Watch ``root`` recursively; hand each synced :class:`Change` or :class:`Rescan` to ``sink``.

    ``sink(item, seen_at)`` is called from watchdog's threads (and from the
    thread calling :meth:`start` / :meth:`maintain`), ``seen_at`` being
    ``time.monotonic()`` when the event was seen. :func:`batches` is the
    usual way to use it.
    """

    def __init__(
        self,
        root: str,
        *,
        sink: Callable[[Item, float], None],
        rules: IgnoreRules | None = None,
        rewatch: float = REWATCH,
    ) -> None:
        if _WATCHDOG_ERROR is not None or not sys.platform.startswith("linux"):
            raise FetchsyncError(
                "watching needs Linux inotify through watchdog >= 7.1",
                hint=_WATCHDOG_ERROR or f"this platform is {sys.platform}",
            )
        real = os.path.realpath(root)  # the root may be a link; nothing below it is followed
        if not os.path.isdir(real):
            raise ConfigError(f"cannot watch {root}: not a directory")
        self.root = real
        self._prefix = real.rstrip("/") + "/"
        self.filter = IgnoreFilter(real, rules)
        self.rewatch = rewatch
        self._sink = sink
        self._lock = threading.Lock()
        self._observer: _Observer | None = None
        self._fd: _InotifyFD | None = None
        self._starting = False
        self._unwatched = 0
        self._first_unwatched = ""
        self._root_lost = False
        self._root_id: tuple[int, int] | None = None
        self._next_root_check = 0.0
        self._restart_now = ""  # why to start over at the next maintain()
        self._next_attempt = 0.0
        self._limit_warned = False
        self._overflow_warned_at: float | None = None

    # -- state ------------------------------------------------------------------

    @property
    def degraded(self) -> bool:
        """Whether some changes can be seen only by a rescan (unwatched directories, root gone)."""
        return self._unwatched > 0 or self._root_lost or self._observer is None

    # -- life cycle ---------------------------------------------------------------

    def start(self, reason: str | None = None) -> None:
        """Add the watches (synchronously: changes from now on are seen).

        Then ``sink`` gets a :class:`Rescan`: ``reason``, or the watch-limit
        warning when some directory could not be watched. Raises
        ConfigError when the root is not a directory, FetchsyncError when
        no inotify instance can be had.
        """
        with self._lock:
            if self._observer is not None:
                return
            self._unwatched = 0
            self._first_unwatched = ""
            self._root_lost = False
            self._restart_now = ""
            self._root_id = _dir_id(self.root)
            try:
                fd = _InotifyFD(self)
            except OSError as exc:
                raise FetchsyncError(
                    f"cannot watch {self.root}: {exc.strerror or exc}",
                    hint=(
                        f"too many inotify instances; {_describe_sysctl('max_user_instances')}"
                        if exc.errno == errno.EMFILE
                        else None
                    ),
                ) from exc
            fd.start()
            observer = _Observer(fd)
            observer.schedule(
                _Handler(self),
                self.root,
                recursive=True,
                event_filter=_EVENT_FILTER,
                follow_symlink=False,
            )
            self._starting = True
            try:
                observer.start()
            except BaseException as exc:
                fd.stop()
                fd.join()
                if not isinstance(exc, OSError):
                    raise
                if exc.errno == errno.ENOSPC:
                    pass  # not even the root (counted by _InotifyFD): rescan every `rewatch` s
                elif exc.errno in (errno.ENOENT, errno.ENOTDIR):
                    raise ConfigError(f"cannot watch {self.root}: it is gone") from exc
                else:
                    raise FetchsyncError(
                        f"cannot watch {self.root}: {exc.strerror or exc}"
                    ) from exc
            else:
                self._observer = observer
                self._fd = fd
            finally:
                self._starting = False
        now = time.monotonic()
        self._next_attempt = now + self.rewatch
        if self._unwatched:
            message = _watch_limit_message(
                self.root, self._unwatched, self._first_unwatched, rewatch=self.rewatch
            )
            if not self._limit_warned:
                log.warning("%s", message)
                self._limit_warned = True
            else:
                log.debug("%s", message)
            self._sink(Rescan(message), now)
            return
        if self._limit_warned:
            log.info("every directory under %s is watched again", self.root)
            self._limit_warned = False
        if reason:
            self._sink(Rescan(reason), now)

    def stop(self) -> None:
        """Remove the watches and stop watchdog's threads. Idempotent."""
        with self._lock:
            observer, self._observer = self._observer, None
            self._fd = None
        if observer is not None:
            observer.stop()
            observer.join()

    def restart(self, reason: str) -> None:
        """Start over: stop, forget the ignore files read, start; then a :class:`Rescan`."""
        self.stop()
        self.filter.reset()
        self.start(reason)

    def maintain(self, now: float) -> None:
        """Start over when needed: at once when the ignore rules changed or the root was
        replaced, else every ``rewatch`` seconds while degraded.

        Call it regularly from the thread that owns the watcher (:func:`batches` does).
        """
        if self._observer is not None and not self._root_lost and now >= self._next_root_check:
            self._next_root_check = now + _ROOT_CHECK
            if _dir_id(self.root) != self._root_id:
                log.warning("%s was moved away or replaced; watching that path again", self.root)
                self._restart_now = f"{self.root} was moved away or replaced"
        if self._restart_now:
            reason = self._restart_now
            log.info("%s: watching %s again", reason, self.root)
        elif self.degraded and now >= self._next_attempt:
            reason = "watching every directory again"
        else:
            return
        try:
            self.restart(reason)
        except ConfigError as exc:  # the root is gone: try again later
            self._root_lost = True
            self._next_attempt = now + self.rewatch
            self._sink(Rescan(f"{reason}; {exc}"), now)

    def __enter__(self) -> Watcher:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- from watchdog's threads ------------------------------------------------------

    def _relative(self, path: str) -> str | None:
        """``path`` relative to the root; "" for the root; None outside it."""
        if path.startswith(self._prefix):
            return path[len(self._prefix) :]
        return "" if path.rstrip("/") == self.root.rstrip("/") else None

    def _wants_watch(self, path: bytes) -> bool:
        rel = self._relative(os.fsdecode(path))
        return rel is None or rel == "" or self.filter(rel, True)

    def _on_event(self, event: FileSystemEvent) -> None:
        now = time.monotonic()
        try:
            kind = event.event_type
            if kind == "moved":
                self._emit(os.fsdecode(event.src_path), MOVED, event.is_directory, now)
                self._emit(os.fsdecode(event.dest_path), CREATED, event.is_directory, now)
            elif kind in _KIND:
                self._emit(os.fsdecode(event.src_path), _KIND[kind], event.is_directory, now)
        except Exception as exc:  # a dead handler thread would miss everything
            log.exception("error handling %r", event)
            self._sink(Rescan(f"error in the watcher: {exc}"), now)

    def _emit(self, full: str, kind: str, is_dir: bool, now: float) -> None:
        rel = self._relative(full)
        if rel is None:
            return
        if rel == "":
            if kind in (DELETED, MOVED):
                self._root_lost = True
                log.warning(
                    "%s was deleted or moved away; watching it again every %g s",
                    self.root,
                    self.rewatch,
                )
                self._sink(Rescan(f"{self.root} was deleted or moved away"), now)
            return  # the root's own mode is not synced
        if is_dir and kind == CREATED and os.path.islink(full):
            # watchdog reports a link to a directory found in a new directory as a directory
            is_dir = False
        change = Change(rel, kind, is_dir)  # type: ignore[arg-type]
        if self.filter.note(change):
            self._restart_now = f"ignore rules changed: {rel}"
        if self.filter(rel, is_dir):
            self._sink(change, now)

    def _on_overflow(self) -> None:
        now = time.monotonic()
        message = (
            f"inotify event queue overflowed ({_describe_sysctl('max_queued_events')}): "
            f"changes were lost; rescanning {self.root}"
        )
        last = self._overflow_warned_at
        if last is None or now - last > _OVERFLOW_WARN_INTERVAL:
            log.warning("%s", message)
            self._overflow_warned_at = now
        else:
            log.debug("%s", message)
        self._sink(Rescan(message), now)

    def _on_watch_limit(self, path: bytes) -> None:
        self._unwatched += 1
        if self._unwatched > 1:
            return
        rel = self._relative(os.fsdecode(path))
        self._first_unwatched = rel or ""
        if self._starting:
            return  # start() reports it once, with the count
        message = _watch_limit_message(self.root, 1, self._first_unwatched, rewatch=self.rewatch)
        self._next_attempt = time.monotonic() + self.rewatch
        if not self._limit_warned:
            log.warning("%s", message)
            self._limit_warned = True
        self._sink(Rescan(message), time.monotonic())


def batches(
    root: str,
    *,
    rules: IgnoreRules | None = None,
    quiet: float = QUIET,
    cap: float = CAP,
    max_paths: int = MAX_PATHS,
    rewatch: float = REWATCH,
    stop_event: threading.Event | None = None,
) -> Generator[Batch, None, None]:
    """Yield batches of what changes under ``root``, until ``stop_event`` is set or the generator
    is closed.

    The first batch is a rescan ("started watching"), due once the watches
    are in place. ``rules`` are the base ignore rules (defaults and
    ``--exclude`` patterns; the tree's ``.fetchsyncignore`` files are read
    as it goes). ``quiet``, ``cap`` and ``max_paths`` are the
    :class:`~fetchsync.agent.coalescer.Coalescer`'s. Stops within about
    0.1 s of ``stop_event`` being set while it waits for changes.
    """
    items: queue.SimpleQueue[tuple[Item, float]] = queue.SimpleQueue()

    def sink(item: Item, at: float) -> None:
        items.put((item, at))

    coalescer = Coalescer(quiet=quiet, cap=cap, max_paths=max_paths)
    watcher = Watcher(root, sink=sink, rules=rules, rewatch=rewatch)
    watcher.start(f"started watching {watcher.root}")
    try:
        while stop_event is None or not stop_event.is_set():
            now = time.monotonic()
            watcher.maintain(now)
            wait = coalescer.due(now)
            if wait == 0.0:
                batch = coalescer.take(now)
                if batch is not None:
                    yield batch
                continue
            try:
                item, at = items.get(timeout=_POLL if wait is None else min(wait, _POLL))
            except queue.Empty:
                continue
            coalescer.add(item, at)
            while not coalescer.full:
                try:
                    item, at = items.get_nowait()
                except queue.Empty:
                    break
                coalescer.add(item, at)
    finally:
        watcher.stop()
