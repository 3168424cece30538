"""Exclude rules: ``.fetchsyncignore`` files in gitignore syntax, for every verb and both ends.

The semantics are git's (``man gitignore``, git 2.39's ``dir.c`` and
``wildmatch.c``), checked against ``git check-ignore`` in the tests:

- blank lines and lines starting with ``#`` are skipped; ``\\#`` and ``\\!``
  escape a leading ``#`` or ``!``; trailing spaces are trimmed unless escaped
  with a backslash; a CR before the LF and a UTF-8 BOM are dropped;
- ``!pattern`` re-includes what a lower pattern excluded, but nothing under a
  directory that is itself excluded can be re-included;
- a pattern with a ``/`` at its start or in its middle is anchored to the
  directory holding the ignore file; otherwise it matches a name at any depth;
- a trailing ``/`` matches directories only (a symlink is not a directory);
- ``*``, ``?`` and ``[...]`` (``!``/``^`` negation, ranges, ``[:class:]``) never
  match ``/``; ``**/`` at the start, ``/**`` at the end and ``/**/`` in the middle
  span directories; any other ``**`` is a ``*`` (git quirk kept: right after
  the literal start of an anchored pattern it counts as leading, so ``a**/b``
  matches ``ax/y/b``); a malformed ``[`` or a trailing ``\\`` matches nothing;
  matching is on the bytes of the UTF-8 name (``?`` is one byte), and is
  case-sensitive (``core.ignorecase`` is not emulated);
- the last matching pattern wins.

Precedence, lowest first, the last match winning among the lists that apply
to a path: :data:`DEFAULT_PATTERNS` (like ``core.excludesFile``, so a
``.fetchsyncignore`` can re-include a default with ``!``), the root
``.fetchsyncignore``, nested ``.fetchsyncignore`` files (deeper ones win and
apply to their own subtree only, anchored at their own directory), and last
the ``--exclude`` patterns of the command line, anchored at the synced root.
A ``.fetchsyncignore`` is synced like any file, as git tracks ``.gitignore``.

Intended use. A tree scanner walks top-down and keeps the rules that apply::

    rules = IgnoreRules.build(extra=cli_excludes)
    text = read_ignore_file(root, "")
    if text is not None:
        rules = rules.with_file("", text)

    def scan(dirpath, rules):            # dirpath "" is the root
        for entry in os.scandir(os.path.join(root, dirpath)):
            rel = entry.name if not dirpath else dirpath + "/" + entry.name
            is_dir = entry.is_dir(follow_symlinks=False)
            if rules.ignored(rel, is_dir):
                continue                 # and never descend into it
            if is_dir:
                text = read_ignore_file(root, rel)
                sub = rules if text is None else rules.with_file(rel, text)
                scan(rel, sub)

Rules may also be accumulated over the whole tree (a file applies below its
own directory only, whatever else the rules hold), which is what a watcher
needs: it hears about one path at a time, keeps the rules of its last scan
(updated with :meth:`IgnoreRules.with_file` or
:meth:`IgnoreRules.without_file` when a ``.fetchsyncignore`` changes) and asks
:meth:`IgnoreRules.ignored_any`, which also checks every parent directory.
:meth:`IgnoreRules.explain` says which pattern decided, for "why is this file
not synced?".

Paths are POSIX paths relative to the synced root (``pkg/src/node.cpp``):
no leading or trailing ``/``, no ``.`` or ``..``. They are not validated on
each call, to keep matching fast; the wire layer validates them.

Standard library only, Python 3.6: this module runs on the robot.
"""

import errno
import os
import re
import stat
from functools import lru_cache
from typing import Any, Callable, Iterable, Optional, Sequence, Tuple

__all__ = [
    "DEFAULT_PATTERNS",
    "IGNORE_FILENAME",
    "VCS_NAMES",
    "MAX_IGNORE_FILE_SIZE",
    "IgnoreMatch",
    "IgnoreRules",
    "read_ignore_file",
]

IGNORE_FILENAME = ".fetchsyncignore"

# An ignore file is a few lines; a bigger one is a mistake (a renamed log?).
MAX_IGNORE_FILE_SIZE = 1 << 20

# Bound of the per-rules memo of directory verdicts used by ignored_any.
_DIR_CACHE_SIZE = 1 << 16

