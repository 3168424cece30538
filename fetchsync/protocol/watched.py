"""A scanned tree kept current by Linux inotify, so a drift check need not stat everything.

A warm endpoint (one a connection master started ahead of need) scans the
workspace it served last while it waits for a client, watching every
directory it lists. When the client asks what drifted, only the paths the
kernel reported since are looked at again. Anything that makes the events
incomplete (a queue overflow, a watch that could not be added, a changed
``.fetchsyncignore``, no inotify at all) makes :meth:`WatchedTree.refresh`
say so, and the caller scans in full as it always could.

Standard library only (``ctypes``), Python 3.8.
"""

from __future__ import annotations

import ctypes
import os
import struct
from typing import Any, Callable, Dict, List, Optional, Set, Tuple

from fetchsync.protocol.tree import DIR, IGNORE_FILE, Entry, scan, stat_path

IN_MODIFY = 0x2
IN_ATTRIB = 0x4
IN_CLOSE_WRITE = 0x8
IN_MOVED_FROM = 0x40
IN_MOVED_TO = 0x80
IN_CREATE = 0x100
IN_DELETE = 0x200
IN_DELETE_SELF = 0x400
IN_MOVE_SELF = 0x800
IN_Q_OVERFLOW = 0x4000
IN_IGNORED = 0x8000
IN_ONLYDIR = 0x1000000
IN_DONT_FOLLOW = 0x2000000
IN_EXCL_UNLINK = 0x4000000
MASK = (IN_MODIFY | IN_ATTRIB | IN_CLOSE_WRITE | IN_MOVED_FROM | IN_MOVED_TO | IN_CREATE
        | IN_DELETE | IN_DELETE_SELF | IN_MOVE_SELF | IN_ONLYDIR | IN_DONT_FOLLOW | IN_EXCL_UNLINK)
_EVENT = struct.Struct("iIII")


class Unavailable(Exception):
    """No inotify here (not Linux, no libc symbol, or out of instances)."""


class DirWatch:
    """inotify watches on directories, reporting the wire paths touched since last asked."""

    def __init__(self) -> None:
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            init, add = libc.inotify_init1, libc.inotify_add_watch
        except (OSError, AttributeError) as exc:
            raise Unavailable(str(exc)) from None
        add.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_uint32]
        fd = init(os.O_NONBLOCK | os.O_CLOEXEC)
        if fd < 0:
            raise Unavailable(os.strerror(ctypes.get_errno()))
        self.fd = fd
        self._add = add
        self.dirs: Dict[int, str] = {}  # watch descriptor -> wire path of the directory
        self.lost = False  # events may be missing: the caller must scan in full

    def add(self, full: str, rel: str) -> None:
        wd = self._add(self.fd, os.fsencode(full), MASK)
        if wd < 0:
            err = ctypes.get_errno()
            if err not in (2, 20):  # ENOENT, ENOTDIR: it went away; its parent's event says so
                self.lost = True    # ENOSPC (the watch limit) and the like
            return
        self.dirs[wd] = rel  # a directory moved here keeps its descriptor, under its new path

    def touched(self) -> Optional[Set[str]]:
        """Wire paths with events since the last call, or None if some were lost."""
        out: Set[str] = set()
        while True:
            try:
                buf = os.read(self.fd, 1 << 16)
            except BlockingIOError:
                break
            pos = 0
            while pos + _EVENT.size <= len(buf):
                wd, mask, _cookie, length = _EVENT.unpack_from(buf, pos)
                name = buf[pos + _EVENT.size:pos + _EVENT.size + length].rstrip(b"\0")
                pos += _EVENT.size + length
                if mask & IN_Q_OVERFLOW:
                    self.lost = True
                    continue
                rel = self.dirs.get(wd)
                if mask & IN_IGNORED:
                    self.dirs.pop(wd, None)
                    continue
                if rel is None:
                    continue
                if not name:
                    if not rel and mask & (IN_DELETE_SELF | IN_MOVE_SELF):
                        self.lost = True  # the root itself went away
                    out.add(rel)
                    continue
                text = os.fsdecode(name)
                out.add(rel + "/" + text if rel else text)
                out.add(rel)  # its own times changed: no event in its parent says so
        return None if self.lost else out

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


class WatchedTree:
    """The entries under ``root`` (as :func:`scan` gives them), kept current by inotify."""

    def __init__(self, root: str, rules: Any, is_temp: Callable[[str], bool]) -> None:
        self.root = root
        self.rules = rules
        self.is_temp = is_temp
        self.watch = DirWatch()
        self.rules_at: Dict[str, Any] = {}  # listed directory -> rules below it
        try:
            result = scan(root, rules, is_temp=is_temp, on_dir=self.watch.add,
                          rules_out=self.rules_at)
        except BaseException:
            self.watch.close()
            raise
        self.entries: Dict[str, Entry] = result.entries
        self.skipped: List[Tuple[str, str]] = result.skipped
        self.version = 0  # moves on whenever a refresh found events

    def refresh(self) -> bool:
        """Bring the entries up to date; False if that is not possible (scan in full instead)."""
        touched = self.watch.touched()
        if touched is None:
            return False
        if touched:
            self.version += 1
        # parents first: a new directory is scanned whole before its children's events
        try:
            for path in sorted(touched, key=lambda p: (p.count("/"), p)):
                if not self._refresh(path):
                    self.watch.lost = True
                    return False
        except OSError:  # say, a path that cannot be looked at any more: its events are spent
            self.watch.lost = True
            return False
        return not self.watch.lost

    def _forget(self, path: str) -> None:
        self.entries.pop(path, None)
        self.rules_at.pop(path, None)
        prefix = path + "/"
        for table in (self.entries, self.rules_at):
            for key in [k for k in table if k.startswith(prefix)]:
                del table[key]

    def _refresh(self, path: str) -> bool:
        if not path:
            return True  # the root's own attributes are not part of the tree
        parent, _, name = path.rpartition("/")
        if name == IGNORE_FILE:
            return False  # the rules changed: everything below may be in or out now
        if parent not in self.rules_at:
            self._forget(path)  # below an ignored, special or vanished directory
            return True
        if self.is_temp(name):
            return True
        e = stat_path(os.path.join(self.root, path))
        rules = self.rules_at[parent]
        old = self.entries.get(path)
        if e is None or (rules is not None and rules.ignored(path, e.kind == DIR)):
            self._forget(path)
            return True
        if e.kind != DIR:
            if old is not None and old.kind == DIR:
                self._forget(path)
            self.entries[path] = e
            return True
        if old is not None and old.kind == DIR and path in self.rules_at and old.ino == e.ino:
            self.entries[path] = e  # its attributes; its children have their own events
            return True
        self._forget(path)
        self.entries[path] = e
        result = scan(self.root, self.rules, is_temp=self.is_temp, start=path,
                      on_dir=self.watch.add, rules_out=self.rules_at)
        self.entries.update(result.entries)
        self.skipped.extend(result.skipped)
        return True

    def close(self) -> None:
        self.watch.close()
