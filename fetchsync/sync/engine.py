"""push and pull: the sync engine's verbs over a :class:`~fetchsync.link.connection.Connection`.

``push`` makes ``<remote workspace>/src`` identical to the local ``src/``;
``pull`` the reverse. Both scan the local tree (stat only, hashing what the
last-synced state cannot vouch for), plan with :func:`fetchsync.sync.plan.plan`,
send operations in pipelined batches, and advance the state with what the
other end reports it now holds. The watch agent uses the same :class:`Syncer`.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import errno
import gc
import hashlib
import logging
import os
import queue
import stat as stat_mod
import threading
import time
import types
import zlib
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Callable, Generator, Iterable, Iterator, Mapping, TypeVar

from fetchsync.errors import ConflictError, MassDeletionError, RemoteError, SyncError
from fetchsync.link.client import Applied, Content, Endpoint, Failed, Listing, Opened, Pending
from fetchsync.link.connection import LIVENESS_INTERVAL, Connection
from fetchsync.protocol import delta as delta_mod
from fetchsync.protocol import hashing, stl, wire
from fetchsync.protocol import messages as M
from fetchsync.protocol.ignore import (
    IGNORE_FILENAME,
    MAX_IGNORE_FILE_SIZE,
    IgnoreRules,
    build_rules,  # noqa: F401  (the verbs' name for it)
)
from fetchsync.protocol.paths import ancestors
from fetchsync.protocol.store import Store, is_temp
from fetchsync.protocol.tree import Entry, ScanResult, entry_from_stat, scan, stat_path
from fetchsync.sync.plan import COPY, DELTA, WHOLE, Planned, catkin_toplevel, plan
from fetchsync.sync.state import State, Synced
from fetchsync.trace import mark

log = logging.getLogger(__name__)

V = TypeVar("V")

_deflate: types.ModuleType | None = None  # see _fast


def _fast() -> types.ModuleType:
    """ISA-L's deflate: the same zlib streams the robot's standard library inflates,
    made ~7x faster than zlib's level 1 at the same size (bench/README.md); the
    standard library's where it has no wheel. Imported when first needed: a no-op
    push compresses nothing, and the import was ~5-9 ms of every push's CPU."""
    global _deflate
    if _deflate is None:
        try:
            from isal import isal_zlib

            _deflate = isal_zlib
        except ImportError:
            _deflate = zlib
    return _deflate


# Files from SIG_MIN up travel as deltas against the signature the laptop kept of what
# it last sent (no round trip); smaller ones go whole, their delta being about their
# size (a chunk averages 1 KiB). At 16 KiB most edited sources went whole: rclcpp's
# history (bench/history.py --link wifi --commits 15 --switches 2 --baseline-rev,
# 16 -> 2 KiB) sent 56.3 -> 33.3 KiB for 15 commits, 287 -> 157 KiB for 2 switches.
SIG_MIN = 2 * 1024
# What the state keeps of a text file up to messages.ZDICT_BASE_MAX bytes sent: the
# content itself, deflated, behind this tag (in place of a signature). Its next version is
# then sent deflated with that content as the dictionary (messages.SRC_ZDICT), no round
# trip: a one-line change costs tens of bytes where a chunk delta sent the changed chunk
# (~1 KiB) and a file under SIG_MIN went whole. bench/acct.py --history 30 (rclcpp's last
# 30 commits, fetchsync's frames without SSH): content 45.3 -> 21.9 KB, beyond the no-op
# 2.03 -> 1.23 KB per commit; a one-line edit of the bench's .cpp 992 -> 88 bytes. The
# state grows by the deflated text (bench tree of 2,000 files / 40 MiB: 0.6 -> 3.9 MB) and
# the laptop signs fewer files (its CPU went down). The record is used only while its
# content hashes to what the robot holds (else the file goes whole).
BASE_MAGIC = b"FZB1"
# The robot is asked to sign its copy (a round trip and the signature's bytes) only
# from this size: below it the request costs about what it saves.
ROBOT_SIG_MIN = 16 * 1024
BIG = 32 * 1024 * 1024  # larger files travel in UPLOAD pieces
PIECE = 8 * 1024 * 1024
BATCH_BYTES = 8 * 1024 * 1024  # blob bytes per request
BATCH_OPS = 4000
FIRST_BATCHES_SMALLER = {0: 3, 1: 2, 2: 1}  # batch index -> BATCH_BYTES shifted right by
WINDOW = 3  # batches between the caller and the link: compressing, ready, being sent
INLINE_BATCH = 64 * 1024  # a round's only batch up to this much data: sent by the caller
# A large round starts with writes of large files (from LARGE up, binary mostly: packed
# at once) up to LARGE_FIRST bytes, the rest in the plan's order: the link is busy from the
# first batch while the text behind them is deflated at level 6, where the first batches
# of small text files (~50 ms of CPU per MiB) left it idle. The bench's initial push on
# Wi-Fi (2,000 files / 40 MiB, 6 interleaved, load 5.4; the link's arrivals at the
# shaper): link idle in the first second after the robot's listing 0.86 -> 0.09 s, the
# first batch sent 0.27 -> 0.09 s after it, the link's last data byte 0.95 s sooner,
# 23.66 -> 23.63 MB; bench/run.py --rev/--baseline-rev, 5 interleaved: 0.84x (load 5-8),
# 1.03x (load 8-9: noise) of the time.
LARGE = 256 * 1024
LARGE_FIRST = 8 * 1024 * 1024
LARGE_FROM = 2048  # rounds of more operations than this
RACY_NS = 2_000_000_000
MAX_ROUNDS = 4
READ_TRIES = 5  # reads of a file that changes while read, before giving up on it
VANISHED = "vanished while it was being read; treated as deleted"

# A test seam: when set, called as ``read_hook(full_path, event)`` where a push
# reads a local file, with event "open" (about to open it) or "read" (a chunk
# was read), so a test can change or remove the file at that exact moment.
read_hook: Callable[[str, str], None] | None = None

Progress = Callable[[int, int], None]


@dataclass
class Report:
    verb: str
    robot: str = ""
    connection: str = ""  # "ssh", "master" (a persistent connection) or "local"
    local: str = ""
    remote: str = ""
    files: int = 0
    dirs: int = 0
    links: int = 0
    deleted: int = 0
    chmods: int = 0
    reused: int = 0
    deltas: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    seconds: float = 0.0
    rounds: int = 0
    dry_run: bool = False
    conflicts: list[dict[str, str]] = field(default_factory=list)
    errors: list[dict[str, str]] = field(default_factory=list)
    skipped: list[dict[str, str]] = field(default_factory=list)
    planned: list[dict[str, str]] = field(default_factory=list)

    @property
    def changed(self) -> int:
        return self.files + self.dirs + self.links + self.deleted + self.chmods

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        out["ok"] = not self.errors
        return out

    def add(self, other: Report) -> None:
        """Count ``other``'s work (a push made after this one, as part of it) in this one."""
        for f in fields(self):
            mine = getattr(self, f.name)
            if f.name not in ("seconds", "dry_run") and isinstance(mine, (int, list)):
                setattr(self, f.name, mine + getattr(other, f.name))

    def count(self, p: Planned) -> None:
        kind = p.op.kind
        if kind == M.WRITE:
            self.files += 1
            self.reused += p.how == COPY
            self.deltas += p.how == DELTA
        elif kind == M.MKDIR:
            self.dirs += 1
        elif kind == M.SYMLINK:
            self.links += 1
        elif kind == M.DELETE:
            self.deleted += 1
        elif kind == M.CHMOD:
            self.chmods += 1


# --------------------------------------------------------------------------- local side
#: How a file to read is opened: never through a symlink, never waiting on a FIFO.
OPEN_FLAGS = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)


@dataclass
class LocalTree:
    items: dict[str, M.Listed]
    stats: dict[str, Entry]
    skipped: list[tuple[str, str]]
    unhashed: set[str] = field(default_factory=set)  # new files whose hash nobody needed yet

    def guarded(self) -> Callable[[str], bool]:
        """Whether a path is one the laptop could not read, or lies below one: the robot's
        copy must be left as it is (to this scan the path looks deleted, but it is not)."""
        unreadable = {p for p, reason in self.skipped if _unreadable(reason)}
        if not unreadable:
            return lambda path: False
        return lambda path: path in unreadable or any(a in unreadable for a in ancestors(path))

    def hash_where_needed(self, root: str, remote: dict[str, M.Listed], algorithm: str) -> None:
        """Hash the new files the robot could hold already: at the same path, or the same size
        elsewhere (content to reuse). The others are hashed as they are read to be sent."""
        if not self.unhashed or not remote:  # an empty robot holds nothing to compare
            return
        sizes = {r.size for r in remote.values() if r.kind == "f"}
        for path in sorted(self.unhashed):
            item = self.items[path]
            if path not in remote and item.size not in sizes:
                continue
            try:
                digest = _hash_file(os.path.join(root, path), algorithm)
            except OSError as exc:
                self.skipped.append(
                    (path, VANISHED if _gone(exc) else f"cannot read: {exc.strerror}")
                )
                del self.items[path]
                self.stats.pop(path, None)
            else:
                self.items[path] = M.Listed(path, "f", item.mode, item.size, hash=digest)
            self.unhashed.discard(path)


class LocalRules:
    """Whether the laptop's rules exclude a path: the verb's rules with the laptop's
    ``.fetchsyncignore`` files along it, each read once (not only for paths a scan met:
    the robot's paths the laptop no longer lists)."""

    def __init__(self, root: str, rules: IgnoreRules) -> None:
        self.root = root
        self._below: dict[str, IgnoreRules] = {"": _with_ignore_file(rules, root, "")}

    def _rules_below(self, dirpath: str) -> IgnoreRules:
        got = self._below.get(dirpath)
        if got is None:
            parent = dirpath.rpartition("/")[0]
            got = _with_ignore_file(self._rules_below(parent), self.root, dirpath)
            self._below[dirpath] = got
        return got

    def __call__(self, path: str, is_dir: bool) -> bool:
        return self._rules_below(path.rpartition("/")[0]).ignored_any(path, is_dir)


def _with_ignore_file(rules: IgnoreRules, root: str, dirpath: str) -> IgnoreRules:
    """``rules`` with the ``.fetchsyncignore`` of ``dirpath``, if it holds a regular one."""
    full = os.path.join(root, dirpath, IGNORE_FILENAME)
    try:
        fd = os.open(full, OPEN_FLAGS)
    except OSError:
        return rules
    try:
        if not stat_mod.S_ISREG(os.fstat(fd).st_mode):
            return rules
        text = os.read(fd, MAX_IGNORE_FILE_SIZE).decode("utf-8", "surrogateescape")
    except OSError:
        return rules
    finally:
        os.close(fd)
    return rules.with_file(dirpath, text)


def _unreadable(reason: str) -> bool:
    """Whether a skipped path's reason says the laptop could not read it (not: it is a FIFO)."""
    return reason.startswith(("cannot read", "cannot list"))


def _gone(exc: OSError) -> bool:
    return isinstance(exc, (FileNotFoundError, NotADirectoryError))


def _hash_file(full: str, algorithm: str) -> str:
    """The content hash of the regular file at ``full``, opened as :func:`read_stable`
    opens it: a FIFO put in its place since the scan made a plain open() wait for a
    writer forever (the push, or the watch agent, hung), a symlink was followed."""
    if read_hook is not None:
        read_hook(full, "open")
    with open(os.open(full, OPEN_FLAGS), "rb") as fh:
        if not stat_mod.S_ISREG(os.fstat(fh.fileno()).st_mode):
            raise _not_regular(full)
        return hashing.file_digest(algorithm, fh).hex()


def _racy(entry: Entry, now_ns: int) -> bool:
    return now_ns - entry.mtime_ns < RACY_NS


def scan_tree(root: str, rules: IgnoreRules) -> ScanResult:
    """Stat everything under ``root`` the rules keep; a one-line error if it cannot be listed."""
    try:
        return scan(root, rules, is_temp=is_temp, on_dir=_searchable)
    except OSError as exc:
        raise SyncError(f"cannot list {root}: {exc.strerror or exc}") from exc


def _searchable(full: str, _rel: str) -> None:
    """Raise PermissionError if the entries of directory ``full`` cannot be looked up
    (it lost its x bit): the scan then reports it as one it cannot list, and its robot
    copy is left alone, instead of its entries looking deleted."""
    os.lstat(os.path.join(full, "."))


def scan_local(
    root: str,
    rules: IgnoreRules,
    synced: dict[str, Synced],
    algorithm: str,
    *,
    lazy: bool = False,
    scanned: ScanResult | None = None,
) -> LocalTree:
    """The local tree with content hashes; the state vouches for files whose stat is unchanged.

    With ``lazy``, files the state does not know are left unhashed (hash ``""``,
    listed in ``unhashed``) for :meth:`LocalTree.hash_where_needed`. ``scanned``
    is a scan already made (by :func:`scan_tree`, or the connection master's).
    """
    result = scanned if scanned is not None else scan_tree(root, rules)
    items: dict[str, M.Listed] = {}
    stats: dict[str, Entry] = {}
    skipped = list(result.skipped)
    unhashed: set[str] = set()
    for path, e in result.entries.items():
        _add_entry(
            root, path, e, synced, algorithm, items, stats, skipped, unhashed if lazy else None
        )
    return LocalTree(items, stats, skipped, unhashed)