DEFAULT_PATTERNS: "tuple[str, ...]" = (
    # Version control metadata: never wanted on the robot, and large. `.git` has
    # no trailing slash because in submodules and worktrees it is a *file*.
    ".git",
    ".hg/",
    ".svn/",
    ".bzr/",
    # Python byte code: rebuilt on the robot by its own interpreter version.
    "__pycache__/",
    "*.pyc",
    "*.pyo",
    # Vim swap files (`.name.swp`, `.swo`, ... when the swap is beside the file,
    # `name.swp` with a `directory` setting) and the probe vim writes to test
    # whether a directory is writable before saving.
    "*.swp",
    "*.swo",
    "*.swx",
    ".*.sw?",
    "4913",
    # Backups of vim, emacs, gedit, nano (`name~`); emacs lock symlinks
    # (`.#name`, dangling on purpose) and auto-saves (`#name#`; the `#` is
    # escaped, or the line would be a comment).
    "*~",
    ".#*",
    "\\#*#",
    # Kate swap files.
    ".*.kate-swp",
    # Temporaries of safe-write saves: generic `.tmp`, JetBrains IDEs
    # (`name.___jb_tmp___`, `name.___jb_old___`), GIO/gedit (`.goutputstream-XXXXXX`).
    # They live for milliseconds and would race the rename that follows.
    "*.tmp",
    "*___jb_tmp___",
    "*___jb_old___",
    ".goutputstream-*",
    # macOS Finder metadata.
    ".DS_Store",
    # fetchsync's own state directory and the temporaries the robot-side
    # endpoint writes before renaming into place.
    ".fetchsync/",
    ".*.fetchsync-tmp-*",
    # Deliberately absent: build/, devel/, install/ (they live beside src/, not
    # in it), and CATKIN_IGNORE / COLCON_IGNORE, markers the robot's build needs.
)


# Version control directories are excluded whatever the patterns say: a `!.git`
# (from a robot's `.fetchsyncignore`, or anyone's) must never bring a
# `.git/config` whose `core.fsmonitor` or hooks git would run on the laptop.
VCS_NAMES = frozenset((b".git", b".hg", b".svn", b".bzr"))
_VCS_INSIDE = re.compile(rb"(?:^|/)\.(?:git|hg|svn|bzr)(?:/|$)")


def _in_vcs_dir(dirpart: bytes) -> bool:
    """Whether a directory path (``a/b``) is or lies inside a VCS directory."""
    return (
        b".git" in dirpart or b".hg" in dirpart or b".svn" in dirpart or b".bzr" in dirpart
    ) and _VCS_INSIDE.search(dirpart) is not None


# --------------------------------------------------------------------------
# Lines


def _trim_trailing_spaces(line: str) -> str:
    """Drop trailing spaces not escaped by a backslash (git's trim_trailing_spaces)."""
    if not line.endswith(" "):
        return line
    last_space = -1
    i, n = 0, len(line)
    while i < n:
        c = line[i]
        if c == " ":
            if last_space < 0:
                last_space = i
        elif c == "\\":
            i += 1
            if i >= n:
                return line
            last_space = -1
        else:
            last_space = -1
        i += 1
    return line if last_space < 0 else line[:last_space]


def _normalize_line(line: str) -> "str | None":
    """The pattern one line of an ignore file holds; None for a blank line or a comment."""
    # git reads lines as C strings: a NUL ends the pattern.
    line = line.split("\0", 1)[0]
    if line.endswith("\r"):
        line = line[:-1]
    if not line or line.startswith("#"):
        return None
    line = _trim_trailing_spaces(line)
    return line or None


def _parse_text(text: str) -> "tuple[str, ...]":
    """The patterns of an ignore file's text, in order."""
    if text.startswith("\ufeff"):
        text = text[1:]
    # Lines end at LF only, as in git (str.splitlines would split at \x0b, \x1c, ...).
    out = []
    for raw in text.split("\n"):
        line = _normalize_line(raw)
        if line is not None:
            out.append(line)
    return tuple(out)


def _check_lines(lines: "Iterable[Any]", what: str) -> "tuple[str, ...]":
    """Lines that must already be normalized patterns (wire input)."""
    if isinstance(lines, (str, bytes)) or not isinstance(lines, (list, tuple)):
        raise ValueError(f"{what}: expected a list of pattern strings")  # noqa: TRY004 (wire)
    out = []
    for line in lines:
        if not isinstance(line, str) or "\n" in line or _normalize_line(line) != line:
            raise ValueError(f"{what}: not a pattern line: {line!r}")
        out.append(line)
    return tuple(out)


