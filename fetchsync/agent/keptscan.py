"""The resident's scan of its workspace, kept between pushes by inotify (issue 24).

A push starts from a stat of every path under ``src/`` (:func:`fetchsync.sync.engine.scan_tree`:
~32 ms of CPU for the bench's 2,547 paths, the largest part of a one-edit push made
by the resident). Between two pushes a user changes a few paths, so the resident
keeps the last scan and an inotify watch on every directory it listed, and at the
next push lists again only the directories where something happened (and their
subtrees); the directory itself is stat'ed again too (a child created or deleted
moves its mtime, which its parent's watch does not report).

It answers exactly what :func:`~fetchsync.sync.engine.scan_tree` would, or steps
aside (a full scan, the watches made again) whenever it cannot know: the kernel's
queue overflowed, a watch could not be added (``max_user_watches``), a directory was
moved (its watches' paths are stale), an ignore file changed, the root was replaced,
a path at the top of the tree changed (its listing is the whole tree's), the tree is
(partly) on a file system whose changes inotify does not all see (NFS, SMB, FUSE,
9p: another machine writes there) or has a mount point inside it.

inotify is what finds new and removed names (a local directory's events are its own,
whoever changed it); it is not what decides a file's content. A write through a hard
link from outside the tree, or through a shared writable mmap, is reported to no
watched directory, so every kept path is ``lstat``'ed again at each push
(:meth:`KeptScan._restat`: ~2,500 ``lstat`` calls, a few ms of the ~32 ms the full walk
costs) and a file takes its stat of now, as a fresh scan's; a directory whose stat
moved is listed again. What the engine then decides from those stats is what it
decides from a fresh scan's.
"""

from __future__ import annotations

import ctypes
import errno
import os
import stat
from typing import Any, Callable

from fetchsync.errors import SyncError
from fetchsync.protocol.kept import (  # the robot's kept listing: the same inotify
    _EVENT,
    IN_ATTRIB,
    IN_CREATE,
    IN_DELETE,
    IN_DELETE_SELF,
    IN_IGNORED,
    IN_ISDIR,
    IN_MODIFY,
    IN_MOVE_SELF,
    IN_MOVED_FROM,
    IN_MOVED_TO,
    IN_ONLYDIR,
    IN_Q_OVERFLOW,
    _parent,
    _StepAside,
)
from fetchsync.protocol.kept import _check_mounts as _check_mounts_at
from fetchsync.protocol.kept import _inotify as _kept_inotify
from fetchsync.protocol.tree import DIR, FILE, IGNORE_FILE, Entry, ScanResult, scan

IN_DONT_FOLLOW = 0x02000000
WATCHED = (
    IN_MODIFY
    | IN_ATTRIB
    | IN_MOVED_FROM
    | IN_MOVED_TO
    | IN_CREATE
    | IN_DELETE
    | IN_DELETE_SELF
    | IN_MOVE_SELF
    | IN_ONLYDIR
    | IN_DONT_FOLLOW
)


_libc: Any = None


def _inotify() -> Any:
    """The C library's inotify calls (the robot's kept listing's), held here too."""
    global _libc
    if _libc is None:
        _libc = _kept_inotify()
    return _libc


