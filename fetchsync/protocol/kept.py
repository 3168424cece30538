"""A long-lived endpoint's listing of ``src/``, kept between pushes by inotify (issue 24).

Every push asks the robot what changed there since the laptop's last sync
(``Store.drift``): a walk of the whole tree, every directory opened and listed and
every entry stat'ed and matched against the ignore rules (the bench's 2,547 paths:
~33 ms of the endpoint's CPU, most of a one-edit push's robot work, and the writes
wait behind it). The endpoint of the resident or of the watch agent lives across
pushes: from the second listing of one Store on, it keeps the walk's entries with an
inotify watch on every directory listed, and at the next listing lists again only the
directories where something happened (each with its subtree, from the root's
descriptor, as the walk does).

It answers exactly what :func:`fetchsync.protocol.tree.scan_fd` would, or steps aside
(a full walk, the watches made again) whenever it cannot know: the kernel's queue
overflowed, a watch could not be added (the user's watches used up: then it gives
every watch back and takes none again), a directory moved, an ignore file changed,
the root is another directory, a path at the top of the tree changed, the tree is on
a file system whose changes inotify does not all see (NFS, SMB, FUSE, 9p: another
machine writes there) or has a mount point inside it, one directory is watched at
two paths (a bind mount).

inotify is only what finds new and removed names. Every kept path is ``lstat``'ed
again at each listing, and an entry whose stat (inode, size, mode, times) moved takes
its stat of now (a file: as a fresh walk would record it) or has its directory listed
again: a write through a hard link from outside the tree, a shared writable mmap, a
change inotify missed is seen as a fresh walk sees it. What Store.drift then decides
from those stats is what it decides from a fresh walk's.

What it pays for: the endpoint's CPU per one-edit push made through a long-lived
endpoint (open + drift listing + the write, in-process through Server.dispatch, the
bench's 2,000-file / 2,547-path tree with the client's rules, a push a second; medians
of 10, two runs each, interleaved, load 3-4): 40.5 / 50.7 ms at 9f598f8 -> 16.7 / 20.9
ms with this, the Store kept on a re-open and drift's inline skip (the listing
35-43 -> 15-19 ms: ~2,500 fstatat from the root's descriptor ~10 ms, the drift loop
~4 ms). The push the user makes, bench/run.py --link wifi --files 2000 --size-mb 40
--reps 7 --scenarios noop,edit --rev bb75eae --baseline-rev 9f598f8 (interleaved, load
2-6): one edit 0.097 vs 0.125 s (0.78x; 0.20x rsync's 0.488 s), no-op 0.089 vs 0.116 s
(the push's own seconds 0.031 vs 0.061). Costs: one inotify watch per directory while the endpoint lives (the resident's
idles out after 10 minutes), and the second listing of a session walks the whole tree
once more to set them.

Python 3.6, standard library only (ctypes), like all of the robot's code.
"""

import ctypes
import errno
import os
import stat as stat_mod
import struct
from typing import Any, Callable, Dict, List, Optional, Set, Tuple

from fetchsync.protocol.paths import open_dir
from fetchsync.protocol.tree import DIR, FILE, IGNORE_FILE, LINK, Entry, ScanResult, scan_fd

IN_MODIFY = 0x2
IN_ATTRIB = 0x4
IN_MOVED_FROM = 0x40
IN_MOVED_TO = 0x80
IN_CREATE = 0x100
IN_DELETE = 0x200
IN_DELETE_SELF = 0x400
IN_MOVE_SELF = 0x800
IN_Q_OVERFLOW = 0x4000
IN_IGNORED = 0x8000
IN_ONLYDIR = 0x01000000
IN_ISDIR = 0x40000000
# the directory is named by /proc/self/fd/N (a descriptor opened without following
# symlinks): the magic link must be followed, so no IN_DONT_FOLLOW
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
)
_EVENT = struct.Struct("iIII")
# File systems whose changes all go through this machine's kernel (the laptop's
# fetchsync.agent.keptscan uses these too): any other makes the kept listing step aside
LOCAL_FILE_SYSTEMS = frozenset(
    (
        "ext2 ext3 ext4 xfs btrfs tmpfs f2fs zfs jfs reiserfs bcachefs overlay ramfs hfsplus apfs"
    ).split()
)

_libc: "Any" = None


def _inotify() -> "Any":
    global _libc
    if _libc is None:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.inotify_init1.argtypes = [ctypes.c_int]
        libc.inotify_add_watch.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_uint32]
        _libc = libc
    return _libc


class _StepAside(Exception):
    """The kept listing cannot say what changed: walk the whole tree."""