def _check_dirpath(dirpath: "Any") -> str:
    """``dirpath`` if it is "" or a normalized relative POSIX path, else ValueError."""
    if not isinstance(dirpath, str):
        raise ValueError(f"directory path must be a string, not {dirpath!r}")  # noqa: TRY004 (wire)
    if dirpath == "":
        return dirpath
    if "\0" in dirpath or any(c in ("", ".", "..") for c in dirpath.split("/")):
        raise ValueError(f"not a normalized relative directory path: {dirpath!r}")
    return dirpath


def _depth(dirpath: str) -> int:
    return dirpath.count("/") + 1 if dirpath else 0


# --------------------------------------------------------------------------
# Patterns to regular expressions (on bytes, as git matches bytes)

_SLASH, _STAR, _QUESTION, _BRACKET, _BACKSLASH = b"/*?[\\"
_LITERAL = [re.escape(bytes([c])) for c in range(256)]
_NEVER = b"(?!)"

_UPPER = frozenset(range(ord("A"), ord("Z") + 1))
_LOWER = frozenset(range(ord("a"), ord("z") + 1))
_DIGIT = frozenset(range(ord("0"), ord("9") + 1))
# git's own ASCII ctype (not the C locale's): e.g. \v and \f are not [:space:].
_CLASSES = {
    b"alnum": _UPPER | _LOWER | _DIGIT,
    b"alpha": _UPPER | _LOWER,
    b"blank": frozenset(b" \t"),
    b"cntrl": frozenset(range(0x20)) | {0x7F},
    b"digit": _DIGIT,
    b"graph": frozenset(range(0x21, 0x7F)),
    b"lower": _LOWER,
    b"print": frozenset(range(0x20, 0x7F)),
    b"punct": frozenset(b"!\"#$%&'()*+,-./:;<=>?@[\\]^_`{|}~"),
    b"space": frozenset(b" \t\n\r"),
    b"upper": _UPPER,
    b"xdigit": _DIGIT | frozenset(b"abcdefABCDEF"),
}


def _simple_length(p: bytes) -> int:
    """Length of the leading part of ``p`` without wildcards or escapes (git's simple_length)."""
    for i, c in enumerate(p):
        if c in b"*?[\\":
            return i
    return len(p)


def _char_class(chars: "Iterable[int]") -> bytes:
    """A regex matching one byte of ``chars``; ``/`` never (git's WM_PATHNAME)."""
    members = sorted(set(chars) - {_SLASH})
    if not members:
        return _NEVER
    parts = []
    i = 0
    while i < len(members):
        j = i
        while j + 1 < len(members) and members[j + 1] == members[j] + 1:
            j += 1
        if j == i:
            parts.append(b"\\x%02x" % members[i])
        else:
            parts.append(b"\\x%02x-\\x%02x" % (members[i], members[j]))
        i = j + 1
    return b"[" + b"".join(parts) + b"]"


def _bracket(p: bytes, i: int) -> "tuple[bytes, int] | None":
    """Translate the bracket expression at ``p[i] == '['``: (regex, index after it).

    None when it is malformed (no closing ``]``, unknown ``[:class:]``): git's
    wildmatch then aborts, so the whole pattern matches nothing. The loop
    follows wildmatch.c so that ``]`` first is literal, ``-`` first or last is
    literal, a range after a range or class is not one, and so on.
    """
    n = len(p)
    i += 1
    if i >= n:
        return None
    negated = p[i] in b"!^"
    if negated:
        i += 1
    matched: "set[int]" = set()
    prev = 0
    while True:
        if i >= n:
            return None
        c = p[i]
        if c == _BACKSLASH:
            i += 1
            if i >= n:
                return None
            c = p[i]
            matched.add(c)
        elif c == ord("-") and prev and i + 1 < n and p[i + 1] != ord("]"):
            i += 1
            c = p[i]
            if c == _BACKSLASH:
                i += 1
                if i >= n:
                    return None
                c = p[i]
            matched.update(range(prev, c + 1))
            c = 0
        elif c == _BRACKET and i + 1 < n and p[i + 1] == ord(":"):
            start = i + 2
            end = p.find(b"]", start)
            if end < 0:
                return None
            if end - start - 1 < 0 or p[end - 1] != ord(":"):
                matched.add(c)  # not a class: a literal "[" (git rescans from the ":")
            else:
                members = _CLASSES.get(p[start : end - 1])
                if members is None:
                    return None
                matched.update(members)
                i = end
                c = 0
        else:
            matched.add(c)
        prev = c
        i += 1
        if i < n and p[i] == ord("]"):
            break
    if negated:
        matched = set(range(256)) - matched
    return _char_class(matched), i + 1