def scan_touched(
    root: str,
    rules: IgnoreRules,
    synced: dict[str, Synced],
    algorithm: str,
    paths: set[str],
    dirs: set[str],
) -> tuple[LocalTree, Callable[[str], bool], set[str] | None]:
    """The local tree restricted to ``paths``, the subtrees below ``dirs`` and their
    ancestors, the predicate saying which paths that scope covers and, when no
    directory is involved, the set of those paths (so callers need not test
    every path of the state against the predicate).

    Files the state does not know are left unhashed, as :func:`scan_local`'s ``lazy``
    leaves them, for :meth:`LocalTree.hash_where_needed`: the watch agent's burst of
    new files is then read once (to be sent, and hashed as it is), not twice."""
    from fetchsync.protocol.paths import is_within

    tree = LocalTree({}, {}, [])
    singles = set(paths) | set(dirs)
    for p in list(singles):
        singles.update(ancestors(p))
    for path in sorted(singles):
        _add_touched(root, path, rules, synced, algorithm, tree)
    # every touched directory bounds the scope, even one deleted since: its
    # synced entries below must be in the plan's view
    tops = sorted(d for d in dirs if not any(is_within(d, o) and d != o for o in dirs))
    for top in tops:
        _add_below(root, top, rules, synced, algorithm, tree)
    if not tops:
        return tree, singles.__contains__, singles

    def scope(path: str) -> bool:
        return path in singles or any(is_within(path, d) for d in tops)

    return tree, scope, None


def _add_touched(
    root: str,
    path: str,
    rules: IgnoreRules,
    synced: dict[str, Synced],
    algorithm: str,
    tree: LocalTree,
) -> None:
    """Add the entry at ``path`` to ``tree``, if there is one the rules keep."""
    try:
        e = stat_path(os.path.join(root, path))
    except OSError as exc:  # a directory above it lost its x bit, say
        tree.skipped.append((path, f"cannot read: {exc.strerror or exc}"))
        return
    if e is not None and not rules.ignored_any(path, e.kind == "d"):
        _add_entry(
            root, path, e, synced, algorithm, tree.items, tree.stats, tree.skipped, tree.unhashed
        )


def _add_below(
    root: str,
    top: str,
    rules: IgnoreRules,
    synced: dict[str, Synced],
    algorithm: str,
    tree: LocalTree,
) -> None:
    """Add what lies below ``top`` to ``tree``, if ``tree`` holds it as a directory."""
    e = tree.stats.get(top)
    if e is None or e.kind != "d":
        return
    try:
        result = scan(root, rules, is_temp=is_temp, start=top, on_dir=_searchable)
    except OSError as exc:
        tree.skipped.append((top, f"cannot list: {exc.strerror or exc}"))
        return
    tree.skipped.extend(result.skipped)
    for path, entry in result.entries.items():
        if tree.stats.get(path) != entry:  # else a touched path already added
            _add_entry(
                root,
                path,
                entry,
                synced,
                algorithm,
                tree.items,
                tree.stats,
                tree.skipped,
                tree.unhashed,
            )


def _add_entry(
    root: str,
    path: str,
    e: Entry,
    synced: dict[str, Synced],
    algorithm: str,
    items: dict[str, M.Listed],
    stats: dict[str, Entry],
    skipped: list[tuple[str, str]],
    unhashed: set[str] | None = None,
) -> None:
    """Add one scanned entry; a file the state cannot vouch for is hashed now, or,
    given ``unhashed``, left for later with hash ``""``."""
    if e.kind == "f":
        s = synced.get(path)
        if (
            s is not None
            and s.kind == "f"
            and s.size == e.size
            and s.mtime_ns == e.mtime_ns
            and s.ctime_ns == e.ctime_ns
            and s.ino == e.ino
        ):
            digest = s.hash
        elif unhashed is not None:
            digest = ""
            unhashed.add(path)
        else:
            try:
                digest = _hash_file(os.path.join(root, path), algorithm)
            except OSError as exc:
                skipped.append((path, VANISHED if _gone(exc) else f"cannot read: {exc.strerror}"))
                return
        items[path] = M.Listed(path, "f", e.mode, e.size, hash=digest)
    elif e.kind == "l":
        items[path] = M.Listed(path, "l", target=e.target)
    else:
        items[path] = M.Listed(path, "d", e.mode)
    stats[path] = e


def _same_file(a: os.stat_result, b: os.stat_result) -> bool:
    return (a.st_ino, a.st_dev, a.st_size, a.st_mtime_ns, a.st_ctime_ns) == (
        b.st_ino,
        b.st_dev,
        b.st_size,
        b.st_mtime_ns,
        b.st_ctime_ns,
    )


def _still_there(full: str, st: os.stat_result) -> bool:
    """Whether ``full`` still names the file ``st`` describes, unchanged (not replaced by a
    rename, not written). Raises FileNotFoundError if it is gone."""
    return _same_file(os.stat(full, follow_symlinks=False), st)


def _pause(attempt: int) -> None:
    if attempt:
        time.sleep(0.025 * (1 << attempt))  # 0.05, 0.1, 0.2, 0.4 s: bounded, lets a save finish


def _not_regular(full: str) -> OSError:
    return OSError(
        errno.EBUSY, "it is no longer a regular file; the robot keeps its previous version", full
    )


def read_stable(full: str, *, tries: int = READ_TRIES) -> tuple[bytes, Entry]:
    """Read a whole file that did not change while read and is still the file at ``full``.

    A file that changed (or was replaced) meanwhile is read again, up to ``tries``
    times, then ``OSError(EBUSY)``; one that is gone raises FileNotFoundError.
    The read stops at the size the file had when opened, so a file appended to
    faster than it is read does not keep it reading.
    """
    for attempt in range(tries):
        _pause(attempt)
        if read_hook is not None:
            read_hook(full, "open")
        fd = os.open(full, OPEN_FLAGS)
        try:
            before = os.fstat(fd)
            if not stat_mod.S_ISREG(before.st_mode):  # a FIFO or a device since the scan
                raise _not_regular(full)
            chunks = []
            left = before.st_size
            while left > 0:
                chunk = os.read(fd, left)  # one call, one copy for a whole file (they are < BIG)
                if not chunk:
                    break
                chunks.append(chunk)
                left -= len(chunk)
                if read_hook is not None:
                    read_hook(full, "read")
            after = os.fstat(fd)
        finally:
            os.close(fd)
        data = chunks[0] if len(chunks) == 1 else b"".join(chunks)
        if len(data) == after.st_size and _same_file(before, after) and _still_there(full, after):
            entry = entry_from_stat(after)
            assert entry is not None
            return data, entry
    raise _kept_changing(full, tries)


def _kept_changing(full: str, tries: int) -> OSError:
    return OSError(
        errno.EBUSY,
        f"it kept changing while it was read ({tries} tries); the robot keeps its previous version",
        full,
    )


class _ReadFailed(Exception):
    """Reading a laptop file failed with ``error``: told apart from the OSErrors of the
    batcher it is read into (a failure of its sender or packer thread, re-raised by its
    ``add``), which end the push as they are instead of being reported as the file's."""

    def __init__(self, error: OSError) -> None:
        super().__init__(str(error))
        self.error = error


@contextlib.contextmanager
def _reading() -> Iterator[None]:
    """Raise the OSErrors of the block as :class:`_ReadFailed`."""
    try:
        yield
    except OSError as exc:
        raise _ReadFailed(exc) from exc


@dataclass
class _Part:
    """An upload part on the robot: its id, and how far its content may reach there."""

    upload: str = ""
    extent: int = 0


def _unread(exc: OSError, path: str, local: LocalTree, report: Report) -> bool:
    """Report a file that could not be read to be sent. Returns True if it vanished: it is
    then dropped from ``local`` (a mirror of the laptop as it is now: the robot loses it
    too, into its trash, as the next push would do anyway)."""
    if _gone(exc):
        local.items.pop(path, None)
        local.stats.pop(path, None)
        report.skipped.append({"path": path, "reason": VANISHED})
        return True
    what = "" if exc.errno == errno.EBUSY else "cannot read: "
    report.errors.append({"path": path, "error": what + (exc.strerror or str(exc))})
    return False


def _synced_from(item: M.Listed, entry: Entry | None, now_ns: int) -> Synced:
    size = item.size if item.kind == "f" else 0
    if entry is None or item.kind != "f" or entry.size != item.size:
        return Synced(item.kind, item.mode, item.hash, item.target, size)
    if _racy(entry, now_ns):
        # too fresh to trust its stat (a same-size rewrite within the
        # timestamp granularity would not show): the next scan hashes it
        return Synced(item.kind, item.mode, item.hash, item.target, size)
    return Synced(
        item.kind,
        item.mode,
        item.hash,
        item.target,
        entry.size,
        entry.mtime_ns,
        entry.ctime_ns,
        entry.ino,
    )


# --------------------------------------------------------------------------- batching
SAMPLE_FROM = 64 * 1024  # smaller files are assumed compressible: testing costs more than it saves
# A batch with at most this much to compress gets zlib's level 6 (rsync -z's), the rest
# ISA-L's level 1. On real source level 6 is 19% smaller (rclcpp's tree: 819 vs
# 1,010 KB) for ~10x the CPU: 3 ms here for 64 KiB (a commit of real history, a save),
# while for a whole tree it would take longer than the bytes it saves take on Wi-Fi.
# bench/history.py --link wifi --baseline-rev: 15 commits of rclcpp 34.0 -> 32.7 KiB.
SMALL_BATCH = 64 * 1024
# Larger batches get level 6 too while the link is slower than zlib 6 can feed it, and
# then also files a sample shows shrink by only 3% or more (meshes, recordings: rsync -z
# compresses them too): on Wi-Fi the link, not zlib, is the bottleneck. Once the link has
# sat idle for FAST_IDLE of the time since the first batch went out, every batch sent
# answered while the next was still being compressed (the compressor slower than the
# link and the robot: loopback, a fast LAN), ISA-L's level 1 and the 85% rule take over
# for the rest of the push. Idle time is a measure a slow link cannot show however its
# early answers fall: the rule before (the raw bytes answered per second against half
# zlib 6's rate) saw a Wi-Fi link as fast whenever a batch of well-compressing text was
# answered early, and sent that batch at level 1: the bench's initial push (2,000 files,
# 40 MiB, wifi) sent +474 KB in one of 3 rounds.
# bench/acct.py (the bench's 300-file, 5 MiB tree, fetchsync's frames without SSH): an
# initial push 2,861,240 -> 2,583,851 bytes (-9.7%; rsync -z sent 2.4 MiB with SSH at
# c5f7845, fetchsync 2.7 MiB); the 2 MiB generated source alone 429 -> 332 KB.
SLOW_WORTH = 0.97
FAST_IDLE = 0.3  # the share of the time since the first batch the link sat idle: fast
FAST_AFTER = 2  # ... judged once this many batches were answered


def _text_order(items: list[tuple[M.Op, bytes, bool]], text: list[int]) -> list[int]:
    """The text parts of a batch in the order they go into its zlib stream: grouped by
    their file name's extension (path order within), so deflate's 32 KiB window meets
    the previous C++ file when it compresses a C++ file, not a launch file or a YAML.
    The bench's tree (2,000 files, 17 MB of text in 8 MiB batches): 4.898 -> 4.685 MB
    at level 6 (-213 KB, 0.9% of its initial push on Wi-Fi), for no CPU."""
    return sorted(text, key=lambda i: items[i][0].path.rpartition("/")[2].rpartition(".")[2])


def _blake2b(data: bytes) -> bytes:
    return hashlib.blake2b(data).digest()


def _binary(data: bytes) -> bool:
    """Whether content is binary: a NUL in its first 8 KiB (git's test)."""
    return b"\0" in data[:8192]


def _place(ops: list[M.Op], where: list[int], parts: list[bytes], *, z: int) -> int:
    """Point ``ops[where[k]]`` at ``parts[k]`` laid end to end in a blob (``z``: the
    blob's inflated compressed part); the blob's length."""
    pos = 0
    for i, data in zip(where, parts):
        ops[i] = ops[i].but(blob=(pos, len(data)), z=1) if z else ops[i].but(blob=(pos, len(data)))
        pos += len(data)
    return pos


def _pack_key(packed: list[bytes], *, level6: bool) -> bytes:
    """What determines a batch's zlib stream: the compressor and level, and its parts'
    bytes and boundaries (BLAKE2b: ~1 GB/s, a small price beside zlib 6's ~30 MB/s)."""
    key = hashlib.blake2b(b"zlib-6" if level6 else _fast().__name__.encode() + b"-1")
    for data in packed:
        key.update(len(data).to_bytes(8, "little"))
        key.update(data)
    return key.digest()


