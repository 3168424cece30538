"""The laptop's memory of the last sync, per (robot, remote workspace).

For every path it holds what the robot was left holding (kind, mode, content
hash or link target), the local stat at that moment (so an unchanged file is
recognised without reading it) and, for larger files, the content's delta
signature (so an edit is sent as a delta without asking the robot). It also
holds the robot index's epoch and generation: when they still match, the robot
has not been written by anyone else since, and one round trip suffices.

Stored in SQLite under ``$XDG_STATE_HOME/fetchsync/`` (one file per target),
updated in one transaction per batch, so a killed push leaves it consistent.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import sqlite3
import time
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Iterator, NamedTuple

from fetchsync.errors import StateError
from fetchsync.protocol import messages as M

if TYPE_CHECKING:
    from fetchsync.config import Target

SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS entries (
    path BLOB PRIMARY KEY,
    kind TEXT NOT NULL, mode INTEGER NOT NULL, hash TEXT NOT NULL, target TEXT NOT NULL,
    size INTEGER NOT NULL, mtime_ns INTEGER NOT NULL, ctime_ns INTEGER NOT NULL, ino INTEGER NOT NULL,
    sig BLOB
);
"""


class Synced(NamedTuple):
    """What was last synced at a path, and the local stat when it was (a NamedTuple: cheap
    to build by the thousand)."""

    kind: str
    mode: int
    hash: str
    target: str
    size: int = -1
    mtime_ns: int = -1
    ctime_ns: int = -1
    ino: int = -1

    def listed(self, path: str) -> M.Listed:
        return M.Listed(
            path,
            self.kind,
            self.mode,
            self.size if self.kind == "f" else 0,
            hash=self.hash,
            target=self.target,
        )

    def expectation(self) -> str:
        if self.kind == "d":
            return M.IS_DIR
        if self.kind == "l":
            return M.expect_link(self.target)
        return M.expect_file(self.hash)


def state_dir() -> Path:
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(
        os.path.expanduser("~"), ".local", "state"
    )
    return Path(base) / "fetchsync"


def state_path(robot_id: str, remote_workspace: str) -> Path:
    key = hashlib.sha256(
        f"{robot_id}\0{remote_workspace}".encode("utf-8", "surrogateescape")
    ).hexdigest()
    slug = re.sub(r"[^A-Za-z0-9._-]+", "_", f"{robot_id}_{remote_workspace}")[:60].strip("_")
    return state_dir() / f"{slug}-{key[:12]}.sqlite"


def _private(path: Path, *, is_dir: bool) -> None:
    """Make ``path`` (the state's directory or database) ours alone: 0700 or 0600, as
    ssh keeps ~/.ssh. The state keeps small text files' content, which another user of
    the laptop must not read; one that is not ours, or not what it should be (a link
    put there), is refused."""
    import stat

    st = os.lstat(path)
    kind_ok = stat.S_ISDIR(st.st_mode) if is_dir else stat.S_ISREG(st.st_mode)
    if not kind_ok or st.st_uid != os.getuid():
        raise StateError(
            f"the state's {'directory' if is_dir else 'database'} {path} is not "
            f"{'a directory' if is_dir else 'a file'} of yours; refusing to use it",
            hint="remove it, or set XDG_STATE_HOME to a directory of your own",
        )
    if st.st_mode & 0o077:
        os.chmod(path, 0o700 if is_dir else 0o600)


def _create_private(path: Path) -> None:
    """The database file, made (or kept) 0600 before SQLite opens it: its -wal and -shm
    files take its mode. The content of small text files is kept in it (dictionary
    writes)."""
    os.close(os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600))
    _private(path, is_dir=False)


