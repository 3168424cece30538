"""Paths on the wire: relative, normalised, inside the root. Checked on both ends.

A wire path is a ``str`` of ``/``-separated components with no empty, ``.``
or ``..`` component, no leading ``/`` and no NUL. Names that are not UTF-8
travel as ``os.fsdecode`` strings (surrogate escapes), which JSON carries.
"""

import errno
import os
from contextlib import contextmanager
from typing import Dict, Iterator, Optional, Tuple

from fetchsync.protocol.errors import PathError

MAX_PATH = 4096
MAX_NAME = 255
_NOT_NAMES = frozenset(("", ".", ".."))


def validate(path: str) -> str:
    """Return ``path`` if it is a valid wire path, else raise PathError."""
    if not isinstance(path, str) or not path:
        raise PathError("empty or non-string path")
    if len(path) > MAX_PATH:
        raise PathError("path too long: %r..." % path[:64])
    if "\x00" in path:
        raise PathError("path contains NUL: %r" % path)
    if path.startswith("/"):
        raise PathError("absolute path: %r" % path)
    for part in path.split("/"):
        if part in _NOT_NAMES:
            raise PathError("path is not normalised or leaves the root: %r" % path)
        # a character encodes to at most 4 bytes: only long names need encoding
        if len(part) > MAX_NAME // 4 and len(os.fsencode(part)) > MAX_NAME:
            raise PathError("name too long in %r" % path)
    return path


def parent(path: str) -> str:
    """The parent of a wire path; ``""`` for a top-level entry."""
    i = path.rfind("/")
    return path[:i] if i >= 0 else ""


def ancestors(path: str) -> "list[str]":
    """Every proper ancestor of ``path``, outermost first."""
    parts = path.split("/")
    return ["/".join(parts[:i]) for i in range(1, len(parts))]


def is_within(path: str, top: str) -> bool:
    return path == top or path.startswith(top + "/")


# a directory of the tree, opened without following a symlink in its last component
O_DIR = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
# a file of the tree, read: not through a symlink, and a FIFO planted there does not block
O_FILE = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
# the errors of opening a symlink (ELOOP) or a file (ENOTDIR) as a directory under O_NOFOLLOW
NOT_A_DIR = (errno.ELOOP, errno.ENOTDIR, errno.EMLINK)


def open_dir(name: str, dir_fd: int) -> int:
    """A descriptor of the directory ``name`` (one component) in ``dir_fd``; an OSError if it
    is absent, or a symlink or anything else (ELOOP, ENOTDIR)."""
    return os.open(name, O_DIR, dir_fd=dir_fd)


def mkdir_open(name: str, dir_fd: int, mode: int = 0o700) -> int:
    """:func:`open_dir`, the directory made first where it is missing."""
    try:
        return os.open(name, O_DIR, dir_fd=dir_fd)
    except FileNotFoundError:
        pass
    try:
        os.mkdir(name, mode, dir_fd=dir_fd)
    except FileExistsError:
        pass
    return os.open(name, O_DIR, dir_fd=dir_fd)


class Root:
    """A tree held by the descriptor of its top directory: the only way the endpoint
    reaches a path in it.

    Each operation walks its wire path's directories one component at a time from
    that descriptor, each opened with ``O_NOFOLLOW | O_DIRECTORY``, and acts on the
    last component through the ``dir_fd`` forms of the system calls: a directory
    swapped for a symlink at any moment makes the walk fail, and cannot redirect
    the operation out of the tree. Nothing found on one walk is trusted on the next
    (mutagen's ``pkg/filesystem`` does the same)."""

    def __init__(self, fd: int, shown: str) -> None:
        self.fd = fd
        self.shown = shown  # for messages only

    def open_dir(self, path: str) -> int:
        """A new descriptor of the directory at wire path ``path`` (``""``: the top)."""
        if not path:
            return os.dup(self.fd)
        fd = self.fd
        parts = validate(path).split("/")
        for k, part in enumerate(parts):
            try:
                sub = os.open(part, O_DIR, dir_fd=fd)
            except OSError as exc:
                where = "/".join(parts[: k + 1])
                if fd != self.fd:
                    os.close(fd)
                if exc.errno == errno.ENOENT:
                    raise PathError("directory missing: %r" % where) from None
                if exc.errno in NOT_A_DIR:
                    raise PathError("not a directory (a symlink?): %r" % where) from None
                raise
            if fd != self.fd:
                os.close(fd)
            fd = sub
        return fd

    @contextmanager
    def parent(self, path: str) -> "Iterator[Tuple[int, str]]":
        """``(descriptor of path's directory, path's last component)``, for one operation."""
        i = validate(path).rfind("/")
        if i < 0:
            yield self.fd, path
            return
        fd = self.open_dir(path[:i])
        try:
            yield fd, path[i + 1 :]
        finally:
            os.close(fd)