def _translate(p: bytes, *, pathname: bool) -> "bytes | None":
    """The regex (for fullmatch) of wildmatch pattern ``p``; None if it never matches.

    ``pathname`` is git's WM_PATHNAME: ``**`` may span directories. Without it
    (patterns matched against a basename) every ``*`` run is one ``*``.
    """
    out = []
    i, n = 0, len(p)
    while i < n:
        c = p[i]
        if c == _STAR:
            j = i + 1
            while j < n and p[j] == _STAR:
                j += 1
            if pathname and j - i >= 2 and (i == 0 or p[i - 1] == _SLASH):
                if j == n:  # trailing "**": everything, slashes included
                    out.append(b".*")
                    i = j
                    continue
                if p[j] == _SLASH:  # "**/": zero or more directories
                    out.append(b"(?:.*/)?")
                    i = j + 1
                    continue
                if p[j] == _BACKSLASH and j + 1 < n and p[j + 1] == _SLASH:
                    out.append(b".*")  # "**\/": git spans, without the zero-directory case
                    i = j
                    continue
            out.append(b"[^/]*")
            i = j
        elif c == _QUESTION:
            out.append(b"[^/]")
            i += 1
        elif c == _BRACKET:
            got = _bracket(p, i)
            if got is None:
                return None
            rx, i = got
            out.append(rx)
        elif c == _BACKSLASH:
            if i + 1 >= n:  # a trailing backslash matches nothing in git
                return None
            out.append(_LITERAL[p[i + 1]])
            i += 2
        else:
            out.append(_LITERAL[c])
            i += 1
    return b"".join(out)


class _Pattern:
    """One compiled pattern line."""

    __slots__ = ("_match", "basename", "dir_only", "line", "negated", "regex")

    def __init__(self, line: str) -> None:
        self.line = line
        p = line.encode("utf-8", "surrogateescape")
        self.negated = p.startswith(b"!")
        if self.negated:
            p = p[1:]
        self.dir_only = p.endswith(b"/")
        if self.dir_only:
            p = p[:-1]
        # Without a slash (the trailing one aside) it matches a name at any depth.
        self.basename = b"/" not in p
        regex: "bytes | None"
        if not p:
            regex = None
        elif self.basename:
            regex = _translate(p, pathname=False)
        else:
            # Anchored. Like git's match_pathname, the literal prefix is compared
            # apart and the rest matched as a pattern of its own, so a "**" right
            # after the prefix counts as leading ("a**/b" matches "ax/y/b" in git).
            prefix = _simple_length(p)
            if p.startswith(b"/"):
                p = p[1:]
                prefix -= 1
            rest = _translate(p[prefix:], pathname=True)
            regex = None if rest is None else re.escape(p[:prefix]) + rest
        self.regex = regex
        self._match: "Callable[[bytes], Any] | None" = None

    def matches(self, name: bytes, rel: bytes, is_dir: bool) -> bool:
        """Slow path, one pattern at a time (for explain)."""
        if self.regex is None or (self.dir_only and not is_dir):
            return False
        if self._match is None:
            self._match = re.compile(self.regex, re.DOTALL).fullmatch
        return self._match(name if self.basename else rel) is not None


# A run: consecutive patterns of the same sign, compiled together, since only
# "does any of them match" matters inside it. (negated, basename match, path match)
_Run = Tuple[bool, Optional[Callable[[bytes], Any]], Optional[Callable[[bytes], Any]]]


