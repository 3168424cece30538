"""The tree model: what a synced root holds, as a flat map of wire paths to entries.

Entries carry what change detection needs without reading content: kind, mode,
size, mtime_ns, ctime_ns, inode (whole-second mtimes are never trusted).
Content hashes are added by callers that keep a cache (the laptop's state, the
robot's index), so a scan itself only stats.
"""

import errno
import os
import stat as stat_mod
import sys
from functools import partial
from stat import S_ISDIR, S_ISLNK, S_ISREG
from typing import TYPE_CHECKING, Any, Callable, Dict, Iterator, List, NamedTuple, Optional, Tuple

if TYPE_CHECKING:
    from fetchsync.protocol.ignore import IgnoreRules

FILE = "f"
DIR = "d"
LINK = "l"

IGNORE_FILE = ".fetchsyncignore"


class Entry(NamedTuple):
    kind: str  # FILE, DIR or LINK
    mode: int  # permission bits (0o7777); 0 for links
    size: int  # bytes for files, 0 otherwise
    mtime_ns: int
    ctime_ns: int
    ino: int
    target: str = ""  # symlink target

    def same_stat(self, other: "Entry") -> bool:
        return (
            self.kind == other.kind
            and self.mode == other.mode
            and self.size == other.size
            and self.mtime_ns == other.mtime_ns
            and self.ctime_ns == other.ctime_ns
            and self.ino == other.ino
            and self.target == other.target
        )


def entry_from_stat(st: "os.stat_result", target: str = "") -> "Optional[Entry]":
    mode = st.st_mode
    if stat_mod.S_ISREG(mode):
        return Entry(
            FILE, stat_mod.S_IMODE(mode), st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino
        )
    if stat_mod.S_ISDIR(mode):
        return Entry(DIR, stat_mod.S_IMODE(mode), 0, st.st_mtime_ns, st.st_ctime_ns, st.st_ino)
    if stat_mod.S_ISLNK(mode):
        return Entry(LINK, 0, 0, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, target)
    return None


def stat_path(full: str) -> "Optional[Entry]":
    """The entry at ``full`` (not following symlinks), or None if absent or special."""
    try:
        st = os.lstat(full)
    except (FileNotFoundError, NotADirectoryError):
        return None
    target = ""
    if stat_mod.S_ISLNK(st.st_mode):
        try:
            target = os.fsdecode(os.readlink(full))
        except OSError:
            return None
    return entry_from_stat(st, target)


class ScanResult(NamedTuple):
    entries: "Dict[str, Entry]"
    skipped: "List[Tuple[str, str]]"  # (path, reason): sockets, FIFOs, unreadable dirs