class KeptTree:
    """:meth:`scan` is ``scan_fd(root_fd, rules, is_temp=is_temp)``, from the last walk and
    inotify's events since, when they say exactly what changed. One thread at a time."""

    def __init__(self, rules: "Any", is_temp: "Callable[[str], bool]") -> None:
        self.rules = rules
        self.is_temp = is_temp
        self._fd = -1
        self._wds: "Dict[int, str]" = {}
        self._entries: "Optional[Dict[str, Entry]]" = None
        self._skipped: "List[Tuple[str, str]]" = []
        self._rules_below: "Dict[str, Any]" = {}  # see scan_fd's rules_out
        self._root_id: "Optional[Tuple[int, int]]" = None
        self._watching = False
        self.gave_up = False  # the user's watches or instances used up: full walks only
        self.full_scans = 0  # how often it walked the whole tree (tests)
        # the paths whose entry changed or came since take_moved() (None: unknown, the
        # whole tree was walked)
        self._moved: "Optional[Set[str]]" = None

    def take_moved(self) -> "Optional[Set[str]]":
        """The paths whose entry is another object than at the last call (it changed or
        came; one that went is not in the walk), or None if the whole tree was walked
        since (any may have)."""
        moved, self._moved = self._moved, set()
        return moved

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
        self._fd = -1
        self._entries = None
        self._wds = {}
        self._rules_below = {}

    def scan(self, root_fd: int) -> "ScanResult":
        """What a walk of the directory held by ``root_fd`` finds now."""
        if self._entries is not None and self._fd >= 0 and self._watching:
            try:
                self._check_root(root_fd)
                dirty = self._drain()
                self._restat(root_fd, dirty)
                self._refresh(root_fd, dirty)
                return ScanResult(dict(self._entries), list(self._skipped))
            except (_StepAside, OSError):
                pass
        return self._full(root_fd)

    # ------------------------------------------------------------------ the full walk
    def _full(self, root_fd: int) -> "ScanResult":
        self.close()
        self.full_scans += 1
        self._moved = None
        self._watching = not self.gave_up
        if self._watching:
            self._fd = _inotify().inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
            if self._fd < 0:  # no inotify instance left (EMFILE), or none at all
                self.gave_up, self._watching = True, False
        st = os.fstat(root_fd)
        self._root_id = (st.st_dev, st.st_ino)
        rules_below: "Dict[str, Any]" = {}
        try:
            result = scan_fd(
                root_fd,
                self.rules,
                is_temp=self.is_temp,
                on_dir=self._on_dir if self._watching else None,
                rules_out=rules_below,
            )
        except BaseException:
            self.close()
            raise
        if not self._watching:
            self.close()
            return result
        self._entries = dict(result.entries)
        self._skipped = list(result.skipped)
        self._rules_below = rules_below
        return result

    def _on_dir(self, fd: int, rel: str) -> None:
        """Before a directory is listed: watch it (nothing after its listing is missed)."""
        if not self._watching:
            return
        wd = _inotify().inotify_add_watch(self._fd, b"/proc/self/fd/%d" % fd, WATCHED)
        if wd < 0:
            self._watching = False  # walked again next time
            if ctypes.get_errno() in (errno.ENOSPC, errno.EMFILE):
                self.gave_up = True  # the user's watches used up: give them all back
                os.close(self._fd)
                self._fd = -1
        elif self._wds.get(wd, rel) != rel:
            self._watching = False  # one directory at two paths: events cannot say which
        else:
            self._wds[wd] = rel

    # ------------------------------------------------------------------ at each listing
    def _check_root(self, root_fd: int) -> None:
        st = os.fstat(root_fd)
        if (st.st_dev, st.st_ino) != self._root_id:
            raise _StepAside("another root")
        _check_mounts(os.readlink("/proc/self/fd/%d" % root_fd))

    def _drain(self) -> "Set[str]":
        """The directories (wire paths) with events since the last look."""
        dirty: "Set[str]" = set()
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

    def _restat(self, root_fd: int, dirty: "Set[str]") -> None:
        """``lstat`` every kept path again (from the root's descriptor: a directory swapped for
        a symlink is then seen at its own path, and its parent listed again): an entry whose
        stat moved takes its stat of now if it is still a file, else its directory
        (the entry itself for a directory) is listed again."""
        entries = self._entries
        assert entries is not None
        stat = os.stat
        for path, entry in list(entries.items()):
            try:
                st = stat(path, dir_fd=root_fd, follow_symlinks=False)
            except OSError:
                dirty.add(_parent(path))
                continue
            mode = st.st_mode
            if (
                st.st_ino == entry.ino
                and st.st_mtime_ns == entry.mtime_ns
                and st.st_ctime_ns == entry.ctime_ns
                and (
                    entry.kind == LINK
                    or (
                        mode & 0o7777 == entry.mode
                        and (entry.kind == DIR or st.st_size == entry.size)
                    )
                )
            ):
                continue  # the entry a fresh walk would record (a symlink's target: its inode's)
            if path.rpartition("/")[2] == IGNORE_FILE:  # written with no event (a hard link)
                raise _StepAside("an ignore file changed")
            if entry.kind == FILE and stat_mod.S_ISREG(mode):
                entries[path] = Entry(
                    FILE, mode & 0o7777, st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino
                )
                if self._moved is not None:
                    self._moved.add(path)
            elif entry.kind == DIR and stat_mod.S_ISDIR(mode):
                dirty.add(path)
            else:
                dirty.add(_parent(path))

    def _refresh(self, root_fd: int, dirty: "Set[str]") -> None:
        """List again the directories in ``dirty``, each with its subtree."""
        entries = self._entries
        assert entries is not None
        if "" in dirty:
            raise _StepAside("the top of the tree changed")
        tops = [d for d in sorted(dirty) if not any(d.startswith(o + "/") for o in dirty)]
        moved = self._moved
        for top in tops:
            prefix = top + "/"
            for path in [p for p in entries if p.startswith(prefix)]:
                del entries[path]
            for path in [p for p in self._rules_below if p.startswith(prefix)]:
                del self._rules_below[path]
            self._skipped = [
                s for s in self._skipped if s[0] != top and not s[0].startswith(prefix)
            ]
            if top not in entries or _parent(top) not in self._rules_below:
                raise _StepAside("a directory not listed before")
            try:
                fd = _open_below(root_fd, top)
            except OSError:
                raise _StepAside("a listed directory is no longer one") from None
            try:
                st = os.fstat(fd)
                entries[top] = Entry(
                    DIR, st.st_mode & 0o7777, 0, st.st_mtime_ns, st.st_ctime_ns, st.st_ino
                )
                result = scan_fd(
                    fd,
                    self._rules_below[_parent(top)],
                    is_temp=self.is_temp,
                    prefix=top,
                    on_dir=self._on_dir,
                    rules_out=self._rules_below,
                )
            finally:
                os.close(fd)
            if not self._watching:
                raise _StepAside("a watch could not be added")
            entries.update(result.entries)
            if moved is not None:
                moved.add(top)
                moved.update(result.entries)
            self._skipped.extend(result.skipped)