def _compile_runs(patterns: "Sequence[_Pattern]", is_dir: bool) -> "tuple[_Run, ...]":
    """The runs of ``patterns`` that can match, the last (winning) run first."""
    groups: "list[tuple[bool, list[bytes], list[bytes]]]" = []
    for pat in patterns:
        if pat.regex is None or (pat.dir_only and not is_dir):
            continue
        if not groups or groups[-1][0] != pat.negated:
            groups.append((pat.negated, [], []))
        _, names, paths = groups[-1]
        (names if pat.basename else paths).append(pat.regex)

    def join(rxs: "list[bytes]") -> "Callable[[bytes], Any] | None":
        if not rxs:
            return None
        return re.compile(b"|".join(b"(?:" + rx + b")" for rx in rxs), re.DOTALL).fullmatch

    return tuple((neg, join(names), join(paths)) for neg, names, paths in reversed(groups))


class _Compiled:
    """The compiled form of one sequence of pattern lines."""

    __slots__ = ("patterns", "runs")

    def __init__(self, lines: "tuple[str, ...]") -> None:
        self.patterns = tuple(_Pattern(line) for line in lines)
        # runs[is_dir]
        self.runs = (_compile_runs(self.patterns, False), _compile_runs(self.patterns, True))


@lru_cache(maxsize=512)
def _compiled(lines: "tuple[str, ...]") -> "_Compiled":
    return _Compiled(lines)


def _decide(runs: "tuple[_Run, ...]", name: bytes, rel: bytes) -> "bool | None":
    """True excluded, False re-included, None no pattern matched."""
    for negated, by_name, by_path in runs:
        if (by_name is not None and by_name(name) is not None) or (
            by_path is not None and by_path(rel) is not None
        ):
            return not negated
    return None


# --------------------------------------------------------------------------
# Rules


class IgnoreMatch:
    """The pattern that decided about a path, as :meth:`IgnoreRules.explain` reports it.

    ``origin`` is ``"default"``, ``"file"`` (the ``.fetchsyncignore`` in
    ``dirpath``) or ``"extra"`` (the command line). ``path`` is the path the
    pattern matched: the one asked about or an excluded parent directory.
    ``ignored`` is False when the pattern is a ``!`` re-include.
    """

    __slots__ = ("dirpath", "ignored", "origin", "path", "pattern")

    def __init__(self, origin: str, dirpath: str, pattern: str, path: str, ignored: bool) -> None:
        self.origin = origin
        self.dirpath = dirpath
        self.pattern = pattern
        self.path = path
        self.ignored = ignored

    def _key(self) -> "tuple[str, str, str, str, bool]":
        return (self.origin, self.dirpath, self.pattern, self.path, self.ignored)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, IgnoreMatch) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def __repr__(self) -> str:
        return (
            f"IgnoreMatch(origin={self.origin!r}, dirpath={self.dirpath!r}, "
            f"pattern={self.pattern!r}, path={self.path!r}, ignored={self.ignored!r})"
        )