class SharedPacks:
    """The compressed streams of a fleet push's batches, shared by its robots' Syncers
    (and the records the state keeps of each content, :meth:`Syncer._kept_of`):
    robots in the same state send the same batches, compressed once. Keyed by exactly
    what makes the bytes (_pack_key), so a robot whose batch differs in one byte, one
    boundary or its level gets its own stream. A stream another robot is compressing is
    waited for, not made twice. Holds up to ``max_bytes`` of streams, the oldest
    dropped first (robots in the same state go at about the same pace).

    Issue 27: on Wi-Fi every batch is deflated at zlib 6 (~0.2 s of CPU per 5 MiB here),
    once per robot without this. Five robots in the same state pushed the bench's
    300-file 5 MiB tree (local robots, one process): compression CPU 0.99 -> 0.19 s,
    the laptop process's CPU 1.58 -> 0.78 s (3 streams made, 12 handed out again)."""

    def __init__(self, *, max_bytes: int = 64 * 1024 * 1024) -> None:
        self.max_bytes = max_bytes
        self.made = 0  # streams compressed
        self.reused = 0  # streams handed out again
        self.reads_shared = 0  # file reads handed out again
        self._lock = threading.Lock()
        self._done: collections.OrderedDict[bytes, list[bytes]] = collections.OrderedDict()
        self._size = 0
        self._making: dict[bytes, threading.Event] = {}
        # path -> (content, its entry, its hashes by name); id(content) -> the same
        self._reads: collections.OrderedDict[str, tuple[bytes, Entry, dict[str, bytes]]] = (
            collections.OrderedDict()
        )
        self._read_size = 0
        self._by_id: dict[int, tuple[bytes, dict[str, Any]]] = {}
        self._reading: dict[str, threading.Event] = {}
        self._once_making: set[tuple[int, str]] = set()  # (content's id, name) being made
        self._once_made = threading.Condition(self._lock)

    def read(self, full: str) -> tuple[bytes, Entry]:
        """:func:`read_stable` of ``full``, the same bytes for every robot of the fleet: a
        robot after the first gets the content read before when ``full`` still is that very
        file (an lstat: inode, size, mode, mtime and ctime, what read_stable checks its own
        read by), so each robot does not read and hash it again (issue 27: with the hashes
        below, 20 robots' ~37 ms of laptop CPU each on the bench's 300-file tree). Only a
        file whose mtime and ctime were at least RACY_NS old when read is shared: a write
        since then moves its ctime past what was kept. A read another robot is making is
        waited for, not made twice (robots go through the tree at about the same pace)."""
        while True:
            with self._lock:
                hit = self._reads.get(full)
                reading = None if hit is not None else self._reading.get(full)
                if hit is None and reading is None:
                    reading = self._reading[full] = threading.Event()
                    break
            if hit is None:
                assert reading is not None
                reading.wait()  # then look again: it is in, or it was not to be shared
                with self._lock:
                    hit = self._reads.get(full)
                if hit is None:
                    return read_stable(full)
            try:
                now = entry_from_stat(os.stat(full, follow_symlinks=False))
            except OSError:
                now = None  # read_stable says what is wrong, as without sharing
            if now is not None and now == hit[1]:
                with self._lock:
                    self.reads_shared += 1
                return hit[0], hit[1]
            return read_stable(full)  # changed since: this robot reads it as it is now
        try:
            data, entry = read_stable(full)
            if time.time_ns() - max(entry.mtime_ns, entry.ctime_ns) >= RACY_NS:
                with self._lock:
                    hashes: dict[str, Any] = {}
                    self._reads[full] = (data, entry, hashes)
                    self._by_id[id(data)] = (data, hashes)
                    self._read_size += len(data)
                    while self._read_size > self.max_bytes and len(self._reads) > 1:
                        _, (gone, _e, _h) = self._reads.popitem(last=False)
                        self._forget(gone)
        finally:
            with self._lock:
                del self._reading[full]
            reading.set()
        return data, entry

    def _forget(self, data: bytes) -> None:
        self._read_size -= len(data)
        held = self._by_id.get(id(data))
        if held is not None and held[0] is data:
            del self._by_id[id(data)]

    def hashed(self, name: str, data: bytes, make: Callable[[bytes], bytes]) -> bytes:
        """``make(data)``, made once for content a shared :meth:`read` handed out (by
        identity: the object is held while kept, so its id is not reused), else anew."""
        with self._lock:
            held = self._by_id.get(id(data))
        if held is None or held[0] is not data:
            return make(data)
        value: bytes | None = held[1].get(name)
        if value is None:  # two robots at once may both make it: the same bytes
            value = held[1][name] = make(data)
        return value

    def once(
        self, name: str, data: bytes, make: Callable[[bytes], V], otherwise: Callable[[], V]
    ) -> V:
        """``make(data)`` made once for content a shared :meth:`read` handed out, kept with
        it (by identity, as :meth:`hashed`); one another robot is making is waited for.
        Other content: ``otherwise()``. Issue 27: a file's digest, kept record and
        compressibility each took a BLAKE2b-keyed lookup per robot (3 locks, a key
        built, an LRU moved on); now one lookup each, by the content's id."""
        making = (id(data), name)
        with self._lock:
            held = self._by_id.get(id(data))
            if held is None or held[0] is not data:
                memo = None
            else:
                memo = held[1]
                while name not in memo and making in self._once_making:
                    self._once_made.wait()
                if name in memo:
                    value: V = memo[name]
                    return value
                self._once_making.add(making)
        if memo is None:
            return otherwise()
        try:
            value = make(data)
            with self._lock:
                memo[name] = value
        finally:
            with self._lock:
                self._once_making.discard(making)
                self._once_made.notify_all()
        return value

    def pack_key(self, packed: list[bytes], *, level6: bool) -> bytes:
        """:func:`_pack_key`'s identity of a batch's stream, from each part's BLAKE2b as
        :meth:`hashed` keeps it (length and digest per part: as exact)."""
        key = hashlib.blake2b(b"parts:zlib-6" if level6 else b"parts:" + _fast().__name__.encode())
        for data in packed:
            key.update(len(data).to_bytes(8, "little"))
            key.update(self.hashed("blake2b-512", data, _blake2b))
        return key.digest()

    def get(self, key: bytes, make: Callable[[], list[bytes]]) -> list[bytes]:
        while True:
            with self._lock:
                hit = self._done.get(key)
                if hit is not None:
                    self._done.move_to_end(key)
                    self.reused += 1
                    return hit
                making = self._making.get(key)
                if making is None:
                    making = self._making[key] = threading.Event()
                    break
            making.wait()  # then look again: it is in, or its maker failed
        try:
            parts = make()
            with self._lock:
                self.made += 1
                self._done[key] = parts
                self._size += sum(len(p) for p in parts)
                while self._size > self.max_bytes and len(self._done) > 1:
                    _, old = self._done.popitem(last=False)
                    self._size -= sum(len(p) for p in old)
        finally:
            with self._lock:
                del self._making[key]
            making.set()
        return parts


@dataclass
class _Packed:
    """A batch ready to go: its operations pointing into its blob, and the blob's parts
    (the zlib stream over the compressible data, then the raw rest)."""

    gen: int
    ops: list[M.Op]
    zparts: list[bytes]
    zpos: int
    raw: list[bytes]
    nbytes: int  # the content it carries, before compression
    tags: list[Any]