class State:
    """One target's state. A damaged database is set aside (``<name>.damaged-<time>``)
    and an empty one takes its place: the next push then lists the robot, adopts what
    it holds already, and rebuilds the rows. ``note`` says so, in one line."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.note = ""
        try:
            path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
            _private(path.parent, is_dir=True)
            _create_private(path)
        except OSError as exc:
            raise StateError(f"cannot make the state {path}: {exc.strerror or exc}") from None
        try:
            self.db = self._open()
        except sqlite3.OperationalError as exc:  # not damage: permissions, a full disk
            raise StateError(f"cannot open the state {path}: {exc}") from None
        except sqlite3.DatabaseError as exc:
            aside = self._set_aside()
            try:
                _create_private(path)
            except OSError as exc2:
                raise StateError(f"cannot make the state {path}: {exc2.strerror}") from None
            self.note = (
                f"the state {path.name} was damaged ({exc}); set aside as {aside.name}, "
                "rebuilt from the robot's listing"
            )
            self.db = self._open()
        # the rows as last read or committed by this connection, and PRAGMA data_version
        # then (see entries())
        self._rows: dict[str, Synced] | None = None
        self._signed: set[str] | None = None
        self._rows_version = -1

    def _open(self) -> sqlite3.Connection:
        db = sqlite3.connect(str(self.path), isolation_level=None)
        try:
            db.execute("PRAGMA journal_mode=WAL")
            # FULL: a commit is on disk when it returns, so the state never says the robot
            # holds less than it does after a power cut (once per push: a few ms)
            db.execute("PRAGMA synchronous=FULL")
            db.executescript(SCHEMA)
            # read every page of the tables: damage shows now, not in the middle of a push
            db.execute(
                "SELECT count(*), sum(length(path) + length(hash) + ifnull(length(sig), 0)) "
                "FROM entries"
            ).fetchone()
            db.execute("SELECT count(*) FROM meta").fetchone()
        except BaseException:
            db.close()
            raise
        return db

    def _set_aside(self) -> Path:
        """Move the damaged database (and its log) out of the way; the new name."""
        aside = self.path.with_name(f"{self.path.name}.damaged-{time.strftime('%Y%m%d-%H%M%S')}")
        for suffix in ("", "-wal", "-shm"):
            try:
                os.rename(f"{self.path}{suffix}", f"{aside}{suffix}")
            except FileNotFoundError:
                pass
            except OSError as exc:
                raise StateError(
                    f"the state {self.path} is damaged and cannot be set aside: "
                    f"{exc.strerror or exc}"
                ) from None
        return aside

    def close(self) -> None:
        self.db.close()

    # meta
    def get(self, key: str, default: str = "") -> str:
        row = self.db.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone()
        return row[0] if row else default

    @property
    def epoch(self) -> str:
        return self.get("epoch")

    @property
    def gen(self) -> int:
        return int(self.get("gen", "-1"))

    def _version(self) -> int:
        """SQLite's ``PRAGMA data_version``: it moves whenever ANOTHER connection (another
        process's push, pull, reset) commits to the database, never for this one's."""
        return int(self.db.execute("PRAGMA data_version").fetchone()[0])

    def _still_kept(self) -> bool:
        """Whether what this connection keeps of the rows is still what the table holds:
        no other connection committed since it was read; else it goes."""
        if self._rows is None and self._signed is None:
            return False
        if self._version() == self._rows_version:
            return True
        self._rows = self._signed = None
        return False

    def entries(self) -> dict[str, Synced]:
        """Every row (a new dict: the caller's to change).

        A process that pushes again and again (the resident) reads them once: this
        connection keeps the rows it read and applies its own commits to them, and
        reads them again when ``PRAGMA data_version`` says another connection committed
        since (the version is taken before the read: a commit between the two makes the
        next call read again). So it answers what a read of the table would
        (tests/test_state_kept_rows.py). The bench's 2,547 rows: ~10 ms read, ~0.3 ms
        kept (and :meth:`signed_paths` ~4 ms -> ~0.1 ms)."""
        if self._still_kept() and self._rows is not None:
            return dict(self._rows)
        version = self._version()
        out = {}
        for row in self.db.execute(
            "SELECT path, kind, mode, hash, target, size, mtime_ns, ctime_ns, ino FROM entries"
        ):
            out[_decode(row[0])] = Synced(*row[1:])
        if self._rows_version != version:
            self._signed = None
        self._rows, self._rows_version = dict(out), version
        return out

    def has_entries(self) -> bool:
        return self.db.execute("SELECT 1 FROM entries LIMIT 1").fetchone() is not None

    def signature(self, path: str) -> bytes | None:
        row = self.db.execute("SELECT sig FROM entries WHERE path=?", (_encode(path),)).fetchone()
        return bytes(row[0]) if row and row[0] is not None else None

    def signed_paths(self) -> set[str]:
        """Paths whose stored entry has a delta signature (kept as :meth:`entries`' rows)."""
        if self._still_kept() and self._signed is not None:
            return set(self._signed)
        version = self._version()
        signed = {
            _decode(r[0]) for r in self.db.execute("SELECT path FROM entries WHERE sig IS NOT NULL")
        }
        if self._rows_version != version:
            self._rows = None
        self._signed, self._rows_version = set(signed), version
        return signed

    def commit(
        self,
        *,
        upserts: Iterable[tuple[str, Synced, bytes | None]] = (),
        deletes: Iterable[str] = (),
        meta: dict[str, str] | None = None,
        replace_all: bool = False,
    ) -> None:
        """Apply one batch of changes atomically. A ``None`` signature keeps the stored one
        only when the content hash is unchanged.

        What :meth:`entries` and :meth:`signed_paths` keep takes the same changes once
        the commit is done, if no other connection committed before it (else, and on
        any failure, it goes: read again next time)."""
        rows_kept, signed = (self._rows, self._signed) if self._still_kept() else (None, None)
        self._rows = self._signed = None  # until committed
        if rows_kept is None:
            signed = None  # its changes depend on the rows' hashes
        changed: list[tuple[str, Synced, bytes | None]] | None = (
            [] if rows_kept is not None else None
        )
        deletes = list(deletes)
        with self._transaction() as cur:
            if replace_all:
                cur.execute("DELETE FROM entries")
            # rows are made as SQLite takes them: a first push of 100,000 paths
            # would otherwise hold them all, twice, next to everything else
            rows = (
                (
                    _encode(path),
                    s.kind,
                    s.mode,
                    s.hash,
                    s.target,
                    s.size,
                    s.mtime_ns,
                    s.ctime_ns,
                    s.ino,
                    sig,
                )
                for path, s, sig in _noted(upserts, changed)
            )
            cur.executemany(_UPSERT, rows)
            cur.executemany("DELETE FROM entries WHERE path=?", [(_encode(p),) for p in deletes])
            for name, value in (meta or {}).items():
                cur.execute("INSERT OR REPLACE INTO meta VALUES (?,?)", (name, value))
        if rows_kept is None or changed is None:
            return
        if replace_all:
            rows_kept.clear()
            if signed is not None:
                signed.clear()
        for path, s, sig in changed:  # as _UPSERT does it
            if signed is not None:
                old = rows_kept.get(path)
                if sig is not None:
                    signed.add(path)
                elif old is None or old.hash != s.hash:
                    signed.discard(path)
            rows_kept[path] = s if type(s) is Synced else Synced(*s)
        for path in deletes:
            rows_kept.pop(path, None)
            if signed is not None:
                signed.discard(path)
        self._rows, self._signed = rows_kept, signed

    @contextlib.contextmanager
    def _transaction(self) -> Iterator[sqlite3.Cursor]:
        """One write transaction: committed at the end, rolled back on any exception.
        SQLite's own failure (the laptop's disk full, the database busy) is a StateError:
        the state is left as it was, behind the robot (a traceback, and the watch agent's
        sync thread gone, before)."""
        cur = self.db.cursor()
        try:
            cur.execute("BEGIN IMMEDIATE")
            try:
                yield cur
                cur.execute("COMMIT")
            except BaseException:
                if self.db.in_transaction:  # a failed COMMIT may have rolled back already
                    with contextlib.suppress(sqlite3.Error):
                        cur.execute("ROLLBACK")
                raise
        except sqlite3.Error as exc:
            raise StateError(f"cannot write the state {self.path}: {exc}") from None

    def reset(self) -> None:
        self.commit(replace_all=True, meta={"epoch": "", "gen": "-1"})


def _noted(
    upserts: Iterable[tuple[str, Synced, bytes | None]],
    into: list[tuple[str, Synced, bytes | None]] | None,
) -> Iterator[tuple[str, Synced, bytes | None]]:
    for each in upserts:
        if into is not None:
            into.append(each)
        yield each


# A NULL signature keeps the stored one only while the content hash is the same.
_UPSERT = """
INSERT INTO entries (path, kind, mode, hash, target, size, mtime_ns, ctime_ns, ino, sig)
VALUES (?,?,?,?,?,?,?,?,?,?)
ON CONFLICT (path) DO UPDATE SET
    kind=excluded.kind, mode=excluded.mode, target=excluded.target, size=excluded.size,
    mtime_ns=excluded.mtime_ns, ctime_ns=excluded.ctime_ns, ino=excluded.ino,
    sig=CASE WHEN excluded.sig IS NOT NULL THEN excluded.sig
             WHEN entries.hash = excluded.hash THEN entries.sig END,
    hash=excluded.hash
"""


def _encode(path: str) -> bytes:
    # raw bytes: names that are not UTF-8 (surrogate escapes) round-trip exactly
    return path.encode("utf-8", "surrogateescape")


def _decode(raw: bytes) -> str:
    return bytes(raw).decode("utf-8", "surrogateescape")


def open_state(target: Target) -> State:
    """The state of ``target``'s robot and remote workspace."""
    from fetchsync.link.session import robot_id

    return State(state_path(robot_id(target), target.remote_workspace))