class IgnoreRules:
    """An immutable set of exclude rules over one synced root.

    Build with :meth:`build`, add the ``.fetchsyncignore`` files met on the
    way down with :meth:`with_file`, ask :meth:`ignored` (walkers) or
    :meth:`ignored_any` (single paths). Patterns are compiled once, per file,
    and shared between the rules derived from one another.
    """

    __slots__ = (
        "_defaults",
        "_dir_cache",
        "_extra",
        "_files",
        "_nested",
        "_root_all",
        "_root_low",
        "_top",
    )

    def __init__(
        self,
        defaults: "tuple[str, ...]",
        files: "tuple[tuple[str, tuple[str, ...]], ...]",
        extra: "tuple[str, ...]",
    ) -> None:
        # Private: use build(), with_file() or from_wire(). `files` is sorted by
        # (depth, dirpath), one entry per directory, none empty.
        self._defaults = defaults
        self._files = files
        self._extra = extra
        root: "tuple[str, ...]" = ()
        nested: "dict[bytes, _Compiled]" = {}
        for dirpath, lines in files:
            if dirpath:
                nested[dirpath.encode("utf-8", "surrogateescape")] = _compiled(lines)
            else:
                root = lines
        # Root-anchored lists merged where precedence allows: fewer regex calls.
        self._root_all = _compiled(defaults + root + extra).runs
        self._root_low = _compiled(defaults + root).runs
        self._top = _compiled(extra).runs
        self._nested = nested
        # Directory -> "it or a parent is excluded", for ignored_any: a watcher
        # asks about many files in few directories. Invisible to callers.
        self._dir_cache: "dict[str, bool]" = {}

    # -- construction -----------------------------------------------------

    @classmethod
    def build(cls, *, defaults: bool = True, extra: "Iterable[str]" = ()) -> "IgnoreRules":
        """Rules with :data:`DEFAULT_PATTERNS` (unless ``defaults`` is false) and ``extra``.

        ``extra`` are the ``--exclude`` patterns: each is one line of a root
        ignore file (so ``#x`` is a comment, write ``\\#x``), of the highest
        precedence.
        """
        if isinstance(extra, (str, bytes)):
            raise TypeError("extra must be a sequence of patterns, not one string")
        lines = []
        for pattern in extra:
            if not isinstance(pattern, str) or "\n" in pattern:
                raise ValueError(f"not a one-line pattern: {pattern!r}")
            line = _normalize_line(pattern)
            if line is not None:
                lines.append(line)
        return cls(DEFAULT_PATTERNS if defaults else (), (), tuple(lines))

    def with_file(self, dirpath: str, text: str) -> "IgnoreRules":
        """These rules plus the ignore file ``text`` found in ``dirpath`` ("" for the root).

        It applies below ``dirpath``, anchored there, and takes precedence
        over files in parent directories. A file already known for
        ``dirpath`` is replaced (the watcher saw it change).
        """
        _check_dirpath(dirpath)
        if not isinstance(text, str):
            raise TypeError("ignore file text must be a string")
        return self._replace(dirpath, _parse_text(text))

    def without_file(self, dirpath: str) -> "IgnoreRules":
        """These rules without the ignore file of ``dirpath`` (it was deleted)."""
        return self._replace(_check_dirpath(dirpath), ())

    def _replace(self, dirpath: str, lines: "tuple[str, ...]") -> "IgnoreRules":
        files = [f for f in self._files if f[0] != dirpath]
        if lines:
            files.append((dirpath, lines))
        files.sort(key=lambda f: (_depth(f[0]), f[0]))
        return IgnoreRules(self._defaults, tuple(files), self._extra)

    # -- wire ---------------------------------------------------------------

    def to_wire(self) -> "list[list[Any]]":
        """JSON-able ``[[dirpath, [pattern, ...]], ...]``, lowest precedence first.

        The first entry is always the defaults (``""``), the last always the
        command-line patterns (``""``); between them the ignore files sorted
        by depth. The peer gets the exact patterns, never its own defaults.
        """
        out: "list[list[Any]]" = [["", list(self._defaults)]]
        out.extend([dirpath, list(lines)] for dirpath, lines in self._files)
        out.append(["", list(self._extra)])
        return out

    @classmethod
    def from_wire(cls, obj: "Any") -> "IgnoreRules":
        """The rules :meth:`to_wire` described; ValueError on any bad shape."""
        if not isinstance(obj, (list, tuple)) or len(obj) < 2:
            raise ValueError("ignore rules: expected a list of at least 2 entries")
        entries = []
        for k, entry in enumerate(obj):
            if not isinstance(entry, (list, tuple)) or len(entry) != 2:
                raise ValueError(f"ignore rules entry {k}: expected [dirpath, patterns]")
            dirpath = _check_dirpath(entry[0])
            entries.append((dirpath, _check_lines(entry[1], f"ignore rules entry {k}")))
        if entries[0][0] or entries[-1][0]:
            raise ValueError("ignore rules: the first and last entries must be for the root")
        files = entries[1:-1]
        seen = set()
        last_depth = 0
        for dirpath, _ in files:
            if dirpath in seen or _depth(dirpath) < last_depth:
                raise ValueError("ignore rules: files must be unique and sorted by depth")
            seen.add(dirpath)
            last_depth = _depth(dirpath)
        kept = sorted((f for f in files if f[1]), key=lambda f: (_depth(f[0]), f[0]))
        return cls(entries[0][1], tuple(kept), entries[-1][1])

    # -- matching -----------------------------------------------------------

    def ignored(self, path: str, is_dir: bool) -> bool:
        """Whether ``path`` is excluded by the patterns that apply to it.

        Parent directories are not checked: a walker asks top-down and does
        not descend into an excluded directory. ``is_dir`` is true for a
        directory, false for a file or a symlink (even to a directory).
        """
        bpath = path.encode("utf-8", "surrogateescape")
        slash = bpath.rfind(b"/")
        name = bpath[slash + 1 :] if slash >= 0 else bpath
        if name in VCS_NAMES or (slash > 0 and _in_vcs_dir(bpath[:slash])):
            return True  # whatever a pattern says: see VCS_NAMES
        d = 1 if is_dir else 0
        nested = self._nested
        if nested and slash > 0:
            found: "list[tuple[int, _Compiled]]" = []
            j = slash
            while j > 0:
                compiled = nested.get(bpath[:j])
                if compiled is not None:
                    found.append((j, compiled))
                j = bpath.rfind(b"/", 0, j)
            if found:  # deepest first, between the command line and the root
                verdict = _decide(self._top[d], name, bpath)
                if verdict is not None:
                    return verdict
                for j, compiled in found:
                    verdict = _decide(compiled.runs[d], name, bpath[j + 1 :])
                    if verdict is not None:
                        return verdict
                return _decide(self._root_low[d], name, bpath) is True
        # Inlined _decide over the merged root lists: the hot path of a scan.
        for negated, by_name, by_path in self._root_all[d]:
            if (by_name is not None and by_name(name) is not None) or (
                by_path is not None and by_path(bpath) is not None
            ):
                return not negated
        return False

    def ignored_any(self, path: str, is_dir: bool) -> bool:
        """Whether ``path`` or any of its parent directories is excluded.

        For single paths (a watcher's events): as in git, nothing under an
        excluded directory can be re-included.
        """
        slash = path.rfind("/")
        if slash > 0 and self._dir_excluded(path[:slash]):
            return True
        return self.ignored(path, is_dir)

    def _dir_excluded(self, dirpath: str) -> bool:
        """Whether directory ``dirpath`` or one of its parents is excluded (memoized)."""
        cache = self._dir_cache
        verdict = cache.get(dirpath)
        if verdict is not None:
            return verdict
        # Climb to the deepest known ancestor, then decide top-down from there.
        pending = [dirpath]
        excluded = False
        j = dirpath.rfind("/")
        while j > 0:
            parent = dirpath[:j]
            known = cache.get(parent)
            if known is not None:
                excluded = known
                break
            pending.append(parent)
            j = dirpath.rfind("/", 0, j)
        if len(cache) > _DIR_CACHE_SIZE:
            cache.clear()
        for d in reversed(pending):
            excluded = excluded or self.ignored(d, True)
            cache[d] = excluded
        return excluded

    def explain(self, path: str, is_dir: bool) -> "IgnoreMatch | None":
        """The pattern that decides about ``path`` as :meth:`ignored_any` sees it, or None.

        Slow (one pattern at a time); for messages and debugging, not scans.
        """
        j = path.find("/")
        while j >= 0:
            match = self._explain_own(path[:j], True)
            if match is not None and match.ignored:
                return match
            j = path.find("/", j + 1)
        return self._explain_own(path, is_dir)

    def _explain_own(self, path: str, is_dir: bool) -> "IgnoreMatch | None":
        bpath = path.encode("utf-8", "surrogateescape")
        name = bpath[bpath.rfind(b"/") + 1 :]
        lists: "list[tuple[str, str, tuple[str, ...]]]" = [("extra", "", self._extra)]
        for dirpath, lines in reversed(self._files):
            lists.append(("file", dirpath, lines))
        lists.append(("default", "", self._defaults))
        for origin, dirpath, lines in lists:
            if dirpath:
                prefix = dirpath.encode("utf-8", "surrogateescape") + b"/"
                if not bpath.startswith(prefix):
                    continue
                rel = bpath[len(prefix) :]
            else:
                rel = bpath
            for pat in reversed(_compiled(lines).patterns):
                if pat.matches(name, rel, is_dir):
                    return IgnoreMatch(origin, dirpath, pat.line, path, not pat.negated)
        return None

    # -- value semantics ----------------------------------------------------

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, IgnoreRules):
            return NotImplemented
        return (self._defaults, self._files, self._extra) == (
            other._defaults,
            other._files,
            other._extra,
        )

    def __hash__(self) -> int:
        return hash((self._defaults, self._files, self._extra))

    def __repr__(self) -> str:
        files = [d for d, _ in self._files]
        return (
            f"IgnoreRules(defaults={len(self._defaults)} patterns, files={files!r}, "
            f"extra={list(self._extra)!r})"
        )