class Dirs:
    """The directories one batch writes in, their descriptors kept for the batch (a burst of
    new files in one directory walks it once, not twice per file), each CHECKED AGAIN
    before every use: every component of its path, from the root's descriptor outwards,
    must still name the very directory (device and inode) the kept descriptor holds, as
    the walk of :meth:`Root.open_dir` would find it. Where one no longer does (a directory
    moved, deleted, or swapped for a symlink since), it is opened afresh from its checked
    parent with ``O_NOFOLLOW | O_DIRECTORY``: a symlink then fails the operation exactly as
    a fresh walk does. A descriptor is never trusted beyond that one check: the window
    between the check and the call that uses it is a fresh walk's own. The descriptors held
    are bounded (:data:`Dirs.KEEP`); paths deeper than :data:`Dirs.DEPTH` are not kept
    (the caller walks them with :meth:`Root.parent`)."""

    KEEP = 64  # descriptors held at most (all closed when a walk would pass it)
    DEPTH = 16  # directories deeper than this are walked afresh, not kept

    def __init__(self, root: Root) -> None:
        self.root = root
        self.kept: "Dict[str, Tuple[int, int, int]]" = {}  # path: (fd, st_dev, st_ino)

    def parent(self, path: str) -> "Optional[Tuple[int, str]]":
        """``(descriptor of path's directory, last component)``, the descriptor this
        cache's (not to be closed); None where the path is too deep to keep."""
        i = path.rfind("/")
        if i < 0:
            return self.root.fd, path
        top = path[:i]
        parts = top.split("/")
        if len(parts) > self.DEPTH:
            return None
        if len(self.kept) + len(parts) > self.KEEP:
            self.close()
        fd = self.root.fd
        where = ""
        for part in parts:
            where = where + "/" + part if where else part
            held = self.kept.get(where)
            if held is not None:
                try:
                    st = os.stat(part, dir_fd=fd, follow_symlinks=False)
                except OSError:
                    st = None
                if st is not None and st.st_ino == held[2] and st.st_dev == held[1]:
                    fd = held[0]
                    continue
                del self.kept[where]
                os.close(held[0])
            try:
                sub = os.open(part, O_DIR, dir_fd=fd)
            except OSError as exc:
                if exc.errno == errno.ENOENT:
                    raise PathError("directory missing: %r" % where) from None
                if exc.errno in NOT_A_DIR:
                    raise PathError("not a directory (a symlink?): %r" % where) from None
                raise
            try:
                st = os.fstat(sub)
            except BaseException:
                os.close(sub)
                raise
            self.kept[where] = (sub, st.st_dev, st.st_ino)
            fd = sub
        return fd, path[i + 1 :]

    def close(self) -> None:
        kept, self.kept = self.kept, {}
        for fd, _dev, _ino in kept.values():
            os.close(fd)


def lstat_at(name: str, dir_fd: int) -> "Optional[os.stat_result]":
    """``name``'s lstat in ``dir_fd``, or None if there is nothing there."""
    try:
        return os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
    except (FileNotFoundError, NotADirectoryError):
        return None
