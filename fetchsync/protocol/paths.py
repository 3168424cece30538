"""Paths on the wire: relative, normalised, inside the root. Checked on both ends.

A wire path is a ``str`` of ``/``-separated components with no empty, ``.``
or ``..`` component, no leading ``/`` and no NUL. Names that are not UTF-8
travel as ``os.fsdecode`` strings (surrogate escapes), which JSON carries.
"""

from __future__ import annotations

import os
import stat as stat_mod

from fetchsync.protocol.errors import PathError

MAX_PATH = 4096
MAX_NAME = 255
_NOT_NAMES = frozenset(("", ".", ".."))
FULL_CACHE = 4096


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


def ancestors(path: str) -> list[str]:
    """Every proper ancestor of ``path``, outermost first."""
    parts = path.split("/")
    return ["/".join(parts[:i]) for i in range(1, len(parts))]


def is_within(path: str, top: str) -> bool:
    return path == top or path.startswith(top + "/")


class Resolver:
    """Maps wire paths to filesystem paths under ``root`` without following symlinks.

    A write must never go through a symlink out of the root: every ancestor
    directory of a target is checked with ``lstat`` to be a real directory
    (cached per instance, so a batch pays once per directory).
    """

    def __init__(self, root: str) -> None:
        self.root = root
        self._dirs_ok = {"": True}  # type: dict[str, bool]
        # the paths validated lately, with their full paths: an operation asks for
        # its path's three or four times (check, write, rename, record)
        self._full = {}  # type: dict[str, str]

    def full(self, path: str) -> str:
        try:
            return self._full[path]
        except (KeyError, TypeError):  # TypeError: not a string, which validate() says
            pass
        if len(self._full) >= FULL_CACHE:
            self._full.clear()
        out = self._full[path] = os.path.join(self.root, validate(path))
        return out

    def check_parents(self, path: str) -> None:
        """Raise PathError unless every ancestor of ``path`` is a real directory."""
        self.full(path)  # valid
        i = path.rfind("/")
        if i < 0 or self._dirs_ok.get(path[:i]):
            # a directory is known good only once its ancestors were, and forget()
            # drops what lies below a directory with it: the parent vouches for them
            return
        for anc in ancestors(path):
            if self._dirs_ok.get(anc):
                continue
            try:
                st = os.lstat(os.path.join(self.root, anc))
            except FileNotFoundError:
                raise PathError("parent directory missing: %r" % anc)
            if not stat_mod.S_ISDIR(st.st_mode):
                raise PathError("parent is not a directory (a symlink?): %r" % anc)
            self._dirs_ok[anc] = True

    def known_dir(self, path: str) -> None:
        """Record ``path`` as a real directory (one just made and checked), whose
        ancestors ``check_parents`` found real before it was made."""
        self._dirs_ok[path] = True

    def forget(self, path: str) -> None:
        """Drop cached knowledge about ``path`` and below (it was removed or replaced)."""
        for key in [k for k in self._dirs_ok if k and is_within(k, path)]:
            del self._dirs_ok[key]