# --------------------------------------------------------------------------
# Files


def read_ignore_file(root: str, dirpath: str) -> "str | None":
    """The text of ``root/dirpath/.fetchsyncignore``, or None if there is none.

    Neither the file nor any directory of ``dirpath`` is followed through a
    symlink (git does not follow a symlinked ``.gitignore`` either, and a
    link must not read outside the root); a symlink, a directory or any
    other non-regular file counts as no file. Undecodable bytes are kept
    with ``surrogateescape``, so they match the same bytes in names.
    Raises ValueError for a bad ``dirpath`` or a file over
    :data:`MAX_IGNORE_FILE_SIZE`, OSError for other failures to read.
    """
    _check_dirpath(dirpath)
    parts = dirpath.split("/") if dirpath else []
    cloexec = getattr(os, "O_CLOEXEC", 0)
    nofollow = getattr(os, "O_NOFOLLOW", 0)
    # O_NONBLOCK: a FIFO named .fetchsyncignore must not hang the scan.
    file_flags = os.O_RDONLY | cloexec | nofollow | getattr(os, "O_NONBLOCK", 0)
    if os.open not in os.supports_dir_fd or not nofollow:
        return _read_ignore_file_by_path(root, parts)
    dir_flags = os.O_RDONLY | cloexec | nofollow | getattr(os, "O_DIRECTORY", 0)
    fd = os.open(root, os.O_RDONLY | cloexec | getattr(os, "O_DIRECTORY", 0))
    try:
        for part in parts:
            try:
                sub = os.open(part, dir_flags, dir_fd=fd)
            except OSError as exc:
                if _is_absent(exc):
                    return None
                raise
            os.close(fd)
            fd = sub
        try:
            ffd = os.open(IGNORE_FILENAME, file_flags, dir_fd=fd)
        except OSError as exc:
            if _is_absent(exc):
                return None
            raise
    finally:
        os.close(fd)
    try:
        if not stat.S_ISREG(os.fstat(ffd).st_mode):
            return None
        data = _read_fd(ffd, MAX_IGNORE_FILE_SIZE + 1)
    finally:
        os.close(ffd)
    return _decode(data, dirpath)