class _Batcher:
    """Packs operations into pipelined requests; collects results in order.

    Three stages, each on a thread of its own, so the laptop's CPU and the link work
    at once: the caller's thread reads files and adds operations; a packer thread
    compresses each batch (the compressible data as one zlib stream, the rest, such
    as meshes and archives, raw); a sender thread sends it, while the robot applies
    the one before. At most WINDOW batches are between the caller and the link
    (compressing, ready, being sent), so memory stays bounded.

    On Wi-Fi most batches are deflated at level 6 (~0.5 s of CPU for 8 MiB of meshes
    here); with packing and sending on one thread the link sat idle meanwhile: the
    bench's initial push of 2,000 files / 40 MiB (bench/run.py --link wifi, 23.2 MiB
    sent) left it idle ~1.3 of its 6.9 s (traced at 760409d).
    """

    def __init__(
        self,
        endpoint: Endpoint,
        *,
        policy: str,
        epoch: str,
        gen: int,
        progress: Progress | None,
        total: int,
        packs: SharedPacks | None = None,
        unsplit: set[str] | frozenset[str] = frozenset(),
    ) -> None:
        self.endpoint = endpoint
        self.unsplit = unsplit  # paths the robot could not apply: sent as they are
        self.conn = endpoint.conn
        self.policy, self.epoch, self.gen = policy, epoch, gen
        self.items: list[tuple[M.Op, bytes, bool]] = []
        self.tags: list[Any] = []
        self.raw_len = 0
        self.batches = 0
        # the batches sent and not answered yet, with their tags; each is let go of once
        # its answer is read
        self.sent: collections.deque[tuple[Pending[Applied], list[Any]]] = collections.deque()
        self.progress = progress
        self.total = total
        self.done = 0
        Job = tuple[int, list[tuple[M.Op, bytes, bool]], list[Any]]
        self._to_pack: queue.SimpleQueue[Job | None] = queue.SimpleQueue()
        self._to_send: queue.SimpleQueue[_Packed | None] = queue.SimpleQueue()
        self._room = threading.Semaphore(WINDOW)
        self._threads: list[threading.Thread] = []
        self._failure: BaseException | None = None
        self._mark: tuple[int, int] = (-1, -1)
        self.last: Applied | None = None
        self.stale = False
        # the link's speed, as the sender sees it sit idle (see FAST_IDLE)
        self.slow = True  # until shown otherwise: the links robots live on are
        self._first_sent = 0.0
        self._early: list[Pending[Applied]] = []  # the first FAST_AFTER batches' answers
        self._last_sent: Pending[Applied] | None = None
        self.idle = 0.0  # seconds the link sat idle, every batch sent answered
        # while the sender waits for a batch: since when, and the last batch sent then
        self._waiting: tuple[float, Pending[Applied] | None] | None = None
        self.packs = packs

    def add(self, op: M.Op, data: bytes = b"", tag: Any = None, *, packed: bool = False) -> None:
        """``packed``: ``data`` is compressed already (it travels raw)."""
        z = (
            not packed
            and bool(data)
            and self.conn.compress
            and (len(data) < SAMPLE_FROM or self._compressible(data))
        )
        self.items.append((op, data, z))
        self.tags.append(tag)
        self.raw_len += len(data)
        # the first batches are smaller, so the robot starts writing while the
        # next ones are read here, and is not idle waiting for a whole 8 MiB
        if (
            self.raw_len >= BATCH_BYTES >> FIRST_BATCHES_SMALLER.get(self.batches, 0)
            or len(self.items) >= BATCH_OPS
        ):
            self.flush()

    def _compressible(self, data: bytes) -> bool:
        """wire.compressible; in a fleet push once per content for all robots (link, issue
        27), a sample another robot is making waited for (robots go at the same pace)."""
        worth = SLOW_WORTH if self.slow else wire.WORTH_COMPRESSING
        if self.packs is None:
            return wire.compressible(data, worth=worth)
        packs = self.packs

        def by_content() -> bool:  # not a shared read (a file written just now)
            key = b"sample %r\0" % worth + packs.hashed("blake2b-512", data, _blake2b)
            said = packs.get(key, lambda: [b"y" if wire.compressible(data, worth=worth) else b""])
            return said == [b"y"]

        return packs.once(
            f"sample {worth!r}", data, lambda d: wire.compressible(d, worth=worth), by_content
        )

    def flush(self, *, last: bool = False) -> None:
        """Hand the operations added so far on as one batch; ``last``: none follow."""
        if self._failure is not None:
            # the packer or the sender failed: say so now, not after reading and
            # hashing the rest of the tree for batches that would never be sent
            raise self._failure
        if not self.items:
            return
        # each batch applied moves the robot's generation on by one: batch k
        # of this round may apply only if nobody else wrote in between
        gen = self.gen + self.batches
        self.batches += 1
        if last and not self._threads and self.raw_len <= INLINE_BATCH:
            # the round's only batch, a small one (a save, an edit): packed and sent on
            # this thread. Two threads started for it and two hand-overs cost a wifi save
            # ~0.8 ms before its bytes left, and ms more whenever the CPUs were busy
            # (FETCHSYNC_TRACE, bench/saveab.py). Small: its send fits the link's buffers,
            # where a larger one could block this thread on a dead link, which the
            # threaded path's _stalled() notices within LIVENESS_INTERVAL
            mark("push: the first batch read")
            job, self.items, self.tags, self.raw_len = (gen, self.items, self.tags), [], [], 0
            self._send(self._pack(*job))
            return
        if not self._threads:
            self._threads = [
                threading.Thread(target=loop, name=name, daemon=True)
                for loop, name in (
                    (self._pack_loop, "fetchsync-packer"),
                    (self._send_loop, "fetchsync-sender"),
                )
            ]
            for thread in self._threads:
                thread.start()
        if gen == self.gen:
            mark("push: the first batch read")
        while self._failure is None:
            if self._room.acquire(timeout=LIVENESS_INTERVAL):
                self._to_pack.put((gen, self.items, self.tags))
                break
            self._stalled()
        self.items, self.tags, self.raw_len = [], [], 0

    def _stalled(self) -> None:
        """Called every few seconds while waiting on the sender: if nothing moved
        either way meanwhile, make sure the link is alive (raises if not)."""
        mark = (self.conn.bytes_out, self.conn.bytes_in)
        if mark != self._mark:
            self._mark = mark
            return
        self.conn.check_link()

    def _pack_loop(self) -> None:
        while True:
            job = self._to_pack.get()
            if job is None:
                self._to_send.put(None)
                return
            packed = None
            if self._failure is None:
                try:
                    packed = self._pack(*job)
                except BaseException as exc:  # re-raised in answered(), on the caller's thread
                    self._failure = exc
            del job
            if packed is None:
                self._room.release()
            else:
                self._to_send.put(packed)

    def _send_loop(self) -> None:
        while True:
            packed = self._next_packed()
            if packed is None:
                return
            try:
                if self._failure is None:
                    self._send(packed)
            except BaseException as exc:  # re-raised in answered(), on the caller's thread
                self._failure = exc
            finally:
                del packed
                self._room.release()

    def _next_packed(self) -> _Packed | None:
        """The next batch to send, once packed. While the sender waits for it, the time
        the link sits idle with every batch sent answered adds to ``idle``: from when
        the wait began or the last batch's answer arrived (the connection's
        ``last_arrival``), whichever was later, to the batch. Waited for without
        waking up meanwhile: a fleet's senders polled every 3 ms (20 robots on Wi-Fi:
        ~330 wakeups a second each, ~23 us of laptop CPU apiece)."""
        try:
            return self._to_send.get_nowait()
        except queue.Empty:
            pass
        self._waiting = (time.monotonic(), self._last_sent)
        packed = self._to_send.get()
        idle = self._idle_waiting(time.monotonic())
        self._waiting = None  # then counted: the packer may add less, never twice
        self.idle += idle
        return packed

    def _idle_waiting(self, now: float) -> float:
        """How long the link has sat idle in the sender's wait going on (0 if none)."""
        waiting = self._waiting
        if waiting is None or waiting[1] is None or not waiting[1].answered():
            return 0.0
        return max(0.0, now - max(waiting[0], self.conn.last_arrival))

    def _pack(self, gen: int, items: list[tuple[M.Op, bytes, bool]], tags: list[Any]) -> _Packed:
        ops = [op for op, _, _ in items]
        text: list[int] = []
        binary: list[int] = []
        raws: list[int] = []
        for i, (_, data, z) in enumerate(items):
            if not data:
                continue
            if not z:
                raws.append(i)
            elif _binary(data):
                binary.append(i)
            else:
                text.append(i)
        # one zlib stream over the compressible parts, made without joining them: the
        # text first (_text_order), then the binary data (see _deflate)
        text = _text_order(items, text)
        packed = [items[i][1] for i in text + binary]
        if binary and self.slow and self.endpoint.stl:
            self._split_meshes(ops, text, binary, packed)
        zpos = _place(ops, text + binary, packed, z=1)
        raw = [items[i][1] for i in raws]
        _place(ops, raws, raw, z=0)
        nbytes = zpos + sum(len(data) for data in raw)
        zparts: list[bytes] = []
        if packed:
            self._measure_link()
            level6 = zpos <= SMALL_BATCH or self.slow
            if self.packs is None:
                zparts = self._deflate(packed, level6=level6)
            else:
                zparts = self.packs.get(
                    self.packs.pack_key(packed, level6=level6),
                    lambda: self._deflate(packed, level6=level6),
                )
        return _Packed(gen, ops, zparts, zpos, raw, nbytes, tags)

    def _split_meshes(
        self, ops: list[M.Op], text: list[int], binary: list[int], packed: list[bytes]
    ) -> None:
        """Binary STLs whole in the batch go with their records split (protocol.stl): the
        bench's initial push on Wi-Fi 24.19 -> 23.72 MB (0.993x -> 0.974x rsync's bytes;
        its meshes 12.55 -> 12.07 MB at ISA-L's level 1, ~0.1 s of the link, for 51 ms of
        this thread's CPU), real description packages 6-26% fewer bytes of meshes
        (PR2/pr2_common 2.11 -> 1.70 MB, husky 1.35 -> 1.01 MB). Only while the link is the
        bottleneck (``slow``): on a fast one this thread is, and the bytes matter less.
        Its count in the header always holds a NUL (SIZE_MAX): _deflate still sees it
        as binary."""
        for k, i in enumerate(binary, start=len(text)):
            if ops[i].source == M.SRC_DATA and ops[i].path not in self.unsplit:
                split = stl.split(packed[k])
                if split is not None:
                    ops[i] = ops[i].but(source=M.SRC_STL)
                    packed[k] = split

    def _send(self, b: _Packed) -> None:
        progress, base, nbytes = self.progress, self.done, b.nbytes

        def sent(k: int, n: int) -> None:  # the batch's share of the total, as its frame goes out
            if progress is not None:
                progress(base + nbytes * k // max(n, 1), self.total)

        pending = self.endpoint.send_sync(
            b.ops,
            policy=self.policy,
            epoch=self.epoch,
            gen=b.gen,
            zpart=(sum(len(p) for p in b.zparts), b.zpos) if b.zparts else None,
            blob_parts=b.zparts + b.raw,
            sent=sent,
        )
        self.sent.append((pending, b.tags))
        if self._last_sent is None:
            mark("push: the first batch sent")
        self._last_sent = pending
        if len(self._early) < FAST_AFTER:
            self._early.append(pending)
        if not self._first_sent:
            self._first_sent = time.monotonic()
        self.done += nbytes

    def _deflate(self, packed: list[bytes], *, level6: bool) -> list[bytes]:
        """``packed`` (its text, then its binary data) as one zlib stream, in parts: at
        level 6, or ISA-L's level 1. At level 6 the binary data (``_binary``) goes at
        ISA-L's level 1 all the same, in the same stream: its deflate blocks follow the
        text's, and the stream's checksum is made here over both.

        On binary data (meshes, maps, recordings) ISA-L's level 1 is as small as zlib's
        level 6 for a tenth of its CPU; on text it is 7-10% larger. The bench's tree
        (2,000 files, 40 MiB; 8 MiB streams): text 17.0 MB -> 4.90 MB at level 6 in
        0.83 s of CPU; binary 24.9 MB -> 19.28 MB at level 6 in 1.06 s, 19.27 MB at
        ISA-L's level 1 in 0.10 s."""
        split = next((i for i, data in enumerate(packed) if _binary(data)), len(packed))
        if not level6 or split == 0:
            deflate = _fast().compressobj(1)
            zparts = [deflate.compress(data) for data in packed]
            zparts.append(deflate.flush())
            return zparts
        head = zlib.compressobj(6)
        zparts = [head.compress(data) for data in packed[:split]]
        if split == len(packed):
            zparts.append(head.flush())
        else:
            zparts.append(head.flush(zlib.Z_SYNC_FLUSH))  # byte-aligned, not the last block
        if split < len(packed):
            tail = _fast().compressobj(1, zlib.DEFLATED, -15)  # raw deflate: no header
            zparts += [tail.compress(data) for data in packed[split:]]
            zparts.append(tail.flush())
            check = zlib.adler32(b"")
            for data in packed:
                check = zlib.adler32(data, check)
            zparts.append(check.to_bytes(4, "big"))
        return zparts

    def _measure_link(self) -> None:
        """Decide ``slow`` (see FAST_IDLE), once for the push: at level 1 the compressor
        keeps ahead, the link does not sit idle any more, and the reason is gone."""
        if not self.slow or len(self._early) < FAST_AFTER or not self._early[-1].answered():
            return
        now = time.monotonic()
        if self.idle + self._idle_waiting(now) >= FAST_IDLE * (now - self._first_sent):
            self.slow = False
            log.debug("fast link: idle %.3f s since the first batch", self.idle)

    def _drain(self) -> None:
        if self._threads:
            self._to_pack.put(None)
            for thread in self._threads:
                while thread.is_alive():
                    thread.join(LIVENESS_INTERVAL)
                    if thread.is_alive() and self._failure is None:
                        self._stalled()
            self._threads = []
        if self._failure is not None:
            raise self._failure

    def close(self) -> None:
        """End the threads once they are done with what they hold, when the caller gives up
        on the round (an exception): what is queued is dropped, not sent."""
        if self._threads:
            if self._failure is None:
                self._failure = SyncError("the push was abandoned")
            self._to_pack.put(None)
            self._threads = []

    def answered(self, *, wait: bool = False) -> list[tuple[Any, M.Result]]:
        """The results of the batches answered since the last call, in order (with ``wait``,
        of every batch sent, once the last is out).
        Each batch is let go of once read, so a push of 100,000 operations does not hold
        them all, nor all their answers.

        ``last`` then holds the last answer that applied, ``stale`` whether one was refused
        as stale (someone else wrote to the robot meanwhile; later batches are refused too).
        """
        if wait:
            self._drain()
        out: list[tuple[Any, M.Result]] = []
        while self.sent:
            pending, tags = self.sent[0]
            if not wait and not pending.answered():
                break
            applied = pending.wait()
            self.sent.popleft()
            if applied.stale:
                self.stale = True
                continue
            self.last = applied
            out.extend(zip(tags, applied.results))
        return out


# --------------------------------------------------------------------------- push
class Syncer:
    """Pushes a local tree to one remote workspace over a connection, keeping state."""

    def __init__(
        self,
        conn: Connection,
        state: State,
        *,
        local_root: str,
        remote_workspace: str,
        rules: IgnoreRules,
        policy: str = "preserve",
    ) -> None:
        self.endpoint = Endpoint(conn)
        self.state = state
        self.local_root = local_root
        self.remote_workspace = remote_workspace
        self.rules = rules
        self.policy = policy
        self.algorithm = conn.algorithm
        self.opened: Opened | None = None  # the workspace, once opened in this session
        self._synced: dict[str, Synced] | None = None  # the state's entries, kept between calls
        self._signed: set[str] | None = None  # paths whose state entry holds a signature
        # upload parts this session abandoned (id -> how far they reach): a later upload
        # at least as long overwrites one instead of leaving it on the robot until the
        # session ends (the watch agent's sessions last hours)
        self._spare_uploads: dict[str, int] = {}
        self.deletions = Deletions()  # the chain of deleting pushes just before this one
        self._deleting = 0  # files the push under way deletes
        self.packs: SharedPacks | None = None  # a fleet push's streams, shared by its robots

    @property
    def conn(self) -> Connection:
        """The connection to the robot (a new one may be set: a new session)."""
        return self.endpoint.conn

    @conn.setter
    def conn(self, conn: Connection) -> None:
        self.endpoint = Endpoint(conn)

    def _send_open(self, *, readonly: bool = False) -> Pending[Opened]:
        """``readonly``: the endpoint neither creates the workspace nor locks it nor
        rewrites its index, and refuses writes (a dry run)."""
        return self.endpoint.send_open(
            self.remote_workspace, rules=self.rules, create=not readonly, readonly=readonly
        )

    def _open_readonly(self) -> bool:
        """Open the workspace read-only (a dry run); False if it does not exist yet."""
        try:
            self.opened = self._send_open(readonly=True).wait()
        except RemoteError as exc:
            if "does not exist" in str(exc):
                return False
            raise
        return True

    def reload_entries(self) -> None:
        """Drop the state's entries held in memory and load them again in one go (the
        watch agent's compaction after a large sync: see Agent._compact)."""
        if self._synced is not None:
            self._synced = None
            gc.collect()
            self._load_synced()

    def _load_synced(self) -> dict[str, Synced]:
        if self._synced is None:
            synced = self.state.entries()
            if self.state.get("algorithm") not in ("", self.algorithm):
                synced = {}
            self._synced = synced
        return self._synced

    def push(
        self,
        *,
        dry_run: bool = False,
        progress: Progress | None = None,
        scanned: ScanResult | None = None,
        scanner: Callable[[], ScanResult] | None = None,
        confirm_deletions: bool = False,
        ahead_ok: bool = True,
    ) -> Report:
        """Make the robot's tree identical to the local one, after asking it what changed there.

        ``scanned``: the local tree scanned (by :func:`scan_tree`) since the last push,
        such as the CLI's scan made while the robot's endpoint starts. ``scanner``: what
        scans it instead of :func:`scan_tree` (the resident's kept scan), called once the
        robot has been asked for its changes, so both work at once.
        ``confirm_deletions``: delete most of the robot's files if that is what the
        plan says (else :class:`MassDeletionError`, see :func:`refuse_mass_deletion`).
        ``ahead_ok``: the local changes may go before the robot's answer (see
        :meth:`_push_ahead`).
        """
        t0 = time.monotonic()
        report = Report("push", dry_run=dry_run)
        b_out, b_in = self.conn.bytes_out, self.conn.bytes_in
        self._synced = self._signed = None  # reread: another process may have pushed since
        epoch, gen = self.state.epoch, self.state.gen
        open_req, list_req = self._send_open_and_list(dry_run=dry_run)
        synced = self._load_synced()  # while the robot answers
        if scanned is None:
            scanned = scanner() if scanner is not None else scan_tree(self.local_root, self.rules)
            mark("push: scanned")
        excluded = LocalRules(self.local_root, self.rules)
        ahead = None
        # the local changes if the robot reports none (what _local_changes then says
        # again: computed once, ~2.5 ms of 2,547 paths after a no-op's listing)
        undrifted: set[str] | None = None
        if (
            ahead_ok
            and open_req is not None
            and not dry_run
            and self.policy == "preserve"
            and synced
            and epoch
        ):
            undrifted = _local_changes(
                scanned, synced, Listing(epoch=epoch, gen=gen, full=False), epoch, gen, excluded
            )
            ahead = self._push_ahead(
                undrifted, synced, open_req, epoch, gen, progress, confirm_deletions
            )
        if open_req is not None and self.opened is None:  # not waited for ahead
            self.opened = open_req.wait()
        listing = list_req.wait() if list_req is not None else Listing(epoch="", gen=-1)
        mark("push: the robot's listing in")
        if ahead is not None:
            report, stale = ahead
            if stale or listing.drifted or (listing.epoch, listing.gen) != (epoch, gen):
                # another writer, or the robot changed while it was away from this
                # laptop: push over what it holds now (each write sent ahead checked
                # its own path there; none after a stale one applies: Server._chained)
                if stale:  # refused: what it would delete is planned and counted again
                    self.deletions.files = max(0, self.deletions.files - self._deleting)
                report.add(
                    self.push(
                        progress=progress, confirm_deletions=confirm_deletions, ahead_ok=False
                    )
                )
                report.seconds = time.monotonic() - t0
                return report
            else:
                report.bytes_sent = self.conn.bytes_out - b_out
                report.bytes_received = self.conn.bytes_in - b_in
                report.seconds = time.monotonic() - t0
                return report
        if dry_run:
            differing = None
        elif undrifted is not None and not listing.drifted:  # as _local_changes says
            differing = undrifted if (listing.epoch, listing.gen) == (epoch, gen) else None
        else:
            differing = _local_changes(scanned, synced, listing, epoch, gen, excluded)
        if differing is None:
            self._push_listed(
                scanned,
                synced,
                listing,
                report,
                dry_run=dry_run,
                progress=progress,
                confirm_deletions=confirm_deletions,
            )
        else:
            # the robot holds what we last synced: only the paths that changed here
            # since need a plan, as the watch agent pushes them
            self._opened_at(epoch, gen)
            if differing:
                report = self.push_paths(
                    differing, progress=progress, confirm_deletions=confirm_deletions
                )
        report.bytes_sent = self.conn.bytes_out - b_out
        report.bytes_received = self.conn.bytes_in - b_in
        report.seconds = time.monotonic() - t0
        return report

    def _send_open_and_list(
        self, *, dry_run: bool
    ) -> tuple[Pending[Opened] | None, Pending[Listing] | None]:
        """Open the workspace (unless open) and ask for the robot's changes since the state's
        generation (its whole tree if the state is empty). Returns the answers on their
        way (no listing: a dry run's workspace does not exist, it lists empty)."""
        fresh = (
            self.state.epoch != ""
            and self.state.get("algorithm") in ("", self.algorithm)
            and self.state.has_entries()
        )
        exists = self._open_readonly() if dry_run else True
        open_req = self._send_open() if self.opened is None and not dry_run else None
        since = (self.state.epoch, self.state.gen) if fresh else None
        list_req = self.endpoint.send_listing(since=since) if exists else None
        return open_req, list_req

    def _push_ahead(
        self,
        differing: set[str] | None,
        synced: dict[str, Synced],
        open_req: Pending[Opened],
        epoch: str,
        gen: int,
        progress: Progress | None,
        confirm_deletions: bool,
    ) -> tuple[Report, bool] | None:
        """Push the paths changed here since the state's generation while the robot still
        works out its own changes (its listing): the writes queue behind the listing on
        the robot, which needs ~30 ms for 2,000 files, instead of the laptop's planning,
        reading and delta starting only once it arrived. Only when the robot's open
        answered the state's generation (no other writer since); each write still checks
        on the robot that its path holds what the state says was last synced there (a
        robot-side edit is kept aside, never lost). The caller pushes again if the
        listing then says the robot changed, or a batch was refused as stale. Wifi,
        2,000-file tree, load 3-5, medians of 5 interleaved: the robot idle between its
        listing's answer and the sync request 51.7 -> 0.3 ms (a line inserted atop a 2
        MiB file; push in-process 167 -> 110 ms), 31.3 -> 0.2 ms (one small edit; 123 ->
        82 ms). ``differing``: the local changes if the robot has none (see
        :func:`_local_changes`). None (nothing sent) unless a few; else (the report,
        whether a batch was refused as stale)."""
        if not differing:
            return None
        self.opened = opened = open_req.wait()
        if (opened.epoch, opened.gen) != (epoch, gen):
            return None  # another writer: the listing will say what the robot holds
        return self._push_touched(
            set(differing),
            set(),
            synced,
            progress=progress,
            confirm_deletions=confirm_deletions,
        )

    def _push_listed(
        self,
        scanned: ScanResult,
        synced: dict[str, Synced],
        listing: Listing,
        report: Report,
        *,
        dry_run: bool,
        progress: Progress | None,
        confirm_deletions: bool,
    ) -> None:
        """Push against the robot's tree as ``listing`` says it is (it drifted since the
        state's generation, or the state is empty): the whole local tree is planned."""
        remote = self._apply_listing(listing, synced)
        local = scan_local(
            self.local_root, self.rules, synced, self.algorithm, lazy=True, scanned=scanned
        )
        local.hash_where_needed(self.local_root, remote, self.algorithm)
        _report_skipped(local, report)
        self._converge(
            local,
            remote,
            synced,
            listing.epoch,
            listing.gen,
            report,
            dry_run=dry_run,
            progress=progress,
            confirm_deletions=confirm_deletions,
            listed=remote if listing.full else [e.path for e in listing.entries],
        )

    def push_paths(
        self,
        paths: Iterable[str],
        dirs: Iterable[str] = (),
        *,
        progress: Progress | None = None,
        confirm_deletions: bool = False,
    ) -> Report:
        """Push only what changed at ``paths`` and below ``dirs`` (the watch agent's fast path).

        No listing from the robot: the plan starts from the last-synced state,
        and each operation's expectation is checked there. If another writer
        is detected, this falls back to a full :meth:`push`.
        """
        synced = self._load_synced()
        if not synced or self.state.epoch == "":
            return self.push(progress=progress, confirm_deletions=confirm_deletions)
        if self.opened is None:  # a new connection (the agent back online): no listing
            self.opened = self._send_open().wait()
        paths, dirs = set(paths), set(dirs)
        if "" in dirs:
            return self.push(progress=progress, confirm_deletions=confirm_deletions)
        report, stale = self._push_touched(
            paths, dirs, synced, progress=progress, confirm_deletions=confirm_deletions
        )
        if stale:
            return self.push(progress=progress, confirm_deletions=confirm_deletions)
        return report

    def _push_touched(
        self,
        paths: set[str],
        dirs: set[str],
        synced: dict[str, Synced],
        *,
        progress: Progress | None,
        confirm_deletions: bool,
    ) -> tuple[Report, bool]:
        """:meth:`push_paths` once the workspace is open: the report, and whether the
        robot refused the push as stale (another writer: nothing was written)."""
        t0 = time.monotonic()
        report = Report("push")
        b_out, b_in = self.conn.bytes_out, self.conn.bytes_in
        paths.discard("")
        if not paths and not dirs:
            return report, False
        local, scope, only = scan_touched(
            self.local_root, self.rules, synced, self.algorithm, paths, dirs
        )
        if only is not None:
            remote = {p: synced[p].listed(p) for p in only if p in synced}
        else:
            remote = {p: s.listed(p) for p, s in synced.items() if scope(p)}
        local.hash_where_needed(self.local_root, remote, self.algorithm)
        _report_skipped(local, report)
        stale = self._converge(
            local,
            remote,
            synced,
            self.state.epoch,
            self.state.gen,
            report,
            scope=scope,
            scope_paths=only,
            progress=progress,
            confirm_deletions=confirm_deletions,
        )
        report.bytes_sent = self.conn.bytes_out - b_out
        report.bytes_received = self.conn.bytes_in - b_in
        report.seconds = time.monotonic() - t0
        return report, stale

    def _converge(
        self,
        local: LocalTree,
        remote: dict[str, M.Listed],
        synced: dict[str, Synced],
        epoch: str,
        gen: int,
        report: Report,
        *,
        dry_run: bool = False,
        progress: Progress | None = None,
        scope: Callable[[str], bool] | None = None,
        scope_paths: set[str] | None = None,
        listed: Iterable[str] | None = None,
        confirm_deletions: bool = False,
    ) -> bool:
        """Plan, send and settle rounds until the robot holds ``local`` (within ``scope``),
        then advance the state. Returns True if an incremental run met another writer.

        ``listed``: the paths the robot's listing reported (all, after a full one),
        which its index does not vouch for; those found identical are adopted there."""
        if self._signed is None:
            self._signed = self.state.signed_paths()
        rnd = Round(self, local, remote, synced, epoch, gen, report, scope=scope, listed=listed)
        self._deleting = 0
        try:
            return self._rounds(
                rnd, synced, dry_run, progress, scope, scope_paths, confirm_deletions
            )
        finally:
            if self._deleting:  # a chain of deletions goes on from the end of this push
                self.deletions.ended = time.monotonic()

    def _rounds(
        self,
        rnd: Round,
        synced: dict[str, Synced],
        dry_run: bool,
        progress: Progress | None,
        scope: Callable[[str], bool] | None,
        scope_paths: set[str] | None,
        confirm_deletions: bool,
    ) -> bool:
        """:meth:`_converge`'s rounds: plan, check the deletions, send, settle, commit."""
        for n in range(MAX_ROUNDS):
            planned = rnd.plan()
            if n == 0 and not dry_run:
                self._check_deletions(
                    planned,
                    rnd.remote,
                    synced,
                    confirmed=confirm_deletions,
                    scoped=scope is not None,
                )
            if dry_run:
                rnd.report_ahead(planned)
                break
            if not planned:
                break
            again = rnd.run(planned, progress)
            if rnd.stale:
                if scope is not None:
                    rnd.commit()
                    return True
                # another writer touched the robot: start again from what it holds now
                rnd.relist()
                continue
            if not again:
                break
        if not dry_run and rnd.report.rounds:  # no round: the first plan was empty already
            rnd.check_converged()
        rnd.take_identical(adopt=not dry_run)
        rnd.forget_gone(scope_paths)
        if not dry_run:
            rnd.commit()
        return False

    def _check_deletions(
        self,
        planned: list[Planned],
        remote: dict[str, M.Listed],
        synced: dict[str, Synced],
        *,
        confirmed: bool,
        scoped: bool = False,
    ) -> int:
        """The mass-deletion guard (:func:`refuse_mass_deletion`), counting the files
        deleted in the chain of pushes just before too (:attr:`deletions`): the watch
        agent sees an ``rm -rf`` as several batches, each of which may be small. A push
        joins the chain when it starts within RECENT seconds of the end of the chain's
        last push, however long that push took (a slow link, a busy machine). The chain
        is recorded in the state before its files go, for the next process (the watch
        agent restarted between two pieces of an rm -rf: each new count let half of what
        was left go). Returns the files this push deletes."""
        chain = self.deletions
        window = KEPT if chain.resumed else RECENT
        chain.resumed = False
        before = chain.files
        if time.monotonic() - chain.ended >= window:
            chain.files = 0
        if confirmed:
            chain.files = 0
            doomed = 0
        else:
            doomed = refuse_mass_deletion(
                planned, remote, synced, recent=chain.files, scoped=scoped
            )
            chain.files += doomed
            self._deleting = doomed
        if doomed or chain.files != before:
            self.state.commit(meta={"deletions": f"{chain.files} {time.time()}"})
        return doomed

    def _commit(
        self,
        upserts: dict[str, tuple[Synced, bytes | None]],
        deletes: set[str],
        new_synced: dict[str, Synced],
        epoch: str,
        gen: int,
    ) -> None:
        if self._signed is not None and self._synced is not None:
            for path, (s, sig) in upserts.items():
                old = self._synced.get(path)
                # State.commit keeps a stored signature only while the content is the same
                if sig is None and (old is None or old.hash != s.hash):
                    self._signed.discard(path)
                elif sig is not None:
                    self._signed.add(path)
            self._signed.difference_update(deletes)
        try:
            self.state.commit(
                upserts=((p, s, sig) for p, (s, sig) in upserts.items()),
                deletes=deletes,
                meta={"epoch": epoch, "gen": str(gen), "algorithm": self.algorithm},
            )
        except BaseException:  # the state is as it was (a full disk): read it again
            self._synced = self._signed = None
            raise
        self._synced = new_synced
        self._opened_at(epoch, gen)

    def _opened_at(self, epoch: str, gen: int) -> None:
        """The robot's workspace is now at (``epoch``, ``gen``)."""
        self.opened = (
            dataclasses.replace(self.opened, epoch=epoch, gen=gen)
            if self.opened is not None
            else Opened(self.remote_workspace, epoch, gen)
        )

    def _robot_signatures(
        self,
        planned: list[Planned],
        remote: dict[str, M.Listed],
        robot_sigs: dict[str, bytes],
        whole_only: set[str],
    ) -> list[Planned]:
        """Ask the robot to sign its copies of large files we would otherwise send whole.

        That happens when the state has no signature for them: a first push
        onto a tree someone else put there, or after a base mismatch.
        """
        wanted = [p for p in planned if _robot_could_sign(p, remote, whole_only)]
        if not wanted:
            return planned
        answers = self.endpoint.sigs([p.op.path for p in wanted])
        upgraded: dict[str, Planned] = {}
        for p, ans in zip(wanted, answers):
            r = remote[p.op.path]
            if isinstance(ans, Failed) or ans.hash != r.hash:
                continue
            robot_sigs[p.op.path] = ans.signature
            upgraded[p.op.path] = Planned(p.op.but(source=M.SRC_DELTA, base=r.hash), DELTA, p.item)
        return [upgraded.get(p.op.path, p) if p.op.kind == M.WRITE else p for p in planned]

    def _apply_listing(self, listing: Listing, synced: dict[str, Synced]) -> dict[str, M.Listed]:
        return listing.tree(lambda: {p: s.listed(p) for p, s in synced.items()})

    def _send_op(
        self,
        batcher: _Batcher,
        p: Planned,
        local: LocalTree,
        report: Report,
        robot_sigs: dict[str, bytes],
    ) -> bool:
        """Add one planned operation, reading its content now. Returns True if the local
        file vanished meanwhile (it is then dropped from ``local``: a delete to plan)."""
        op = p.op
        if op.kind != M.WRITE or p.how == COPY:
            sig = self.state.signature(op.from_path) if p.how == COPY and op.size > 0 else None
            batcher.add(op, tag=(p, sig))
            return False
        full = os.path.join(self.local_root, op.path)
        if op.size > BIG:
            try:
                self._send_big(batcher, p, full, report, local)
            except _ReadFailed as failed:  # not the batcher's: its failures are the push's
                return _unread(failed.error, op.path, local, report)
            return False
        try:
            data, entry = read_stable(full) if self.packs is None else self.packs.read(full)
        except OSError as exc:
            return _unread(exc, op.path, local, report)
        self._send_content(batcher, p, data, entry, local, robot_sigs)
        return False

    def _send_content(
        self,
        batcher: _Batcher,
        p: Planned,
        data: bytes,
        entry: Entry,
        local: LocalTree,
        robot_sigs: dict[str, bytes],
    ) -> None:
        """Add a file's write with the content just read: as a delta where planned and
        smaller, else whole (also if it changed since the scan: sent as it is now)."""
        op = p.op
        digest = (
            self._hex(data)
            if self.packs is None
            else self.packs.once("hex " + self.algorithm, data, self._hex, lambda: self._hex(data))
        )
        # a large text file's new signature comes from its delta's pass when it goes as one
        by_delta = p.how == DELTA and len(data) > M.ZDICT_BASE_MAX and b"\0" not in data[:8192]
        sig = None if by_delta else self._kept_of(data)
        if digest != op.hash or len(data) != op.size:
            # changed since the scan: send what is there now, whole
            op = op.but(hash=digest, size=len(data), source=M.SRC_DATA, base="")
            p = Planned(op, WHOLE, M.Listed(op.path, "f", entry.mode, len(data), hash=digest))
            local.items[op.path] = p.item  # type: ignore[assignment]
        local.stats[op.path] = entry
        if p.how == DELTA:
            stored = robot_sigs.get(op.path) or self.state.signature(op.path)
            if stored is not None and stored[:4] == BASE_MAGIC:
                if by_delta:
                    sig, by_delta = self._kept_of(data), False
                sent, stored = self._from_base(batcher, p, data, stored, sig)
                if sent:
                    return
            if stored is not None:
                base_sig = delta_mod.Signature.from_bytes(stored)
                if (
                    by_delta
                    and base_sig.algorithm == self.algorithm
                    and (base_sig.params == delta_mod.DEFAULT_PARAMS)
                ):
                    found, new_sig = delta_mod.delta_and_signature(data, base_sig)
                    sig, by_delta = new_sig.to_bytes(), False
                else:
                    found = delta_mod.delta(data, base_sig)
                d = delta_mod.encode_delta(found)
                if by_delta:
                    sig = self._kept_of(data)
                if len(d) < len(data):
                    batcher.total -= op.size - len(d)  # the progress counts what travels
                    batcher.add(op, d, tag=(p, sig))
                    return
            op = op.but(source=M.SRC_DATA, base="")
            p = Planned(op, WHOLE, p.item)
        if by_delta:
            sig = self._kept_of(data)
        batcher.add(op, data, tag=(p, sig))

    def _kept_of(self, data: bytes) -> bytes | None:
        """What the state keeps of content sent, to send its next version by: text up to
        ZDICT_BASE_MAX bytes itself (deflated: a ``BASE_MAGIC`` record), larger text its
        delta signature, binary files (a NUL in the first 8 KiB, git's test: meshes,
        recordings, images) nothing: they are rarely edited in place, their lines (the
        chunk boundaries) are noise, and signing them was a third of an initial push's
        CPU. If one does change, the robot signs its copy on request (a round trip).

        In a fleet push the record is made once per content for all robots (``packs``:
        keyed by the content's BLAKE2b and this push's algorithm, all a record depends
        on). Issue 27: 12 robots, the bench's 300-file tree on wifi, this was ~0.1 s of
        each robot's ~0.15 s of laptop CPU after its connection opened."""
        if not data or _binary(data):
            return None
        packs = self.packs
        if packs is None:
            return self._make_kept(data)

        def by_content() -> bytes | None:  # not a shared read (a file written just now)
            key = b"kept\0" + self.algorithm.encode() + b"\0"
            key += packs.hashed("blake2b-512", data, _blake2b)
            parts = packs.get(key, lambda: [k] if (k := self._make_kept(data)) else [])
            return parts[0] if parts else None

        return packs.once("kept " + self.algorithm, data, self._make_kept, by_content)

    def _hex(self, data: bytes) -> str:
        return hashing.digest(self.algorithm, data).hex()

    def _make_kept(self, data: bytes) -> bytes | None:
        if len(data) <= M.ZDICT_BASE_MAX:
            packed: bytes = _fast().compress(data, 1)
            return BASE_MAGIC + packed
        if len(data) >= SIG_MIN:
            return delta_mod.signature(data, algorithm=self.algorithm).to_bytes()
        return None

    def _from_base(
        self, batcher: _Batcher, p: Planned, data: bytes, record: bytes, sig: bytes | None
    ) -> tuple[bool, bytes | None]:
        """Send ``data`` deflated with the content the robot holds (kept by the state in
        ``record``) as the dictionary, where the robot takes that: (True, None). Else
        (False, the signature of that content to send a delta by: an older robot), or
        (False, None) when the record's content is not what the robot holds (by hash):
        the laptop does not know it then, and the file goes whole."""
        op = p.op
        try:
            base = zlib.decompress(record[4:])
        except zlib.error:
            return False, None
        if len(base) > M.ZDICT_BASE_MAX or hashing.digest(self.algorithm, base).hex() != op.base:
            return False, None
        if not self.endpoint.zdict or len(data) > M.ZDICT_SIZE_MAX:
            return False, delta_mod.signature(base, algorithm=self.algorithm).to_bytes()
        deflate = zlib.compressobj(9, zlib.DEFLATED, -15, 9, zdict=base)
        packed = deflate.compress(data) + deflate.flush()
        if len(packed) >= len(data):
            return False, None
        batcher.total -= op.size - len(packed)
        batcher.add(op.but(source=M.SRC_ZDICT), packed, tag=(p, sig), packed=True)
        return True, None

    def _send_big(
        self, batcher: _Batcher, p: Planned, full: str, report: Report, local: LocalTree
    ) -> None:
        """A large file travels in pieces to the robot's upload area, then is renamed into place.

        The robot renames the upload only if it matches the hash of what was read, and it
        is sent only if the file did not change while read (nor was replaced), so the
        robot never holds half of one version and half of another. A file that changed
        is read and uploaded again, up to READ_TRIES times; the pieces of an attempt
        overwrite the last one's in the same upload, and a part left by a file that kept
        changing or vanished is reused by a later upload of this session (see
        ``_spare_uploads``). A read that fails raises :class:`_ReadFailed` (the OSError
        :func:`read_stable` would raise); the batcher's own failures (the link's, its
        threads') go up as they are, not as this file's.
        """
        part = _Part()
        done = False
        try:
            for attempt in range(READ_TRIES):
                _pause(attempt)
                with _reading():
                    if read_hook is not None:
                        read_hook(full, "open")
                    fd = os.open(full, OPEN_FLAGS)
                try:
                    with _reading():
                        before = os.fstat(fd)
                        if not stat_mod.S_ISREG(before.st_mode):
                            raise _not_regular(full)
                    if not part.upload or before.st_size < part.extent:
                        # a longer part's tail would stay past the end: use another one
                        self._spare(part.upload, part.extent)
                        part = _Part(*self._take_upload(before.st_size))
                    h, offset = self._send_pieces(batcher, fd, full, before, part)
                    with _reading():
                        after = os.fstat(fd)
                finally:
                    os.close(fd)
                with _reading():
                    done = (
                        offset == after.st_size
                        and _same_file(before, after)
                        and _still_there(full, after)
                    )
                if done:
                    break
        finally:
            if not done:
                self._spare(part.upload, part.extent)
        if not done:
            raise _ReadFailed(_kept_changing(full, READ_TRIES))
        op = p.op.but(
            source=M.SRC_UPLOAD, upload=part.upload, base="", hash=h.digest().hex(), size=offset
        )
        entry = entry_from_stat(after)
        item = M.Listed(op.path, "f", p.op.mode, offset, hash=op.hash)
        local.items[op.path] = item
        if entry is not None:
            local.stats[op.path] = entry
        batcher.add(op, tag=(Planned(op, WHOLE, item), None))

    def _send_pieces(
        self, batcher: _Batcher, fd: int, full: str, before: os.stat_result, part: _Part
    ) -> tuple[hashing.Hasher, int]:
        """Send the open file ``fd`` into ``part`` piece by piece, stopping early if it
        changes; its hash object and how far it was sent."""
        h = hashing.new(self.algorithm)
        offset = 0
        while offset < before.st_size:
            with _reading():
                piece = os.read(fd, min(PIECE, before.st_size - offset))
                if not piece:
                    break
                if read_hook is not None:
                    read_hook(full, "read")
                if not _same_file(before, os.fstat(fd)):
                    break  # changed under us: stop sending this attempt now
            h.update(piece)
            batcher.add(M.Op(M.UPLOAD, "", upload=part.upload, size=offset), piece, tag=None)
            offset += len(piece)
            part.extent = max(part.extent, offset)
        return h, offset

    def _take_upload(self, size: int) -> tuple[str, int]:
        """An upload id for ``size`` bytes: an abandoned part no longer than that, else a new one."""
        for upload, extent in self._spare_uploads.items():
            if extent <= size:
                del self._spare_uploads[upload]
                return upload, extent
        return os.urandom(8).hex(), 0

    def _spare(self, upload: str, extent: int) -> None:
        if upload and extent:
            self._spare_uploads[upload] = extent


class Round:
    """One push's rounds: its plan, batches, answers and their settling, until the robot
    holds the local tree (within a scope); then the state's new rows. What lives across
    pushes (the connection, the state, upload parts, recent deletions) is the Syncer's.
    """

    def __init__(
        self,
        syncer: Syncer,
        local: LocalTree,
        remote: dict[str, M.Listed],
        synced: dict[str, Synced],
        epoch: str,
        gen: int,
        report: Report,
        *,
        scope: Callable[[str], bool] | None,
        listed: Iterable[str] | None,
    ) -> None:
        self.syncer = syncer
        self.local = local
        self.remote = remote  # what the robot holds, as its answers say
        self.synced = synced  # what the state says was last synced
        self.new_synced = dict(synced)
        self.upserts: dict[str, tuple[Synced, bytes | None]] = {}
        self.deletes: set[str] = set()
        self.whole_only: set[str] = set()  # base mismatches: sent whole next time
        self.robot_sigs: dict[str, bytes] = {}
        self.kept: set[str] = set()  # paths whose robot version was kept aside
        self.epoch, self.gen = epoch, gen
        self.report = report
        self.scope = scope
        self.robot_listed = set(listed or ())
        self.adopt_all = False
        self.stale = False
        self.now_ns = time.time_ns()
        self.excluded = LocalRules(syncer.local_root, syncer.rules)
        self.unreadable = local.guarded()
        self.left_alone = {
            p for p, r in remote.items() if p not in local.items and self.excluded(p, r.kind == "d")
        }

    def expect(self, path: str) -> str:
        s = self.new_synced.get(path)
        return s.expectation() if s is not None else M.ABSENT

    def plan(self) -> list[Planned]:
        """The next round's operations (see :func:`reconcile`)."""
        signed, whole_only, new_synced = (
            self.syncer._signed or set(),
            self.whole_only,
            self.new_synced,
        )

        def has_signature(path: str, dst: M.Listed) -> bool:
            s = new_synced.get(path)
            return (
                path in signed
                and path not in whole_only
                and s is not None
                and s.kind == "f"
                and s.hash == dst.hash
            )

        return reconcile(
            self.local.items,
            self.remote,
            self.expect,
            guarded=self.guarded,
            has_signature=has_signature,
        )

    def guarded(self, path: str) -> bool:
        """What the laptop could not read, and what its rules now exclude (an --exclude, a
        pattern added to a .fetchsyncignore), is left as the robot has it."""
        return path in self.left_alone or self.unreadable(path)

    def report_ahead(self, planned: list[Planned]) -> None:
        """A dry run's report: the plan and the conflicts it would meet."""
        for p in planned:
            self.report.count(p)
            self.report.planned.append({"op": p.op.kind, "path": p.op.path, "how": p.how})
        self.report.conflicts += _conflicts_ahead(
            planned, self.remote, self.expect, refuse=self.syncer.policy == "refuse"
        )

    def run(self, planned: list[Planned], progress: Progress | None) -> bool:
        """Send one round and settle its answers. Returns whether another round is worth
        it: a base mismatch (it goes whole next time), a file that vanished (its
        delete), content the robot holds unseen. A lasting failure (no space,
        permission) is reported once. ``stale`` says if another writer was met."""
        mark("push: planned")
        syncer = self.syncer
        self.report.rounds += 1
        planned = syncer._robot_signatures(planned, self.remote, self.robot_sigs, self.whole_only)
        batcher = _Batcher(
            syncer.endpoint,
            policy=syncer.policy,
            epoch=self.epoch,
            gen=self.gen,
            progress=progress,
            total=sum(p.op.size for p in planned if p.how in (WHOLE, DELTA)),
            packs=syncer.packs,
            unsplit=self.whole_only,
        )
        again = False
        # settled as the robot answers, so a large push never holds every
        # operation and every answer at once
        planned = _large_first(planned)
        planned.reverse()
        try:
            while planned:
                again |= syncer._send_op(
                    batcher, planned.pop(), self.local, self.report, self.robot_sigs
                )
                if len(planned) % 512 == 0:
                    again |= self.settle(batcher.answered())
            # no post-apply scan: the robot reported its changes at the start of
            # this push, and each operation re-checks its own path there
            batcher.flush(last=True)
            again |= self.settle(batcher.answered(wait=True))
        finally:
            batcher.close()
        self.stale = batcher.stale
        if batcher.last is not None:
            self.epoch, self.gen = batcher.last.epoch, batcher.last.gen
        return again

    def relist(self) -> None:
        """Start again from what the robot holds now (another writer was met)."""
        listing = self.syncer.endpoint.listing()
        self.remote = self.syncer._apply_listing(listing, self.synced)
        self.epoch, self.gen = listing.epoch, listing.gen
        self.adopt_all = True
        self.stale = False

    def settle(self, answered: list[tuple[Any, M.Result]]) -> bool:
        again = False
        for tag, res in answered:
            again |= res.code == M.BASE_MISMATCH
            again |= self._settle(tag, res)
        return again

    def _settle(self, tag: Any, res: M.Result) -> bool:
        """Take one answer into the round's view of the robot and the state's rows.
        Returns True if the robot now holds content this laptop never saw there (another
        round must replace it, keeping the robot's version aside)."""
        report = self.report
        if tag is None:  # an upload piece
            if not res.ok:
                report.errors.append({"path": "(upload)", "error": res.message})
            return False
        p, sig = tag
        path = p.op.path
        if res.preserved and path not in self.kept:
            # once per push: a chmod's conflict keeps the robot's version, and the write
            # of the next round keeps it again
            self.kept.add(path)
            report.conflicts.append({"path": path, "kept": res.preserved})
        if not res.ok:
            self._failed(path, res)
            return False
        report.count(p)
        if p.op.kind == M.DELETE:
            self._forget_below(path, including=True)
            return False
        written = _as_sent(res.written, p.item) if res.written else p.item
        return written is not None and self._written(p, sig, written)

    def _failed(self, path: str, res: M.Result) -> None:
        """An operation that did not apply: sent whole next round (its delta's base was not
        there), or reported (a refused conflict, a failure)."""
        if res.code == M.BASE_MISMATCH:
            self.whole_only.add(path)
            self.remote.pop(path, None)  # unknown: the next round sends it whole
        elif res.code == M.CONFLICT:
            self.report.conflicts.append({"path": path, "kept": "", "refused": res.message})
        else:
            self.report.errors.append({"path": path, "error": res.message or res.code})

    def _written(self, p: Planned, sig: bytes | None, written: M.Listed) -> bool:
        """What an operation left on the robot, into the round's view and the state's rows.
        Returns True if that is content this laptop never saw there."""
        path, remote = p.op.path, self.remote
        if p.item is not None and not _same_content(written, p.item):
            # the operation went through over content someone else put there (a chmod
            # of a file edited on the robot): what the robot holds is not a version
            # this laptop synced, so it never becomes the base the next write expects;
            # that write keeps it in conflicts/
            remote[path] = written
            return True
        if (
            p.op.kind in (M.MKDIR, M.WRITE, M.SYMLINK)
            and path in remote
            and remote[path].kind == "d"
            and written.kind != "d"
        ):
            self._forget_below(path, including=False)
        remote[path] = written
        item = self.local.items.get(path)
        s = _synced_from(
            written,
            self.local.stats.get(path) if item is not None and item.hash == written.hash else None,
            self.now_ns,
        )
        self.new_synced[path] = s
        self.upserts[path] = (s, sig)
        self.deletes.discard(path)
        return False

    def _forget_below(self, path: str, *, including: bool) -> None:
        """``path``'s subtree (and ``path`` itself if ``including``) is gone from the robot."""
        prefix = path + "/"

        def gone(key: str) -> bool:
            return key.startswith(prefix) or (including and key == path)

        for key in [k for k in self.remote if gone(k)]:
            del self.remote[key]
        for key in [k for k in self.new_synced if gone(k)]:
            del self.new_synced[key]
            self.upserts.pop(key, None)
            self.deletes.add(key)

    def check_converged(self) -> None:
        """Report it if the robot still differs after the rounds (and nothing else says why)."""
        report, local = self.report, self.local
        failed = {e["path"] for e in report.errors}
        left = (
            []
            if _same_tree(local.items, self.remote)
            else [
                p
                for p in reconcile(local.items, self.remote, self.expect, guarded=self.guarded)
                if p.op.path not in failed
            ]
        )
        if left and not report.errors and not any(c.get("refused") for c in report.conflicts):
            report.errors.append(
                {
                    "path": left[0].op.path,
                    "error": f"{len(left)} path(s) still differ on the robot after "
                    f"{report.rounds} rounds (is something there rewriting them?)",
                }
            )

    def take_identical(self, *, adopt: bool) -> None:
        """Paths already identical need no operation, but the state must know them, and so
        must the robot's index if it did not (else every later drift check there would
        report them, and a no-op push would list them all); ``adopt``: tell the robot."""
        to_adopt: list[M.Listed] = []
        for path, item in self.local.items.items():
            r = self.remote.get(path)
            if r is not None and r == item and path not in self.upserts:
                if self.adopt_all or path in self.robot_listed:
                    to_adopt.append(item)
                s = _synced_from(item, self.local.stats.get(path), self.now_ns)
                if self.new_synced.get(path) != s:
                    self.upserts[path] = (s, None)
                    self.new_synced[path] = s
        if to_adopt and adopt:
            adopted = self.syncer.endpoint.adopt(to_adopt)
            self.epoch, self.gen = adopted.epoch, adopted.gen

    def forget_gone(self, scope_paths: set[str] | None) -> None:
        """Drop the rows of what the robot no longer holds (within the scope). An excluded
        path the robot did not list keeps its row: it is left alone there."""
        new_synced = self.new_synced
        candidates = (
            list(new_synced) if scope_paths is None else [p for p in scope_paths if p in new_synced]
        )
        for path in candidates:
            if (
                path not in self.remote
                and path not in self.upserts
                and (self.scope is None or self.scope(path))
                and not self.excluded(path, new_synced[path].kind == "d")
            ):
                self.deletes.add(path)
                del new_synced[path]

    def commit(self) -> None:
        self.syncer._commit(self.upserts, self.deletes, self.new_synced, self.epoch, self.gen)


def _large_first(planned: list[Planned]) -> list[Planned]:
    """The first writes of files from LARGE up, up to LARGE_FIRST bytes, moved to the head
    of the plan's writes (after its directories: plan.plan's order is mkdirs, writes,
    deletes), in their order; a file another write copies from (COPY of the robot's old
    content) keeps its place."""
    if len(planned) <= LARGE_FROM:
        return planned
    copied = {p.op.from_path for p in planned if p.op.kind == M.WRITE and p.how == COPY}
    first = next((i for i, p in enumerate(planned) if p.op.kind == M.WRITE), len(planned))
    moved: list[Planned] = []
    size = 0
    for p in planned[first:]:
        op = p.op
        if size >= LARGE_FIRST:
            break
        if (
            op.kind == M.WRITE
            and p.how in (WHOLE, DELTA)
            and op.size >= LARGE
            and op.path not in copied
        ):
            moved.append(p)
            size += op.size
    if not moved:
        return planned
    taken = {id(p) for p in moved}
    return planned[:first] + moved + [p for p in planned[first:] if id(p) not in taken]


def reconcile(
    local: Mapping[str, M.Listed],
    remote: Mapping[str, M.Listed],
    expect: Callable[[str], str],
    *,
    guarded: Callable[[str], bool],
    has_signature: Callable[[str, M.Listed], bool] = lambda p, d: False,
    pulling: bool = False,
) -> list[Planned]:
    """The operations that make the robot (``remote``, as it holds it) hold ``local``,
    each expecting what ``expect(path)`` says was last synced there, leaving ``guarded``
    paths and the link of :func:`fetchsync.sync.plan.catkin_toplevel` as the robot has
    them. ``pulling``: the other way, ``local`` is the robot's tree and ``remote`` the
    laptop's. Pure: no I/O (see :func:`fetchsync.sync.plan.plan`)."""
    laptop, robot = (remote, local) if pulling else (local, remote)
    return [
        p
        for p in plan(local, remote, expect, has_signature=has_signature)
        if not guarded(p.op.path)
        and not catkin_toplevel(
            p.op.path,
            laptop=laptop.get(p.op.path),
            robot=robot.get(p.op.path),
            last_synced=expect(p.op.path),
        )
    ]


def pull(
    conn: Connection,
    state: State,
    *,
    local_workspace: str,
    remote_workspace: str,
    rules: IgnoreRules,
    confirm: Callable[[Report], bool] | None = None,
    dry_run: bool = False,
    progress: Progress | None = None,
) -> Report:
    """Mirror the robot's ``src/`` into the local one.

    Every local file it replaces or deletes is kept in ``<workspace>/.fetchsync/trash/``
    (bounded), every one edited since the last sync in ``.fetchsync/conflicts/``;
    setuid and setgid bits of the robot's files are dropped.
    """
    t0 = time.monotonic()
    report = Report("pull", dry_run=dry_run)
    algorithm = conn.algorithm
    endpoint = Endpoint(conn)
    # read-only: a pull writes nothing on the robot (not even its index), so it works on
    # a robot whose disk is read-only too
    endpoint.open(remote_workspace, rules=rules, create=False, readonly=True)
    listing = endpoint.listing()
    remote = {e.path: _no_setid(e) for e in listing.entries}
    synced = state.entries() if state.get("algorithm") in ("", algorithm) else {}
    local_root = os.path.join(local_workspace, "src")
    os.makedirs(local_root, exist_ok=True)
    local = scan_local(local_root, rules, synced, algorithm)
    _report_skipped(local, report)
    report.skipped += [{"path": p, "reason": r} for p, r in listing.skipped]
    # a local path we could not read is left as it is, not replaced
    guarded = local.guarded()
    planned = _copies_kept(_plan_pull(remote, local, synced, guarded))
    for p in planned:
        report.planned.append({"op": p.op.kind, "path": p.op.path, "how": p.how})
    if dry_run or not planned:
        for p in planned:
            report.count(p)
    if dry_run:
        report.seconds = time.monotonic() - t0
        return report
    if planned and confirm is not None:
        _confirm_pull(planned, confirm)
    failed = _apply_pulled(endpoint, planned, local_workspace, report)
    final = scan_local(local_root, rules, {}, algorithm) if planned else local
    upserts = _pulled_rows(final, remote, synced, guarded, failed)
    # the robot's index is left as it was: the next push finds the paths pulled as
    # changes there, identical to the laptop's, and adopts them then
    state.commit(
        upserts=upserts,
        replace_all=True,
        meta={"epoch": listing.epoch, "gen": str(listing.gen), "algorithm": algorithm},
    )
    report.bytes_sent = conn.bytes_out
    report.bytes_received = conn.bytes_in
    report.seconds = time.monotonic() - t0
    return report


def _plan_pull(
    remote: dict[str, M.Listed],
    local: LocalTree,
    synced: dict[str, Synced],
    guarded: Callable[[str], bool],
) -> list[Planned]:
    """The operations that make the laptop hold the robot's tree: whole files, no deltas
    (a delta would apply to the local file, which goes to the trash)."""

    def expect(path: str) -> str:
        s = synced.get(path)
        return s.expectation() if s is not None else M.ABSENT

    return reconcile(remote, local.items, expect, guarded=guarded, pulling=True)


def _copies_kept(planned: list[Planned]) -> list[Planned]:
    """``planned`` with each copy of a local file that the pull itself replaces (the file,
    or a directory above it: a write, a link or a directory made there, which first moves
    the local one aside) read from the robot instead: the copy would find its source gone
    (the robot copied a file and then edited it, swapped two files). A plain delete of
    the source comes after every write (the plan's order): a rename still copies."""
    replaced = {p.op.path for p in planned if p.op.kind in (M.WRITE, M.SYMLINK, M.MKDIR)}
    out: list[Planned] = []
    for p in planned:
        src = p.op.from_path
        if p.how == COPY and (src in replaced or any(a in replaced for a in ancestors(src))):
            p = Planned(p.op.but(source=M.SRC_DATA, base="", from_path=""), WHOLE, p.item)
        out.append(p)
    return out


def _confirm_pull(planned: list[Planned], confirm: Callable[[Report], bool]) -> None:
    """Ask ``confirm`` with a preview of ``planned``; AbortedError if it declines."""
    preview = Report("pull")
    for p in planned:
        preview.count(p)
    if not confirm(preview):
        from fetchsync.errors import AbortedError

        raise AbortedError("pull cancelled; nothing was changed")


def _pulled_rows(
    final: LocalTree,
    remote: dict[str, M.Listed],
    synced: dict[str, Synced],
    guarded: Callable[[str], bool],
    failed: set[str],
) -> list[tuple[str, Synced, bytes | None]]:
    """The state's rows after a pull: what the laptop now holds as the robot does, and
    the last-synced rows of what it could not read (left untouched)."""
    now_ns = time.time_ns()
    upserts: list[tuple[str, Synced, bytes | None]] = []
    for path, item in final.items.items():
        r = remote.get(path)
        if r is not None and r == item and path not in failed:
            upserts.append((path, _synced_from(item, final.stats.get(path), now_ns), None))
    for path, s in synced.items():
        if guarded(path) and path not in final.items:
            # untouched: what was last synced there still holds
            upserts.append((path, s, None))
    return upserts


def _apply_pulled(
    endpoint: Endpoint, planned: list[Planned], local_workspace: str, report: Report
) -> set[str]:
    """Fetch what ``planned`` needs from the robot and apply it to the local workspace,
    by the same endpoint code the robot runs, a part at a time (:func:`_fetch`); report
    each answer. Returns the paths that failed."""
    store = Store(local_workspace, algorithm=endpoint.algorithm, create=True)
    # a local file replaced goes to the trash (or, edited since the last sync, to the
    # conflicts) once its replacement is whole: a write that fails leaves it in place
    store.keep_replaced = True
    failed: set[str] = set()
    try:
        with _writing(local_workspace):
            store.lock()
        for ops, blobs, tags in _fetch(endpoint, planned, report):
            with _writing(local_workspace):
                results = store.apply(ops, b"".join(blobs))
                store.save_index()
            _report_pulled(tags, results, local_workspace, report, failed)
    finally:
        store.discard_uploads()  # a large file's pieces whose file was not written
        store.unlock()
    return failed


@contextlib.contextmanager
def _writing(local_workspace: str) -> Iterator[None]:
    """A failure of the laptop's own disk (full, read-only) where the pull writes its
    bookkeeping (.fetchsync/: the lock, the batch mark, the index) as one line, not a
    traceback; a file that cannot be written is a result of its own."""
    try:
        yield
    except OSError as exc:
        raise SyncError(
            f"cannot write the pull into {local_workspace}: {exc.strerror or exc}",
            hint="free some space there (or fix its permissions) and pull again",
        ) from None


def _report_pulled(
    tags: list[Planned | None],
    results: list[M.Result],
    local_workspace: str,
    report: Report,
    failed: set[str],
) -> None:
    for tag, res in zip(tags, results):
        if tag is None:
            continue
        if res.preserved:
            report.conflicts.append(
                {
                    "path": tag.op.path,
                    "kept": os.path.join(local_workspace, res.preserved)
                    if not os.path.isabs(res.preserved)
                    else res.preserved,
                }
            )
        if not res.ok:
            failed.add(tag.op.path)
            report.errors.append({"path": tag.op.path, "error": res.message or res.code})
            continue
        report.count(tag)


SETID = stat_mod.S_ISUID | stat_mod.S_ISGID


def _no_setid(item: M.Listed) -> M.Listed:
    """A robot's file as pull writes it: never setuid or setgid here (a pull may run as root)."""
    return (
        item._replace(mode=item.mode & ~SETID) if item.kind == "f" and item.mode & SETID else item
    )


Part = tuple[list[M.Op], list[bytes], list[Planned | None]]


def _fetch(endpoint: Endpoint, planned: list[Planned], report: Report) -> Iterator[Part]:
    """What the plan needs from the robot, as local operations with their blob, in parts
    of about BATCH_BYTES of content, the next part's reads asked for while one is
    applied; a large file's pieces a part each. The laptop holds a part or two, never
    the whole pull (a pull of 80 MiB peaked at 221 MiB; a robot's sizes are its word)."""
    parts = _pull_parts(planned)
    asked = [_ask_small(endpoint, part) for part in parts[:1]]
    for i, part in enumerate(parts):
        if i + 1 < len(parts):
            asked.append(_ask_small(endpoint, parts[i + 1]))
        fetched = _take_small(asked[i], report)
        asked[i] = []
        ops: list[M.Op] = []
        blobs: list[bytes] = []
        tags: list[Planned | None] = []
        pos = 0
        for p in part:
            op = p.op
            if op.kind == M.WRITE and p.how != COPY:
                if op.size > BIG:
                    if ops:  # what comes before it is applied first, in the plan's order
                        yield ops, blobs, tags
                        ops, blobs, tags, pos = [], [], [], 0
                    whole = yield from _fetch_big(endpoint, p, report)
                    if whole is None:
                        continue
                    op = whole
                else:
                    got = fetched.pop(op.path, None)
                    if got is None:
                        continue
                    listed, data = got.listed, got.data
                    # whole content: pull asks for no delta (the local file goes to the trash)
                    op = op.but(
                        hash=listed.hash,
                        size=listed.size,
                        mode=_no_setid(listed).mode,
                        source=M.SRC_DATA,
                        base="",
                        blob=(pos, len(data)),
                    )
                    blobs.append(data)
                    pos += len(data)
            ops.append(op)
            tags.append(p)
        if ops:
            yield ops, blobs, tags


def _small(p: Planned) -> bool:
    """Whether ``p`` writes a file read whole from the robot (up to BIG)."""
    return p.op.kind == M.WRITE and p.how != COPY and p.op.size <= BIG


def _pull_parts(planned: list[Planned]) -> list[list[Planned]]:
    """``planned`` cut, in its order, into parts of about BATCH_BYTES of whole files read
    from the robot (or BATCH_OPS of them); a large file's pieces count apart."""
    parts: list[list[Planned]] = [[]]
    size = count = 0
    for p in planned:
        if size >= BATCH_BYTES or count >= BATCH_OPS:
            parts.append([])
            size = count = 0
        parts[-1].append(p)
        if _small(p):
            size += p.op.size
            count += 1
    return parts if parts[0] else []


def _ask_small(
    endpoint: Endpoint, part: list[Planned]
) -> list[tuple[Pending[list[Content | Failed]], list[Planned]]]:
    """The read of the whole files of ``part`` (those up to BIG), sent."""
    group = [p for p in part if _small(p)]
    return [(endpoint.send_read([p.op.path for p in group]), group)] if group else []


def _take_small(
    asked: list[tuple[Pending[list[Content | Failed]], list[Planned]]], report: Report
) -> dict[str, Content]:
    """The robot's answers and content for a read :func:`_ask_small` sent."""
    fetched: dict[str, Content] = {}
    for answers, group in asked:
        for p, ans in zip(group, answers.wait()):
            if isinstance(ans, Failed):
                report.errors.append({"path": p.op.path, "error": ans.message})
                continue
            fetched[p.op.path] = ans
    return fetched


def _fetch_big(
    endpoint: Endpoint, p: Planned, report: Report
) -> Generator[Part, None, M.Op | None]:
    """A large file read piece by piece, each piece a part of its own (an upload piece);
    returns the operation that writes the file from them, or None (reported)."""
    upload = os.urandom(8).hex()
    offset = 0
    listed = None
    while offset < p.op.size:
        [ans] = endpoint.read([(p.op.path, offset, PIECE)])
        if isinstance(ans, Failed):
            report.errors.append({"path": p.op.path, "error": ans.message})
            return None
        listed = ans.listed
        if not ans.data:
            break
        piece = M.Op(M.UPLOAD, "", upload=upload, size=offset, blob=(0, len(ans.data)))
        yield [piece], [ans.data], [None]
        offset += len(ans.data)
    if listed is None or listed.hash != p.op.hash or offset != listed.size:
        report.errors.append({"path": p.op.path, "error": "changed on the robot while it was read"})
        return None
    return p.op.but(source=M.SRC_UPLOAD, upload=upload, base="")


def _conflicts_ahead(
    planned: list[Planned],
    remote: dict[str, M.Listed],
    expect: Callable[[str], str],
    *,
    refuse: bool,
) -> list[dict[str, str]]:
    """The conflicts ``planned`` would meet on the robot (a dry run's report): each
    operation whose path there holds something else than was last synced, and each
    directory it replaces or deletes with files edited there below it; as the endpoint
    checks them (a mkdir over a directory is not checked)."""
    out: list[dict[str, str]] = []

    def conflict(path: str) -> None:
        out.append(
            {"path": path, "kept": "", "refused": "changed on the robot since the last sync"}
            if refuse
            else {"path": path, "kept": ".fetchsync/conflicts/"}
        )

    for p in planned:
        op = p.op
        r = remote.get(op.path)
        if op.kind == M.MKDIR and r is not None and r.kind == "d":
            continue
        if (r.expectation() if r is not None else M.ABSENT) != op.expect:
            conflict(op.path)
        elif r is not None and r.kind == "d":
            # the endpoint keeps (or, strict, refuses for) the files edited below, as one
            # conflict at the directory
            prefix = op.path + "/"
            if any(
                k.startswith(prefix) and v.kind != "d" and v.expectation() != expect(k)
                for k, v in remote.items()
            ):
                conflict(op.path)
    return out


@dataclass
class Deletions:
    """The files a chain of deleting pushes removed from the robot, and when its last push
    ended (see :meth:`Syncer._check_deletions`). The watch agent hands the same one to
    each Syncer it makes, so a reconnection between two batches of an ``rm -rf`` does not
    start the count again."""

    files: int = 0
    ended: float = 0.0
    # taken over from the state by a watch agent (restarted in the middle of an rm -rf):
    # its first push joins the chain within KEPT seconds, as the time between the two
    # processes is not known
    resumed: bool = False

    @classmethod
    def kept(cls, state: State) -> Deletions:
        """The chain the state recorded (see :meth:`Syncer._check_deletions`), if its last
        push started within KEPT seconds; else a new one."""
        try:
            files, wall = state.get("deletions").split()
            n, age = int(files), time.time() - float(wall)
        except ValueError:
            return cls()
        if n <= 0 or not 0 <= age < KEPT:
            return cls()
        return cls(n, time.monotonic() - age, True)


MASS_MIN = (
    20  # deleting more of the robot's files than this, and more than half, needs a confirmation
)
RECENT = 10.0  # seconds between one deleting push's end and the next's start: one deletion
KEPT = 600.0  # the same, for a restarted watch agent's first push (the chain kept in the state)


def refuse_mass_deletion(
    planned: list[Planned],
    remote: dict[str, M.Listed],
    synced: dict[str, Synced],
    *,
    recent: int = 0,
    scoped: bool = False,
) -> int:
    """Raise :class:`MassDeletionError` if ``planned`` deletes more than MASS_MIN of the
    robot's files (and links), and more than half of them, counting ``recent`` files
    deleted just before as part of the same deletion; else return how many it deletes.

    A ``src/`` emptied by mistake (an ``rm -rf src/*``, a checkout of the wrong branch,
    a workspace path that points elsewhere) would otherwise empty the robot's, and its
    trash is bounded. What is counted is every file the robot holds at or below a path
    the plan deletes or replaces a directory at (with a file or a link), less those whose
    content it writes again elsewhere (a directory renamed here). ``scoped``:
    ``remote`` is a push's scope only (the watch agent's push of touched paths): the
    robot's files outside it, and the whole, are the state's. A watcher on a busy
    machine reports an ``rm -rf`` in pieces, and a batch naming a few of its files
    finds their directory gone: the push deletes the directory, with every file the
    robot holds below it, named or not.
    """

    def held(path: str) -> M.Listed | Synced | None:
        r = remote.get(path)
        return synced.get(path) if r is None and scoped else r

    gone: set[str] = set()
    for p in planned:
        if p.op.kind == M.DELETE:
            gone.add(p.op.path)
        elif p.op.kind in (M.WRITE, M.SYMLINK):
            there = held(p.op.path)
            if there is not None and there.kind == "d":
                gone.add(p.op.path)
    if not gone:
        return 0
    # a file or link counts itself, a directory what is below it: one pass over the
    # entries, and only for a directory (a watch agent's state may hold 100,000 files:
    # ~0.25 s in Python for each deleting push, with every entry's ancestors tried)
    doomed_paths = set()
    below: list[str] = []
    for path in gone:
        there = held(path)
        if there is not None and there.kind == "d":
            below.append(path + "/")
        elif there is not None:
            doomed_paths.add(path)
    if below:
        prefixes = tuple(below)
        doomed_paths.update(
            p for p, e in remote.items() if p.startswith(prefixes) and e.kind != "d"
        )
        if scoped:  # the robot's files outside the push's view: the state's
            doomed_paths.update(
                p
                for p in synced
                if p.startswith(prefixes) and p not in remote and synced[p].kind != "d"
            )
    doomed = len(doomed_paths) - _written_again(planned, doomed_paths, remote, synced)
    if doomed + recent <= MASS_MIN:
        return doomed
    total = max(_files(remote.values()), _files(synced.values())) + recent
    if (doomed + recent) * 2 > total:
        so_far = f" ({recent} of them deleted by the pushes just before)" if recent else ""
        raise MassDeletionError(
            f"this push would delete {doomed + recent} of the robot's {total} "
            f"files{so_far}; nothing more was changed",
            hint="restore them here, or confirm with fetchsync push --force "
            "(deleted files go to the robot's .fetchsync/trash/)",
        )
    return doomed


def _written_again(
    planned: list[Planned],
    doomed: set[str],
    remote: dict[str, M.Listed],
    synced: dict[str, Synced],
) -> int:
    """How many of the ``doomed`` files ``planned`` writes again elsewhere: a directory
    renamed here has its files written at the new path (by hash), so nothing of the
    robot's is lost. Each write covers one doomed file holding its content."""
    again = collections.Counter(p.op.hash for p in planned if p.op.kind == M.WRITE)
    covered = 0
    for path in doomed:
        e = remote.get(path) or synced.get(path)
        if e is not None and e.kind == "f" and e.hash and again[e.hash] > 0:
            again[e.hash] -= 1
            covered += 1
    return covered


def _files(entries: Iterable[M.Listed | Synced]) -> int:
    """How many of ``entries`` are files or links."""
    return sum(1 for e in entries if e.kind != "d")


def _robot_could_sign(p: Planned, remote: dict[str, M.Listed], whole_only: set[str]) -> bool:
    """Whether ``p`` writes a large file whole that the robot holds a large version of,
    which a delta against could replace (unless its base mismatched already)."""
    if p.op.kind != M.WRITE or p.how != WHOLE or p.op.size < ROBOT_SIG_MIN:
        return False
    r = remote.get(p.op.path)
    return (
        p.op.path not in whole_only and r is not None and r.kind == "f" and r.size >= ROBOT_SIG_MIN
    )


QUICK_MAX = 1000  # local changes pushed path by path when the robot has not drifted


def _local_changes(
    scanned: ScanResult,
    synced: dict[str, Synced],
    listing: Listing,
    epoch: str,
    gen: int,
    excluded: Callable[[str, bool], bool],
) -> set[str] | None:
    """The local paths that differ from what the state recorded when it synced them, if the
    robot reports no drift since the state's generation and they are few; else None.

    The common pushes (nothing changed, or a few edits) are decided in one pass over
    the scan, comparing each entry with the stat the state recorded, before any hash
    or plan over the whole tree. A racy entry (stored without its stat) counts as
    changed, and so is hashed again.
    """
    entries = scanned.entries
    if listing.drifted or listing.epoch != epoch or listing.gen != gen or scanned.skipped:
        return None
    out: set[str] = set()
    get = synced.get
    # unchanged: as the state recorded it when it synced it, a file's stat (size, times,
    # inode), a link's target, a directory's mode (inline: a call per entry cost ~1 ms)
    for path, e in entries.items():
        s = get(path)
        if (
            s is not None
            and s.kind == e.kind
            and s.mode == e.mode
            and (
                s.size == e.size
                and s.mtime_ns == e.mtime_ns
                and s.ctime_ns == e.ctime_ns
                and s.ino == e.ino
                if e.kind == "f"
                else e.kind != "l" or s.target == e.target
            )
        ):
            continue
        out.add(path)
        if len(out) > QUICK_MAX:
            return None
    # the entries the state has rows for: the unchanged ones and the changed ones it
    # knows; as many as its rows, every row's path is here (nothing gone)
    if len(entries) - len(out) + sum(1 for p in out if p in synced) != len(synced):
        # gone here, unless the laptop's rules now exclude it (its row is kept: left alone)
        out.update(
            p for p, s in synced.items() if p not in entries and not excluded(p, s.kind == "d")
        )
        if len(out) > QUICK_MAX:
            return None
    return out


def _same_tree(local: dict[str, M.Listed], remote: dict[str, M.Listed]) -> bool:
    """Whether the robot holds exactly ``local`` as far as its answers said: then a plan
    would be empty (~1 ms for 9,000 paths, against ~8 for the plan; each entry is, as a
    rule, the very item sent)."""
    if len(local) != len(remote):
        return False
    get = remote.get
    for path, item in local.items():
        r = get(path)
        if r is not item and r != item:
            return False
    return True


def _same_content(a: M.Listed, b: M.Listed) -> bool:
    """Whether two entries hold the same content (modes aside)."""
    if a.kind != b.kind:
        return False
    return a.hash == b.hash if a.kind == "f" else a.target == b.target if a.kind == "l" else True


def _as_sent(wire: Any, item: M.Listed | None) -> M.Listed:
    """What the robot reports it wrote, as the item we sent when it is that (the usual case):
    a large push then keeps one copy of each path and hash, not a second one per answer."""
    if (
        item is not None
        and isinstance(wire, list)
        and len(wire) == 5
        and wire[0] == item.path
        and wire[1] == item.kind
        and wire[2] == item.mode
        and wire[3] == item.size
        and wire[4] == (item.target if item.kind == "l" else item.hash)
    ):
        return item
    return M.Listed.from_wire(wire)


def _report_skipped(local: LocalTree, report: Report) -> None:
    """What the scan left out: unreadable paths are failures (the push is incomplete),
    the rest (FIFOs, sockets, vanished files) notes."""
    for path, reason in local.skipped:
        if _unreadable(reason):
            report.errors.append({"path": path, "error": reason})
        else:
            report.skipped.append({"path": path, "reason": reason})


def raise_for(report: Report, *, strict: bool) -> None:
    """Turn a report's failures into the exception the CLI maps to an exit code."""
    refused = [c for c in report.conflicts if c.get("refused")]
    if refused:
        raise ConflictError(
            f"{len(refused)} path(s) were changed on the robot since the last sync; "
            f"nothing was overwritten there (first: {refused[0]['path']})",
            hint="pull them first, or push without --strict to keep them aside",
        )
    if report.errors:
        first = report.errors[0]
        raise SyncError(
            f"{len(report.errors)} path(s) failed; first: {first['path']}: {first['error']}"
        )
    _ = RemoteError, strict