class KeptScan:
    """:meth:`scan` is ``scan_tree(root, rules)``, from the last scan and inotify's events
    since, when they say exactly what changed.

    ``is_temp`` and ``rules`` as the engine's scan uses them. One thread at a time."""

    def __init__(self, root: str, rules: Any, *, is_temp: Callable[[str], bool]) -> None:
        self.root = root
        self.rules = rules
        self.is_temp = is_temp
        self._fd = -1
        self._wds: dict[int, str] = {}
        self._entries: dict[str, Entry] | None = None
        self._skipped: list[tuple[str, str]] = []
        self._root_id: tuple[int, int] | None = None
        self._watching = True  # False while a watch could not be added
        # the user's inotify watches (or instances) are used up: the scans are full ones
        # for this process's life, holding none (an editor, an IDE, a watch agent need them)
        self.gave_up = False
        self.full_scans = 0  # how often it scanned the whole tree (tests, traces)

    @property
    def warm(self) -> bool:
        """Whether the next :meth:`scan` may be answered without a full scan."""
        return self._entries is not None and self._fd >= 0 and self._watching and not self.gave_up

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
        self._fd = -1
        self._entries = None
        self._wds = {}

    def scan(self) -> ScanResult:
        """What a full scan of the tree finds now (SyncError if the root cannot be listed)."""
        if self.warm:
            try:
                _check_mounts(self.root)
                dirty = self._drain()
                self._restat(dirty)
                self._refresh(dirty)
                return ScanResult(dict(self._entries or {}), list(self._skipped))
            except (_StepAside, OSError):
                pass
        return self._full()

    # ------------------------------------------------------------------ the full scan
    def _full(self) -> ScanResult:
        self.close()
        self.full_scans += 1
        self._watching = not self.gave_up
        fd = -1
        if self._watching:
            fd = _inotify().inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
            if fd < 0:  # no inotify instance left (EMFILE), or none at all
                self.gave_up = True
                self._watching = False
        self._fd = fd
        try:
            st = os.stat(self.root)
            self._root_id = (st.st_dev, st.st_ino)
            result = scan(self.root, self.rules, is_temp=self.is_temp, on_dir=self._on_dir)
        except OSError as exc:
            self.close()
            raise SyncError(f"cannot list {self.root}: {exc.strerror or exc}") from exc
        if not self._watching:
            self.close()
            return result
        self._entries = dict(result.entries)
        self._skipped = list(result.skipped)
        return result

    def _on_dir(self, full: str, rel: str) -> None:
        """Before a directory is listed: watch it (so that nothing after its listing is
        missed), then check it can be searched, as the engine's scan does."""
        if self._fd >= 0 and self._watching:
            # the root is listed through a symlink, as the engine's scan lists it; below
            # it none is followed
            mask = WATCHED & ~IN_DONT_FOLLOW if rel == "" else WATCHED
            wd = _inotify().inotify_add_watch(self._fd, os.fsencode(full), mask)
            if wd < 0:
                self._watching = False  # it changed meanwhile: watched again next time
                if ctypes.get_errno() == errno.ENOSPC:  # the watch limit: not again
                    self.gave_up = True
            elif self._wds.get(wd, rel) != rel:
                # one directory at two paths (a bind mount): its events cannot say which
                self._watching = False
            else:
                self._wds[wd] = rel
        # its entries must be looked up: else it is reported as one it cannot list
        os.lstat(os.path.join(full, "."))

    # ------------------------------------------------------------------ the events
    def _drain(self) -> set[str]:
        """The directories (wire paths) with events since the last look."""
        st = os.stat(self.root)
        if (st.st_dev, st.st_ino) != self._root_id:
            raise _StepAside("the root was replaced")
        dirty: set[str] = set()
        while True:
            try:
                data = os.read(self._fd, 1 << 16)
            except BlockingIOError:
                return dirty
            at = 0
            while at + _EVENT.size <= len(data):
                wd, mask, _cookie, size = _EVENT.unpack_from(data, at)
                name = data[at + _EVENT.size : at + _EVENT.size + size].rstrip(b"\0")
                at += _EVENT.size + size
                if mask & IN_Q_OVERFLOW:
                    raise _StepAside("inotify's queue overflowed")
                if mask & IN_IGNORED:
                    self._wds.pop(wd, None)
                    continue
                rel = self._wds.get(wd)
                if rel is None:
                    continue  # a directory deleted: its parent's event says so
                if mask & (IN_DELETE_SELF | IN_MOVE_SELF):
                    if rel == "" or mask & IN_MOVE_SELF:
                        raise _StepAside("a watched directory moved, or the root went")
                    continue
                if mask & IN_ISDIR and mask & (IN_MOVED_FROM | IN_MOVED_TO):
                    raise _StepAside("a directory moved")
                if name == IGNORE_FILE.encode():
                    raise _StepAside("an ignore file changed")
                if name:
                    dirty.add(rel)

    def _refresh(self, dirty: set[str]) -> None:
        """List again the directories in ``dirty`` (each with its subtree)."""
        entries = self._entries
        if entries is None or "" in dirty:
            raise _StepAside("the top of the tree changed")
        tops = [d for d in sorted(dirty) if not any(_within(d, o) for o in dirty if o != d)]
        for top in tops:
            prefix = top + "/"
            for path in [p for p in entries if p.startswith(prefix)]:
                del entries[path]
            self._skipped = [
                s for s in self._skipped if s[0] != top and not s[0].startswith(prefix)
            ]
            st = os.lstat(os.path.join(self.root, top))
            if not stat.S_ISDIR(st.st_mode) or top not in entries:
                raise _StepAside("a listed directory is no longer one")
            entries[top] = Entry(
                DIR, st.st_mode & 0o7777, 0, st.st_mtime_ns, st.st_ctime_ns, st.st_ino
            )
            result = scan(
                self.root, self.rules, is_temp=self.is_temp, start=top, on_dir=self._on_dir
            )
            if not self._watching:
                raise _StepAside("a watch could not be added")
            entries.update(result.entries)
            self._skipped.extend(result.skipped)

    def _restat(self, dirty: set[str]) -> None:
        """``lstat`` every kept path again: a file whose stat moved takes its stat of now
        (a write through a hard link from outside the tree, or through an mmap, is
        reported to no watched directory: tests/test_keptscan_exact.py, and a hard link
        inside it: tests/test_keptscan_hard_links.py); a directory whose stat moved, or
        one whose entry changed kind or went, goes to ``dirty`` (listed again)."""
        entries = self._entries
        if entries is None:
            return
        root = self.root
        lstat = os.lstat
        for path, entry in list(entries.items()):
            try:
                st = lstat(root + "/" + path)
            except OSError:
                dirty.add(_parent(path))
                continue
            if (
                st.st_ino == entry.ino
                and st.st_mtime_ns == entry.mtime_ns
                and st.st_ctime_ns == entry.ctime_ns
            ):
                continue  # any change of mode, size, content or kind moves the ctime
            mode = st.st_mode
            if entry.kind == FILE and stat.S_ISREG(mode):
                entries[path] = Entry(
                    FILE, mode & 0o7777, st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino
                )
            elif entry.kind == DIR and stat.S_ISDIR(mode):
                dirty.add(path)
            else:
                dirty.add(_parent(path))


# File systems whose changes all go through this machine's kernel, so that inotify
# sees every name created or removed in a watched directory. Any other (NFS, CIFS/SMB,
# FUSE, 9p, ceph, ...: another machine or a userspace daemon writes there) makes the
# kept scan step aside.
def _check_mounts(root: str, mountinfo: str = "/proc/self/mountinfo") -> None:
    """:func:`fetchsync.protocol.kept._check_mounts` for ``root`` as named (symlinks in
    it resolved: the mount table names real paths); one ``/proc/self/mountinfo`` read a
    push, ~0.1 ms."""
    _check_mounts_at(os.path.realpath(root), mountinfo)


def _within(path: str, top: str) -> bool:
    return path.startswith(top + "/")