def scan(
    root: str,
    rules: "Optional[IgnoreRules]" = None,
    *,
    is_temp: "Optional[Callable[[str], bool]]" = None,
    start: str = "",
    on_dir: "Optional[Callable[[str, str], None]]" = None,
    rules_out: "Optional[Dict[str, object]]" = None,
) -> "ScanResult":
    """Stat every entry under ``root`` (not following symlinks), honouring ``rules``.

    ``rules`` is an ``IgnoreRules`` (or None); ``.fetchsyncignore`` files met on
    the way extend it for their subtree. Returns a flat map of wire paths.
    ``start`` (a wire path of a directory under ``root``) scans only below it,
    with the ignore files of its ancestors applied. ``on_dir(full, rel)`` is
    called for each directory before it is listed (to watch it), and
    ``rules_out`` receives the rules in force below each listed directory.
    """
    entries = {}  # type: Dict[str, Entry]
    skipped = []  # type: List[Tuple[str, str]]
    if start and rules is not None:
        parts = start.split("/")
        for depth in range(len(parts)):
            anc = "/".join(parts[:depth])
            try:
                with open(
                    os.path.join(root, anc, IGNORE_FILE),
                    "r",
                    encoding="utf-8",
                    errors="surrogateescape",
                ) as fh:
                    rules = rules.with_file(anc, fh.read())
            except OSError:
                pass
    stack = [(start, rules)]
    while stack:
        rel, dir_rules = stack.pop()
        full = os.path.join(root, rel) if rel else root
        try:
            if on_dir is not None:
                on_dir(full, rel)
            it = os.scandir(full)
        except OSError as exc:
            if rel:
                skipped.append((rel, "cannot list: %s" % (exc.strerror or exc)))
            else:
                raise
            continue
        with it:
            items = list(it)
        if dir_rules is not None:
            for de in items:
                if de.name == IGNORE_FILE and de.is_file(follow_symlinks=False):
                    try:
                        with open(de.path, "r", encoding="utf-8", errors="surrogateescape") as fh:
                            dir_rules = dir_rules.with_file(rel, fh.read())
                    except OSError as exc:
                        skipped.append(
                            (
                                rel + "/" + IGNORE_FILE if rel else IGNORE_FILE,
                                "cannot read: %s" % exc.strerror,
                            )
                        )
                    break
        if rules_out is not None:
            rules_out[rel] = dir_rules
        for de, path in _kept(items, rel, dir_rules, is_temp):
            if _record(de, path, partial(os.readlink, de.path), entries, skipped):
                stack.append((path, dir_rules))
    return ScanResult(entries, skipped)


def _kept(
    items: "List[Any]",
    rel: str,
    dir_rules: "Optional[IgnoreRules]",
    is_temp: "Optional[Callable[[str], bool]]",
) -> "Iterator[Tuple[Any, str]]":
    """The directory entries of ``items`` (a listing of wire path ``rel``) that neither
    ``is_temp`` nor the rules exclude, with their wire paths."""
    for de in items:
        name = de.name
        if is_temp is not None and is_temp(name):
            continue
        path = rel + "/" + name if rel else name
        try:
            # d_type from the directory listing: no syscall; decides the
            # ignore rules before paying for a stat
            is_dir = de.is_dir(follow_symlinks=False)
        except OSError:
            continue
        if dir_rules is not None and dir_rules.ignored(path, is_dir):
            continue
        yield de, path


def _record(
    de: "Any",
    path: str,
    readlink: "Callable[[], Any]",
    entries: "Dict[str, Entry]",
    skipped: "List[Tuple[str, str]]",
) -> bool:
    """Record the entry ``de`` at wire path ``path`` (``readlink()`` reads a symlink's
    target); True when it is a directory to list in turn."""
    try:
        st = de.stat(follow_symlinks=False)
    except OSError:
        return False  # vanished while we looked
    mode = st.st_mode
    if S_ISREG(mode):
        entries[path] = Entry(
            FILE, mode & 0o7777, st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino
        )
    elif S_ISDIR(mode):
        entries[path] = Entry(DIR, mode & 0o7777, 0, st.st_mtime_ns, st.st_ctime_ns, st.st_ino)
        return True
    elif S_ISLNK(mode):
        try:
            target = os.fsdecode(readlink())
        except OSError:
            return False
        entries[path] = Entry(LINK, 0, 0, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, target)
    else:
        skipped.append((path, "not a regular file, directory or symlink"))
    return False


def _read_at(name: str, dir_fd: int, limit: int = 1 << 20) -> "Optional[bytes]":
    """The content of regular file ``name`` in ``dir_fd`` (not through a symlink), or None."""
    from fetchsync.protocol.paths import O_FILE

    try:
        fd = os.open(name, O_FILE, dir_fd=dir_fd)
    except OSError:
        return None
    try:
        if not S_ISREG(os.fstat(fd).st_mode):
            return None
        parts = []
        while limit > 0:
            block = os.read(fd, min(limit, 1 << 16))
            if not block:
                break
            parts.append(block)
            limit -= len(block)
        return b"".join(parts)
    finally:
        os.close(fd)