def _open_below(root_fd: int, path: str) -> int:
    """A descriptor of the directory at wire path ``path``, from ``root_fd``, one component
    at a time, never through a symlink."""
    fd = root_fd
    try:
        for part in path.split("/"):
            sub = open_dir(part, fd)
            if fd != root_fd:
                os.close(fd)
            fd = sub
    except BaseException:
        if fd != root_fd:
            os.close(fd)
        raise
    return fd


def _check_mounts(root: str, mountinfo: str = "/proc/self/mountinfo") -> None:
    """Step aside unless ``root`` lies on a local file system with no mount point below
    it (a mount inside the tree can change under a watch without an event)."""
    try:
        with open(mountinfo, "rb") as fh:
            lines = fh.read().decode("utf-8", "surrogateescape").splitlines()
    except OSError:
        raise _StepAside("the mounts cannot be read") from None
    best, fstype = "", ""
    for line in lines:
        fields = line.split(" ")
        try:
            point = _unescape(fields[4])
            fs = fields[fields.index("-", 6) + 1]
        except (IndexError, ValueError):
            raise _StepAside("a mount line cannot be read") from None
        if point == root or root.startswith(point.rstrip("/") + "/"):
            if len(point) >= len(best):
                best, fstype = point, fs
        elif point.startswith(root + "/"):
            raise _StepAside("a mount point inside the tree")
    if fstype not in LOCAL_FILE_SYSTEMS:
        raise _StepAside("the tree is not on a local file system")


def _unescape(field: str) -> str:
    """A mountinfo path: space, tab, newline and backslash come as octal escapes."""
    if "\\" not in field:
        return field
    out, i = [], 0
    while i < len(field):
        if field[i] == "\\" and field[i + 1 : i + 4].isdigit():
            out.append(chr(int(field[i + 1 : i + 4], 8)))
            i += 4
        else:
            out.append(field[i])
            i += 1
    return "".join(out)


def _parent(path: str) -> str:
    return path.rpartition("/")[0]