def _read_fd(fd: int, limit: int) -> bytes:
    """Up to ``limit`` bytes of ``fd``."""
    chunks = []
    while limit > 0:
        chunk = os.read(fd, min(limit, 1 << 16))
        if not chunk:
            break
        chunks.append(chunk)
        limit -= len(chunk)
    return b"".join(chunks)


def _is_absent(exc: "OSError") -> bool:
    # ELOOP / EMLINK (some BSDs) / ENOTDIR: a symlink under O_NOFOLLOW or a file
    # where a directory was expected. ENXIO: a socket opened with O_NONBLOCK.
    return exc.errno in (errno.ENOENT, errno.ELOOP, errno.EMLINK, errno.ENOTDIR, errno.ENXIO)


def _read_ignore_file_by_path(root: str, parts: "list[str]") -> "str | None":
    """Fallback without dir_fd support: the same checks with lstat (racy, but portable)."""
    path = root
    for k, part in enumerate(parts + [IGNORE_FILENAME]):
        path = os.path.join(path, part)
        try:
            mode = os.lstat(path).st_mode
        except FileNotFoundError:
            return None
        if not (stat.S_ISDIR(mode) if k < len(parts) else stat.S_ISREG(mode)):
            return None
    with open(path, "rb") as f:
        data = f.read(MAX_IGNORE_FILE_SIZE + 1)
    return _decode(data, "/".join(parts))


def _decode(data: bytes, dirpath: str) -> str:
    if len(data) > MAX_IGNORE_FILE_SIZE:
        where = dirpath + "/" + IGNORE_FILENAME if dirpath else IGNORE_FILENAME
        raise ValueError(f"{where} is larger than {MAX_IGNORE_FILE_SIZE} bytes")
    return data.decode("utf-8", "surrogateescape")


def build_rules(excludes: "Iterable[str]" = ()) -> "IgnoreRules":
    """Every verb's rules: the defaults, the ``.fetchsyncignore`` files, ``--exclude``."""
    return IgnoreRules.build(defaults=True, extra=tuple(excludes))