def scandir_fd(fd: int) -> "Any":
    """``os.scandir`` of the directory open at ``fd``: Python 3.6's takes no descriptor, so
    there it lists ``/proc/self/fd/N``, which names that very directory (not a path that
    could be swapped meanwhile); its entries' ``stat()`` go through it the same way."""
    if sys.version_info >= (3, 7):
        return os.scandir(fd)
    return os.scandir("/proc/self/fd/%d" % fd)


def _list_dir(
    fd: int,
    rel: str,
    dir_rules: "Optional[IgnoreRules]",
    is_temp: "Optional[Callable[[str], bool]]",
    entries: "Dict[str, Entry]",
    skipped: "List[Tuple[str, str]]",
) -> "Tuple[List[str], Optional[IgnoreRules]]":
    """Record the entries of the directory at ``fd`` (wire path ``rel``); the names of its
    subdirectories and the rules in force below it."""
    with scandir_fd(fd) as it:
        items = list(it)
    if dir_rules is not None:
        for de in items:
            if de.name == IGNORE_FILE:
                text = _read_at(IGNORE_FILE, fd)
                if text is not None:
                    dir_rules = dir_rules.with_file(rel, text.decode("utf-8", "surrogateescape"))
                break
    subdirs = []
    for de, path in _kept(items, rel, dir_rules, is_temp):
        if _record(de, path, partial(os.readlink, de.name, dir_fd=fd), entries, skipped):
            subdirs.append(de.name)
    return subdirs, dir_rules


def scan_fd(
    root_fd: int,
    rules: "Optional[IgnoreRules]" = None,
    *,
    is_temp: "Optional[Callable[[str], bool]]" = None,
    prefix: str = "",
    on_dir: "Optional[Callable[[int, str], None]]" = None,
    rules_out: "Optional[Dict[str, Any]]" = None,
) -> "ScanResult":
    """:func:`scan` of the directory held by ``root_fd``, each directory opened from its
    parent's descriptor without following symlinks (a directory swapped for a symlink
    while we look is skipped, never followed). ``prefix``: the wire path of ``root_fd``'s
    directory, which the paths returned start with. At most one descriptor per level
    is open at a time; ``root_fd`` stays open. ``on_dir(fd, rel)`` is called for each
    directory before it is listed (to watch it), and ``rules_out`` receives the rules
    in force below each listed directory."""
    from fetchsync.protocol.paths import NOT_A_DIR, open_dir

    entries = {}  # type: Dict[str, Entry]
    skipped = []  # type: List[Tuple[str, str]]

    if on_dir is not None:
        on_dir(root_fd, prefix)
    names, top_rules = _list_dir(root_fd, prefix, rules, is_temp, entries, skipped)
    if rules_out is not None:
        rules_out[prefix] = top_rules
    stack = [(root_fd, prefix, top_rules, iter(names))]
    try:
        while stack:
            fd, rel, dir_rules, todo = stack[-1]
            name = next(todo, None)
            if name is None:
                stack.pop()
                if fd != root_fd:
                    os.close(fd)
                continue
            path = rel + "/" + name if rel else name
            try:
                sub = open_dir(name, fd)
            except OSError as exc:
                if exc.errno in NOT_A_DIR or exc.errno == errno.ENOENT:
                    entries.pop(path, None)  # swapped for something else, or gone, meanwhile
                    continue
                skipped.append((path, "cannot list: %s" % (exc.strerror or exc)))
                continue
            try:
                if on_dir is not None:
                    on_dir(sub, path)
                names, sub_rules = _list_dir(sub, path, dir_rules, is_temp, entries, skipped)
            except OSError as exc:
                os.close(sub)
                skipped.append((path, "cannot list: %s" % (exc.strerror or exc)))
                continue
            if rules_out is not None:
                rules_out[path] = sub_rules
            stack.append((sub, path, sub_rules, iter(names)))
    finally:
        for fd, _rel, _rules, _todo in stack:
            if fd != root_fd:
                os.close(fd)
    return ScanResult(entries, skipped)
