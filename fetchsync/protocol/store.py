"""The filesystem endpoint: one synced tree on disk, changed only through operations.

A :class:`Store` owns ``<workspace>/src`` (the synced root) and
``<workspace>/.fetchsync`` (its metadata). It runs on the robot behind the
wire server, and on the laptop for ``pull``: one implementation, both ends.

Rules it keeps:

- One trust boundary: every operation reaches its path through directory
  descriptors, walked one component at a time from ``src``'s descriptor with
  ``O_NOFOLLOW | O_DIRECTORY`` (:class:`paths.Root`), and acts through the
  ``dir_fd`` forms of the system calls; ``.fetchsync`` and its ``trash``,
  ``conflicts`` and ``tmp`` the same. A directory swapped for a symlink at any
  moment fails the operation; it never redirects a write out of the tree. The
  descriptors of ``src`` and ``.fetchsync`` are opened afresh for each request,
  and nothing one operation found is trusted by the next. A symlinked ``src``
  or ``.fetchsync`` is refused.
- Writes go to a temporary beside the target; every temporary of a batch is
  made durable with one ``syncfs`` before any is renamed into place, and the
  renames are made durable with another: a reader never sees a torn file, and
  what was reported written survives a power cut.
- Every operation (write, symlink, mkdir, chmod, delete) compares what stands
  at its path with its expectation (what the sender last synced), right before
  it acts. A mismatch means someone edited it here: that version is kept in
  ``.fetchsync/conflicts/`` (policy ``preserve``; the result says where) or the
  operation is refused (policy ``refuse``). A version replaced by a write is
  kept there by a hard link made only once the new content is durable, and the
  replacement is one rename (renameat2: an exchange, the old version deleted only
  if it is still the one checked): a failure at any step (a full disk), or an
  edit made between the check and the rename, leaves the robot's version kept. Deleted paths go to a bounded ``.fetchsync/trash/``.
  Nothing is lost.
- The index (``.fetchsync/index``, a :mod:`marshal` snapshot, plus
  ``index.log``, the changes made since, appended after every request and
  folded into a new snapshot when it grows) records what was last synced at each
  path, a stat cache for content hashes, an epoch and a generation, so the
  sender can learn in one round trip what changed here since its last sync.
- Opened ``readonly``, a store creates nothing, takes no lock, writes no index
  and refuses every change.
- Memory stays bounded whatever the file size: content is hashed, patched,
  copied and signed in pieces; runs of zeros are left as holes when written.
"""

import errno
import fcntl
import io
import itertools
import marshal
import os
import stat as stat_mod
import struct
import time
import zlib
from typing import Any, BinaryIO, Dict, List, Optional, Set, Tuple, cast

from fetchsync.protocol import hashing, paths, stl, wire
from fetchsync.protocol import messages as M
from fetchsync.protocol.errors import DeltaError, PathError, ProtocolError
from fetchsync.protocol.paths import O_FILE, lstat_at, mkdir_open, open_dir
from fetchsync.protocol.tree import DIR, FILE, LINK, Entry, entry_from_stat, scan_fd, scandir_fd

META = ".fetchsync"
TEMP_MARK = ".fetchsync-tmp-"
TRASH_KEEP_BATCHES = 50
TRASH_KEEP_BYTES = 512 * 1024 * 1024
# seconds between two trash batches (by the time in their names, to the second; any
# endpoint's) that make them one deletion, whose batches are all kept until it ends
TRASH_CHAIN = 10.0
INDEX_VERSION = 3
INDEX = "index"
JOURNAL = "index.log"
JOURNAL_MIN = 1 << 20  # the journal is folded into a new snapshot past this and half the snapshot
_LEN = struct.Struct(">I")
OLD_INDEXES = ("index.json",)  # earlier formats: dropped (the first push lists in full)
_INDEX_TYPES = (
    ("epoch", str),
    ("gen", int),
    ("synced", dict),
    ("cache", dict),
    ("trash", list),
    ("serial", str),
)
PIECE = 1 << 20  # content is read, hashed, patched and written in pieces of this size
HOLE = 64 * 1024  # a piece of zeros this long (aligned in the file) is left a hole when written
_ZEROS = bytes(HOLE)
MAX_READ = 32 * 1024 * 1024  # the most one read answers: larger files are read in pieces
MAX_SIGNED = 4 << 30  # the largest file signed: its signature (~40 MiB) fits an answer
MAX_READ_SIG = 4 * 1024 * 1024  # the largest signature a delta is made against (400,000 chunks)
BATCH_MARK = "batch-in-progress"  # while it exists, temporaries may lie in the tree
TMP = "tmp"
RACY_NS = 2_000_000_000  # a file modified within this many ns is hashed again (see _racy)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
O_NEW = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | _CLOEXEC
NAME_MAX = 255
KEPT = ("conflicts", "trash")  # the places a robot keeps replaced and deleted files
MAX_KEPT = 100000  # the most kept files one listing names
# a batch with at most this many new contents (a save) fsyncs each temporary instead of
# one syncfs before the renames: a journaled ext4 (bench robot's loop disk) took 1.6 vs
# 2.5 ms (p50; p90 6.0 vs 9.2) for one 10 KB temporary, on a wifi save's critical path;
# and a syncfs waits for whatever else the robot writes (a rosbag being recorded)
FSYNC_EACH = 1


class StoreError(ProtocolError):
    """The store cannot be opened or used at all (not a per-file failure)."""


def is_temp(name: str) -> bool:
    return TEMP_MARK in name and name.startswith(".")


_TEMP_IDS = itertools.count()
_TEMP_SALT = os.urandom(6).hex()


def _temp_name(final_name: str) -> str:
    """A temporary's name beside ``final_name``: unique per process (a random salt, then a
    counter), and within NAME_MAX bytes however many bytes the name's characters take."""
    tail = "%s%s%06x" % (TEMP_MARK, _TEMP_SALT, next(_TEMP_IDS) & 0xFFFFFF)
    room = min(100, NAME_MAX - 1 - len(tail))
    if len(final_name) <= room:
        try:
            final_name.encode("ascii")  # one byte a character: it fits whole
        except UnicodeError:
            pass
        else:
            return "." + final_name + tail
    raw = os.fsencode(final_name)[:room]
    head = os.fsdecode(raw.decode("utf-8", "ignore").encode("utf-8")) if raw else ""
    name = "." + head + tail
    while len(os.fsencode(name)) > NAME_MAX:  # pragma: no cover - surrogate escapes only
        head = head[:-1]
        name = "." + head + tail
    return name


_libc = None
_UMASK = -1


def _umask() -> int:
    """This process's umask, read without changing it (os.umask sets it, for a moment,
    for every thread); 0o7777 where it cannot be read: every mode is then set by chmod."""
    global _UMASK
    if _UMASK < 0:
        _UMASK = 0o7777
        try:
            with open("/proc/self/status", "rb") as fh:
                for line in fh:
                    if line.startswith(b"Umask:"):
                        _UMASK = int(line.split()[1], 8)
                        break
        except (OSError, ValueError, IndexError):
            pass
    return _UMASK


def unpack_zpart(blob: bytes, zpart: "Any") -> "Tuple[bytearray, Any]":
    """A sync request's blob as (its compressed part inflated, the raw rest, not copied)."""
    if not (
        isinstance(zpart, list)
        and len(zpart) == 2
        and all(isinstance(x, int) for x in zpart)
        and 0 <= zpart[0] <= len(blob)
        and 0 <= zpart[1] <= wire.MAX_BODY
    ):
        raise ProtocolError("bad compressed-part reference")
    view = memoryview(blob)
    return wire.inflate_exact(view[: zpart[0]], zpart[1]), view[zpart[0] :]


def syncfs(fd: int) -> None:
    """Flush the filesystem holding ``fd`` (one call per batch, not one per file)."""
    global _libc
    try:
        if _libc is None:
            import ctypes  # here: it costs every endpoint start ~4 ms to import

            _libc = ctypes.CDLL(None, use_errno=True)
        if _libc.syncfs(fd) == 0:
            return
    except (OSError, AttributeError):
        pass
    os.sync()


def rmtree_at(name: str, dir_fd: int) -> None:
    """Remove ``name`` in ``dir_fd`` and everything below it, never through a symlink."""
    try:
        os.unlink(name, dir_fd=dir_fd)
        return
    except FileNotFoundError:
        return
    except OSError as exc:
        if exc.errno not in (errno.EISDIR, errno.EPERM):
            raise
    fd = open_dir(name, dir_fd)
    try:
        with scandir_fd(fd) as it:
            items = [(de.name, de.is_dir(follow_symlinks=False)) for de in it]
        for sub, is_dir in items:
            if is_dir:
                rmtree_at(sub, fd)
            else:
                try:
                    os.unlink(sub, dir_fd=fd)
                except FileNotFoundError:
                    pass
    finally:
        os.close(fd)
    os.rmdir(name, dir_fd=dir_fd)


def _size_at(name: str, dir_fd: int) -> int:
    """Bytes of the file, or of every file below the directory, ``name`` in ``dir_fd``."""
    st = lstat_at(name, dir_fd)
    if st is None or not stat_mod.S_ISDIR(st.st_mode):
        return st.st_size if st is not None else 0
    try:
        fd = open_dir(name, dir_fd)
    except OSError:
        return 0
    try:
        return sum(e.size for e in scan_fd(fd).entries.values())
    finally:
        os.close(fd)


def _identity(st: "os.stat_result") -> "Tuple[int, ...]":
    """What tells one version of an index file from another: the file (device, inode) and
    its size and times (the journal is appended to in place, the snapshot replaced)."""
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def _write_all(fd: int, data: "Any") -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


class _Out:
    """A new file's content, written in order to ``fd`` and hashed as it goes; aligned
    pieces of zeros are skipped (left holes), and :meth:`close` sets the final size."""

    def __init__(self, fd: int, algorithm: str, sparse: bool = True, hashed: bool = True) -> None:
        self.fd = fd
        # not hashed: content whose hash was checked as it lies in the request
        self.hasher = hashing.new(algorithm) if hashed else None
        self.size = 0
        self.sparse = sparse
        self.pending_hole = False

    def write(self, data: "Any") -> int:
        view = memoryview(data).cast("B") if not isinstance(data, memoryview) else data
        n = len(view)
        if self.hasher is not None:
            self.hasher.update(view)
        pos = 0
        while pos < n:
            # up to the next HOLE boundary of the file, so holes are aligned
            step = min(n - pos, HOLE - (self.size + pos) % HOLE)
            piece = view[pos : pos + step]
            # a memoryview equals the bytes it holds (mypy's strict equality cannot tell)
            if self.sparse and step == HOLE and piece == _ZEROS:  # type: ignore[comparison-overlap]
                os.lseek(self.fd, step, os.SEEK_CUR)
                self.pending_hole = True
            else:
                _write_all(self.fd, piece)
                self.pending_hole = False
            pos += step
        self.size += n
        return n

    def close(self) -> str:
        """The hex digest of everything written ("" if not hashed); the file's size set (a
        hole at its end)."""
        if self.pending_hole:
            os.ftruncate(self.fd, self.size)
        return self.hasher.digest().hex() if self.hasher is not None else ""


def _copy_fd(src: int, out: "_Out", length: int = -1) -> None:
    """Copy ``length`` bytes (-1: to the end) from ``src``'s position to ``out``."""
    while length != 0:
        block = os.read(src, PIECE if length < 0 else min(PIECE, length))
        if not block:
            if length > 0:
                raise DeltaError("the source ended early")
            return
        out.write(block)
        if length > 0:
            length -= len(block)


class _Tee:
    """A file object that hashes what is read through it (for one pass over a file)."""

    def __init__(self, fh: "Any", algorithm: str) -> None:
        self.fh = fh
        self.hasher = hashing.new(algorithm)

    def read(self, n: int = -1) -> bytes:
        data = self.fh.read(n)  # type: bytes
        self.hasher.update(data)
        return data


def _own_records(fd: int, shown: str) -> None:
    """Refuse a ``.fetchsync`` (open as ``fd``; -1: none) that another user made: in a
    workspace others can write (a group's), one put in place of ours would have its
    index trusted (a forged stat-cache row lists the content its maker chose) and our
    trash and conflicts kept there (tests/test_robot_other_user.py). Its owner only, as
    git's safe.directory: ours is made 0700, and a file system without permissions
    (FAT, NTFS) gives every file the mode 0777 and the owner who mounted it."""
    if fd < 0:
        return
    uid = os.fstat(fd).st_uid
    if uid != os.getuid():
        os.close(fd)
        raise StoreError(
            "%s belongs to another user (uid %d): fetchsync keeps this workspace's "
            "records there and will not trust them; remove it (the next push rebuilds "
            "it) or use another workspace" % (shown, uid)
        )


class Store:
    def __init__(
        self,
        workspace: str,
        *,
        algorithm: str,
        rules: "Any" = None,
        create: bool = True,
        readonly: bool = False,
    ) -> None:
        self.workspace = workspace
        self.root = os.path.join(workspace, "src")
        self.meta = os.path.join(workspace, META)
        self.algorithm = algorithm
        self.rules = rules
        self.readonly = readonly
        self.create = create and not readonly
        self.src = None  # type: Optional[paths.Root]  # while open: see _open
        self._meta_fd = -1  # -1 while closed, or read-only without a .fetchsync
        self._lock_fd = -1
        # upload parts this session started: a client that goes away between
        # the batches of a large file leaves them, with no batch marker to say so
        self._uploads = set()  # type: Set[str]
        self._stamp = None  # type: Optional[str]  # the batch under way's (stamp)
        self._held = []  # type: List[int]  # the index files loaded (see _hold)
        self.kept_tree = None  # type: Any  # a KeptTree (see keep_listing)
        # the laptop's pull: a file replaced goes to the trash, as a deleted one (linked
        # there only once its replacement is whole: a full disk leaves it in place)
        self.keep_replaced = False
        self._open()
        self._load_index()

    # ------------------------------------------------------------------ descriptors
    def _unusable(self, exc: "OSError", where: str) -> "StoreError":
        if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            return StoreError(
                "the remote workspace is not writable: cannot create %s: %s; "
                "check the permissions of %s on the robot, or pass another "
                "--remote-workspace" % (where, exc.strerror, os.path.dirname(where))
            )
        return StoreError("cannot use %s: %s" % (where, exc.strerror or exc))

    def _open_top(self, ws_fd: int, name: str, shown: str, create: bool, mode: int) -> int:
        """``src`` or ``.fetchsync`` of the workspace, never through a symlink; -1 if absent
        and not to be made."""
        try:
            return open_dir(name, ws_fd)
        except FileNotFoundError:
            if not create:
                return -1
        except OSError as exc:
            if exc.errno in paths.NOT_A_DIR:
                raise StoreError(
                    "%s is a symlink or not a directory: fetchsync does not write "
                    "through it; make it a directory" % shown
                ) from None
            raise self._unusable(exc, shown) from None
        try:
            os.mkdir(name, mode, dir_fd=ws_fd)
        except FileExistsError:
            pass
        except OSError as exc:
            raise self._unusable(exc, shown) from None
        return self._open_top(ws_fd, name, shown, False, mode)

    def _open(self) -> None:
        """Open the descriptors of ``src`` and ``.fetchsync`` (afresh for each request:
        a workspace deleted or replaced meanwhile is the new one)."""
        if self.src is not None:
            return
        try:
            if self.create:
                os.makedirs(self.workspace, exist_ok=True)
            ws_fd = os.open(self.workspace, os.O_RDONLY | os.O_DIRECTORY | _CLOEXEC)
        except FileNotFoundError:
            raise StoreError("%s does not exist" % self.workspace) from None
        except OSError as exc:
            raise self._unusable(exc, self.workspace) from None
        try:
            src_fd = self._open_top(ws_fd, "src", self.root, self.create, 0o777)
            if src_fd < 0:
                raise StoreError("%s does not exist" % self.root)
            try:
                meta_fd = self._open_top(ws_fd, META, self.meta, not self.readonly, 0o700)
                _own_records(meta_fd, self.meta)
            except BaseException:
                os.close(src_fd)
                raise
        finally:
            os.close(ws_fd)
        self.src = paths.Root(src_fd, self.root)
        self._meta_fd = meta_fd

    def close(self) -> None:
        """The end of this store: its descriptors, lock, held index files and kept
        listing go."""
        self._release()
        self._hold([])
        if self.kept_tree is not None:
            self.kept_tree.close()
            self.kept_tree = None

    def __del__(self) -> None:
        # a store dropped without close() (the laptop's pull only unlocks it) gives back
        # the index files it holds and its kept listing's inotify descriptor
        try:
            self._hold([])
            if self.kept_tree is not None:
                self.kept_tree.close()
        except Exception:  # a half-made store, or the interpreter's exit
            pass

    def _release(self) -> None:
        """The request's descriptors and lock go (the held index files stay)."""
        if self._lock_fd >= 0:
            os.close(self._lock_fd)
            self._lock_fd = -1
        if self.src is not None:
            os.close(self.src.fd)
            self.src = None
        if self._meta_fd >= 0:
            os.close(self._meta_fd)
            self._meta_fd = -1

    def _root(self) -> "paths.Root":
        self._open()
        assert self.src is not None
        return self.src

    def _meta(self) -> int:
        self._open()
        if self._meta_fd < 0:
            raise StoreError("%s does not exist" % self.meta)
        return self._meta_fd

    def _meta_dir(self, name: str) -> int:
        """A new descriptor of ``.fetchsync/<name>`` (made if missing), not through a symlink."""
        try:
            return mkdir_open(name, self._meta(), 0o700)
        except OSError as exc:
            if exc.errno in paths.NOT_A_DIR:  # this operation's failure
                raise OSError(
                    exc.errno,
                    "%s is a symlink or not a directory: fetchsync does not "
                    "write through it" % os.path.join(META, name),
                ) from None
            raise

    def _read_meta(self, name: str) -> "Optional[bytes]":
        """A file of ``.fetchsync`` (None if absent; never through a symlink)."""
        if self._meta_fd < 0:
            return None
        try:
            fd = os.open(name, O_FILE, dir_fd=self._meta_fd)
        except FileNotFoundError:
            return None
        try:
            if not stat_mod.S_ISREG(os.fstat(fd).st_mode):
                raise OSError(errno.EINVAL, "not a regular file")
            parts = []  # type: List[bytes]
            while True:
                block = os.read(fd, PIECE)
                if not block:
                    return b"".join(parts)
                parts.append(block)
        finally:
            os.close(fd)

    def _write_meta(self, name: str, data: bytes) -> None:
        """Replace ``.fetchsync/<name>`` with ``data`` at once."""
        meta = self._meta()
        tmp = name + ".tmp"
        try:
            os.unlink(tmp, dir_fd=meta)
        except FileNotFoundError:
            pass
        fd = os.open(tmp, O_NEW, 0o600, dir_fd=meta)
        try:
            _write_all(fd, data)
        finally:
            os.close(fd)
        os.replace(tmp, name, src_dir_fd=meta, dst_dir_fd=meta)

    # ------------------------------------------------------------------ index
    def _index_stamp(self) -> "Any":
        """The identity of the index files as they stand now (by name)."""
        stamp = []  # type: List[Optional[Tuple[int, ...]]]
        for name in (INDEX, JOURNAL):
            try:
                st = os.stat(name, dir_fd=self._meta_fd, follow_symlinks=False)
            except (OSError, ValueError):  # ValueError: no .fetchsync (read-only)
                stamp.append(None)
            else:
                stamp.append(_identity(st))
        return tuple(stamp)

    def _held_stamp(self) -> "Any":
        """The identity of the index files this store loaded or saved last: taken from the
        descriptors it holds on them (see _hold), before they were read, so a change
        made after it shows as a different stamp."""
        return tuple(_identity(os.fstat(fd)) if fd >= 0 else None for fd in self._held)

    def _hold(self, names: "List[str]") -> None:
        """Hold descriptors of the index files ``names`` (in place of those held before):
        while held, their inodes cannot be reused by a later file, so a stamp equal to
        the held one is the same file, not a new one that got its inode number
        (the check of :meth:`lock`, which lets a kept store skip reloading)."""
        for fd in self._held:
            if fd >= 0:
                os.close(fd)
        self._held = []
        for name in names:
            fd = -1
            if self._meta_fd >= 0:
                try:
                    fd = os.open(name, O_FILE, dir_fd=self._meta_fd)
                except OSError:
                    fd = -1
            self._held.append(fd)

    def _stamp_loaded(self) -> None:
        """Hold the index files as they stand and remember their identity (before reading
        them, or right after writing them under the lock)."""
        self._hold([INDEX, JOURNAL])
        self._loaded_stamp = self._held_stamp()

    def reopen(self) -> bool:
        """Ready this store for a new ``open`` of its workspace in the same session, as
        a fresh Store would be (the index reloaded by :meth:`lock` if another writer
        saved meanwhile); False if it cannot be (a change of its own left unsaved)."""
        if self._dirty:
            return False
        return True

    def _load_index(self) -> None:
        self._stamp_loaded()
        self._touched_synced = set()  # type: Set[str]  # paths changed since the last save
        self._touched_cache = set()  # type: Set[str]
        # what drift() looks at again next time (None: every entry; see drift)
        self._drift_again = None  # type: Optional[Set[str]]
        self._index_moved = set()  # type: Set[str]  # rows changed since the last drift
        data = None  # type: Any
        try:
            raw = self._read_meta(INDEX)
            if raw is not None:
                data = marshal.loads(raw)
            elif not self.readonly:
                for old in OLD_INDEXES:
                    try:
                        os.unlink(old, dir_fd=self._meta_fd)
                    except OSError:
                        pass
        except (OSError, ValueError, EOFError, TypeError):
            data = None  # a damaged index only costs a full listing
        if (
            not isinstance(data, dict)
            or data.get("v") != INDEX_VERSION
            or data.get("algorithm") != self.algorithm
            or not all(isinstance(data.get(k), t) for k, t in _INDEX_TYPES)
        ):
            data = {
                "v": INDEX_VERSION,
                "epoch": os.urandom(16).hex(),
                "gen": 0,
                "serial": "",
                "algorithm": self.algorithm,
                "synced": {},
                "cache": {},
                "trash": [],
            }
            self._dirty = True
        else:
            self._dirty = False
        self.epoch = data["epoch"]  # type: str
        self.gen = int(data["gen"])
        self.synced = data["synced"]  # type: Dict[str, List[Any]]  # path -> [kind, mode, hash|target]
        self.cache = data["cache"]  # type: Dict[str, List[Any]]  # path -> [size, mtime, ctime, ino, hash]
        self.trash_log = data.get("trash", [])  # type: List[List[Any]]
        self._serial = data["serial"]  # type: str  # the snapshot the journal's records apply to
        index_stat = self._loaded_stamp[0]
        self._snapshot_size = index_stat[1] if index_stat else 0
        # -1: no snapshot of ours to append to (new, damaged): the next save writes one
        self._journal_size = self._replay_journal() if self._serial else -1

    def _replay_journal(self) -> int:
        """Apply the journal's records written since our snapshot; the length of its valid part
        (-1 if the file holds anything else: the next save writes a new snapshot)."""
        try:
            buf = self._read_meta(JOURNAL)
        except OSError:
            return -1
        if buf is None:
            return 0
        pos = 0
        while pos + _LEN.size <= len(buf):
            (n,) = _LEN.unpack_from(buf, pos)
            end = pos + _LEN.size + n
            if end > len(buf):
                break  # torn by a crash mid-append
            rec = self._journal_record(buf[pos + _LEN.size : end])
            if rec is None:
                break
            for table, change in ((self.synced, rec["s"]), (self.cache, rec["c"])):
                for path, value in change.items():
                    if value is None:
                        table.pop(path, None)
                    else:
                        table[path] = value
            self.epoch, self.gen, self.trash_log = rec["epoch"], rec["gen"], rec["trash"]
            pos = end
        return pos if pos == len(buf) else -1

    def _journal_record(self, raw: bytes) -> "Optional[Dict[str, Any]]":
        """One journal record of this snapshot's series, checked; None if it is not one."""
        try:
            rec = marshal.loads(raw)
        except (ValueError, EOFError, TypeError):
            return None
        if not (isinstance(rec, dict) and rec.get("serial") == self._serial):
            return None
        types = (("epoch", str), ("gen", int), ("trash", list), ("s", dict), ("c", dict))
        if not all(isinstance(rec.get(key), kind) for key, kind in types):
            return None
        return rec

    def discard_uploads(self) -> None:
        """Remove the upload parts this session started and never used (its client left)."""
        if not self._uploads:
            return
        try:
            tmp = self._meta_dir(TMP)
        except (OSError, ProtocolError):
            return
        try:
            for part in list(self._uploads):
                try:
                    os.unlink(part, dir_fd=tmp)
                except OSError:
                    pass
        finally:
            os.close(tmp)
        self._uploads.clear()

    def save_index(self) -> None:
        """Record what changed since the last save: a journal record of the touched paths,
        or, once the journal outgrows half the snapshot, a new snapshot.

        Rewriting the whole index after every request cost a one-file save ~0.3 s
        of the robot's time on 100,000 files; a record costs what it holds.
        """
        if not self._dirty or self.readonly:
            return
        if self._journal_size < 0 or self._journal_size > max(
            JOURNAL_MIN, self._snapshot_size // 2
        ):
            self._write_snapshot()
        else:
            rec = marshal.dumps(
                {
                    "serial": self._serial,
                    "epoch": self.epoch,
                    "gen": self.gen,
                    "trash": self.trash_log,
                    "s": {p: self.synced.get(p) for p in self._touched_synced},
                    "c": {p: self.cache.get(p) for p in self._touched_cache},
                }
            )
            fd = os.open(
                JOURNAL,
                os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_NOFOLLOW | _CLOEXEC,
                0o600,
                dir_fd=self._meta(),
            )
            try:
                _write_all(fd, _LEN.pack(len(rec)) + rec)
            finally:
                os.close(fd)
            self._journal_size += _LEN.size + len(rec)
        self._touched_synced.clear()
        self._touched_cache.clear()
        self._dirty = False
        self._stamp_loaded()  # what we wrote, under our lock

    def _write_snapshot(self) -> None:
        self._serial = os.urandom(16).hex()
        blob = marshal.dumps(
            {
                "v": INDEX_VERSION,
                "epoch": self.epoch,
                "gen": self.gen,
                "algorithm": self.algorithm,
                "serial": self._serial,
                "synced": self.synced,
                "cache": self.cache,
                "trash": self.trash_log,
            }
        )
        self._write_meta(INDEX, blob)
        # the old journal's records name the old snapshot: a crash before this
        # line leaves them ignored, never applied to the new one
        self._write_meta(JOURNAL, b"")
        self._snapshot_size = len(blob)
        self._journal_size = 0

    def _set_cache(self, path: str, value: "Optional[List[Any]]") -> None:
        self._set_row(self.cache, self._touched_cache, path, value)

    def _set_synced(self, path: str, value: "Optional[List[Any]]") -> None:
        self._set_row(self.synced, self._touched_synced, path, value)

    def _set_row(
        self, table: "Dict[str, Any]", touched: "Set[str]", path: str, value: "Optional[List[Any]]"
    ) -> None:
        """Set or drop (None) ``path``'s row in one of the index's tables, for the journal."""
        if value is None:
            if table.pop(path, None) is None:
                return
        else:
            table[path] = value
        touched.add(path)
        self._index_moved.add(path)
        self._dirty = True

    def _clean_temps(self) -> None:
        """Remove the temporaries a writer that died mid-batch left in the tree."""
        root = self._root()
        stack = [os.dup(root.fd)]
        while stack:
            fd = stack.pop()
            try:
                with scandir_fd(fd) as it:
                    items = [(de.name, de.is_dir(follow_symlinks=False)) for de in it]
                for name, is_dir in items:
                    try:
                        if is_temp(name):
                            rmtree_at(name, fd)
                        elif is_dir:
                            stack.append(open_dir(name, fd))
                    except OSError:
                        pass
            finally:
                os.close(fd)
        try:
            rmtree_at(TMP, self._meta())
        except OSError:
            pass
        try:
            os.unlink(BATCH_MARK, dir_fd=self._meta())
        except FileNotFoundError:
            pass

    # ------------------------------------------------------------------ locking
    def lock(self, timeout: float = 30.0) -> None:
        """Open the store for one request: its descriptors afresh and, unless read-only,
        the writers' lock; the index is read again if another writer saved meanwhile."""
        self._open()
        if self.readonly:
            if self._index_stamp() != self._loaded_stamp:
                self._load_index()
            return
        if self._lock_fd >= 0:
            return
        fd = os.open(
            "lock", os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | _CLOEXEC, 0o600, dir_fd=self._meta()
        )
        deadline = time.monotonic() + timeout
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError as exc:
                if exc.errno not in (errno.EAGAIN, errno.EACCES):
                    os.close(fd)
                    raise
                if time.monotonic() > deadline:
                    os.close(fd)
                    raise StoreError(
                        "another fetchsync is writing to %s" % self.workspace
                    ) from None
                time.sleep(0.05)
        self._lock_fd = fd
        if lstat_at(BATCH_MARK, self._meta()) is not None:
            # left by a writer that died mid-batch (a live one would hold the
            # lock): its temporaries are garbage now, and only now
            self._clean_temps()
        if self._index_stamp() != self._loaded_stamp:
            self._load_index()  # someone else wrote since we loaded

    def unlock(self) -> None:
        """The end of a request: the lock and the descriptors go."""
        self._release()

    # ------------------------------------------------------------------ reading
    def _hash_fd(self, path: str, fd: int, st: "os.stat_result") -> str:
        """Content hash of the open regular file ``fd`` (``st``: its fstat), stat-cached."""
        cached = self.cache.get(path)
        if (
            cached is not None
            and cached[0] == st.st_size
            and cached[1] == st.st_mtime_ns
            and cached[2] == st.st_ctime_ns
            and cached[3] == st.st_ino
            and not self._racy(st.st_mtime_ns)
        ):
            known = cached[4]  # type: str
            return known
        os.lseek(fd, 0, os.SEEK_SET)
        digest = hashing.file_digest(self.algorithm, fd, PIECE).hex()
        if self._racy(max(st.st_mtime_ns, st.st_ctime_ns)):
            # read while a same-size rewrite in the same timestamp tick would keep every
            # stamp: not remembered (nor an older row), or trusted ever after once 2 s
            # old; hashed again next time (tests/test_store_racy_cache.py)
            self._set_cache(path, None)
        else:
            self._set_cache(path, [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, digest])
        return digest

    def _cached(self, path: str, entry: "Entry") -> "Optional[str]":
        c = self.cache.get(path)
        if (
            c is not None
            and c[0] == entry.size
            and c[1] == entry.mtime_ns
            and c[2] == entry.ctime_ns
            and c[3] == entry.ino
            and not self._racy(entry.mtime_ns)
        ):
            known = c[4]  # type: str
            return known
        return None

    def _hash_at(self, path: str, dir_fd: int, name: str) -> str:
        fd = os.open(name, O_FILE, dir_fd=dir_fd)
        try:
            st = os.fstat(fd)
            if not stat_mod.S_ISREG(st.st_mode):
                raise PathError("%r is not a regular file" % path)
            return self._hash_fd(path, fd, st)
        finally:
            os.close(fd)

    def hash_file(self, path: str, entry: "Entry") -> str:
        """Content hash of the file at ``path`` (stat-cached)."""
        digest = self._cached(path, entry)
        if digest is not None:
            return digest
        with self._root().parent(path) as (dir_fd, name):
            return self._hash_at(path, dir_fd, name)

    @staticmethod
    def _racy(mtime_ns: int) -> bool:
        # a file modified within the last 2 s may change again without its
        # mtime moving on coarse-timestamp filesystems: do not trust the cache
        return int(time.time() * 1e9) - mtime_ns < RACY_NS

    def listed(self, path: str, entry: "Optional[Entry]") -> "Optional[M.Listed]":
        if entry is None:
            return None
        if entry.kind == FILE:
            return M.Listed(path, FILE, entry.mode, entry.size, hash=self.hash_file(path, entry))
        if entry.kind == LINK:
            return M.Listed(path, LINK, target=entry.target)
        return M.Listed(path, DIR, entry.mode)

    def _at(self, path: str, dir_fd: int, name: str) -> "Optional[M.Listed]":
        """What stands at ``path`` (``name`` in ``dir_fd``), with its content hash."""
        st = lstat_at(name, dir_fd)
        if st is None:
            return None
        if stat_mod.S_ISLNK(st.st_mode):
            try:
                target = os.fsdecode(os.readlink(name, dir_fd=dir_fd))
            except OSError:
                return None
            return M.Listed(path, LINK, target=target)
        entry = entry_from_stat(st)
        if entry is None:
            raise PathError("%r is not a regular file, directory or symlink" % path)
        if entry.kind == FILE:
            digest = self._cached(path, entry)
            if digest is None:
                try:
                    digest = self._hash_at(path, dir_fd, name)
                except FileNotFoundError:
                    return None
            return M.Listed(path, FILE, entry.mode, entry.size, hash=digest)
        return M.Listed(path, DIR, entry.mode)

    def written(self, path: str, digest: str) -> "Optional[M.Listed]":
        """What stands at ``path`` right after we wrote content with hash ``digest`` there.

        The content was verified against its hash before the rename, so it is
        not read again now; the stat cache learns the hash only where no later write
        could keep every stamp (see _written_at).
        """
        with self._root().parent(path) as (dir_fd, name):
            return self._written_at(path, dir_fd, name, digest)

    def _written_at(self, path: str, dir_fd: int, name: str, digest: str) -> "Optional[M.Listed]":
        st = lstat_at(name, dir_fd)
        if st is None or not stat_mod.S_ISREG(st.st_mode) or not digest:
            return self._at(path, dir_fd, name)
        if self._racy(max(st.st_mtime_ns, st.st_ctime_ns)):
            # just written, as nearly always: another program's same-size rewrite in the
            # same timestamp tick would keep every stamp, and the cache would answer our
            # content from 2 s on (tests/test_store_racy_cache.py): the next look reads
            # it once (after an initial push every file it wrote: the bench's 2,000 files /
            # 40 MiB, a listing with them uncached 130-175 ms of CPU against 27-34, once)
            self._set_cache(path, None)
        else:
            self._set_cache(path, [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, digest])
        return M.Listed(path, FILE, stat_mod.S_IMODE(st.st_mode), st.st_size, hash=digest)

    def current(self, path: str) -> "Optional[M.Listed]":
        with self._root().parent(path) as (dir_fd, name):
            return self._at(path, dir_fd, name)

    def _scan(self) -> "Any":
        if self.kept_tree is not None:
            return self.kept_tree.scan(self._root().fd)
        return scan_fd(self._root().fd, self.rules, is_temp=is_temp)

    def keep_listing(self) -> None:
        """Keep the walk of the tree between requests (fetchsync.protocol.kept): for an
        endpoint that lives across pushes (its Store re-opened)."""
        if self.kept_tree is None:
            from fetchsync.protocol.kept import KeptTree  # ctypes: not at every start

            self.kept_tree = KeptTree(self.rules, is_temp)

    def listing(self) -> "Tuple[List[M.Listed], List[Tuple[str, str]]]":
        """Everything under the root, with content hashes."""
        result = self._scan()
        out = []
        live = set()
        for path, entry in result.entries.items():
            try:
                item = self.listed(path, entry)
            except (OSError, PathError):
                continue  # vanished, swapped or unreadable: it is reported as skipped
            if item is not None:
                out.append(item)
                live.add(path)
        for path in [p for p in self.cache if p not in live]:
            self._set_cache(path, None)
        out.sort(key=lambda x: x.path)
        return out, sorted(result.skipped)

    def drift(self) -> "Tuple[List[M.Listed], List[str]]":
        """What differs on disk from what was last synced: (changed or new, gone).

        This runs on every push, so unchanged entries cost a stat comparison
        against the cache and nothing more. With a kept listing, not even that: an
        entry found unchanged inline at the last drift is so again while its walk's
        entry (the same object: its stat did not move), its synced row and its cache
        row are the ones then (``settled`` only grows), so only the entries the kept
        walk says moved, those whose rows changed and those not found unchanged last
        time are looked at (the bench's 2,547 paths, a one-edit push: ~4 -> ~0.1 ms;
        tests/test_store_kept_listing.py compares every drift with a fresh Store's).
        """
        entries = self._scan().entries
        moved = self.kept_tree.take_moved() if self.kept_tree is not None else None
        again, self._drift_again = self._drift_again, None  # all again if this one fails
        if again is None or moved is None:
            look = entries.items()  # type: Any
        else:
            look = [(p, entries[p]) for p in again | moved | self._index_moved if p in entries]
        self._index_moved = set()
        unsettled = set()  # type: Set[str]
        synced, cache = self.synced, self.cache
        # what _drifted says of a file its stat cache knows (not racy) or of a directory
        # with its synced mode, said inline: None (the bench's 2,547 paths, a one-edit
        # push: the loop's CPU 15 -> ~4 ms)
        settled = int(time.time() * 1e9) - RACY_NS  # not racy at or before this
        changed = []
        for path, e in look:
            rec = synced.get(path)
            if rec is not None:
                kind, mode, size, mtime_ns, ctime_ns, ino, _target = e
                if kind == FILE:
                    c = cache.get(path)
                    if (
                        c is not None
                        and mtime_ns <= settled
                        and c[0] == size
                        and c[1] == mtime_ns
                        and c[2] == ctime_ns
                        and c[3] == ino
                        and rec[0] == FILE
                        and rec[1] == mode
                        and rec[2] == c[4]
                    ):
                        continue
                elif kind == DIR and rec[0] == DIR and rec[1] == mode:
                    continue
            unsettled.add(path)
            item = self._drifted(path, e, rec)
            if item is not None:
                changed.append(item)
        gone = [p for p in synced if p not in entries]
        changed.sort(key=lambda x: x.path)  # whatever order the walk (or a kept one) had
        if self.kept_tree is not None:
            self._drift_again = unsettled
        return changed, gone

    def _drifted(self, path: str, e: "Entry", rec: "Optional[List[Any]]") -> "Optional[M.Listed]":
        """The entry at ``path`` if it differs from its synced record ``rec``, else None (and
        None for a file that vanished or cannot be read while looked at)."""
        if e.kind == FILE:
            try:
                digest = self.hash_file(path, e)
            except (OSError, PathError):
                return None
            if rec is not None and rec[0] == FILE and rec[2] == digest and rec[1] == e.mode:
                return None
            return M.Listed(path, FILE, e.mode, e.size, hash=digest)
        if e.kind == LINK:
            if rec is not None and rec[0] == LINK and rec[2] == e.target:
                return None
            return M.Listed(path, LINK, target=e.target)
        if rec is not None and rec[0] == DIR and rec[1] == e.mode:
            return None
        return M.Listed(path, DIR, e.mode)

    @staticmethod
    def _matches(item: "M.Listed", rec: "List[Any]") -> bool:
        kind, mode, extra = rec  # type: str, int, str
        if item.kind != kind:
            return False
        if kind == FILE:
            return item.hash == extra and item.mode == mode
        if kind == LINK:
            return item.target == extra
        return item.mode == mode

    def _record(self, path: str, item: "Optional[M.Listed]") -> None:
        if item is None:
            self._set_synced(path, None)
            return
        extra = item.hash if item.kind == FILE else item.target
        self._set_synced(path, [item.kind, item.mode, extra])

    def _forget_below(self, path: str) -> None:
        prefix = path + "/"
        for key in [k for k in self.synced if k == path or k.startswith(prefix)]:
            self._set_synced(key, None)
        for key in [k for k in self.cache if k == path or k.startswith(prefix)]:
            self._set_cache(key, None)

    def adopt(self, items: "List[M.Listed]") -> int:
        """Record ``items`` as synced where the disk still holds exactly them."""
        self._writable()
        n = 0
        for item in items:
            cur = self.current(item.path)
            if cur is not None and self._matches(
                cur, [item.kind, item.mode, item.hash or item.target]
            ):
                self._record(item.path, cur)
                n += 1
        self.gen += 1
        self._dirty = True
        return n

    def _open_file(self, path: str) -> "Tuple[int, os.stat_result]":
        """A regular file of the tree, opened for reading (never through a symlink)."""
        with self._root().parent(path) as (dir_fd, name):
            try:
                fd = os.open(name, O_FILE, dir_fd=dir_fd)
            except OSError as exc:
                if exc.errno in paths.NOT_A_DIR:
                    raise PathError("%r is not a regular file" % path) from None
                raise
        st = os.fstat(fd)
        if not stat_mod.S_ISREG(st.st_mode):
            os.close(fd)
            raise PathError("%r is not a regular file" % path)
        return fd, st

    def signature(self, path: str) -> "Tuple[bytes, str]":
        """The delta signature of the file at ``path``, and its content hash: one pass over
        the file, in pieces (memory bounded by the signature, not the file)."""
        from fetchsync.protocol import delta as delta_mod  # see _write_temp

        fd, st = self._open_file(path)
        if st.st_size > MAX_SIGNED:
            os.close(fd)
            raise ProtocolError(
                "%s: too large for a delta (its signature would not fit in an "
                "answer); it is sent whole" % path
            )
        with io.FileIO(fd, "rb", closefd=True) as fh:
            tee = _Tee(fh, self.algorithm)
            sig = delta_mod.signature_file_bytes(
                cast("BinaryIO", tee),  # it reads, the one method signing uses
                algorithm=self.algorithm,
                bufsize=PIECE,
            )
            return sig, tee.hasher.digest().hex()

    def read(
        self, path: str, *, sig: "Optional[bytes]" = None, offset: int = 0, length: int = -1
    ) -> "Tuple[M.Listed, str, bytes]":
        """Content of a file: (what it is, "data" or "delta", payload). A delta is made
        reading the file in pieces; data is read from ``offset``, ``length`` bytes."""
        fd, st = self._open_file(path)
        with io.FileIO(fd, "rb", closefd=True) as fh:
            digest = self._hash_fd(path, fd, st)
            item = M.Listed(path, FILE, stat_mod.S_IMODE(st.st_mode), st.st_size, hash=digest)
            if sig is not None:
                from fetchsync.protocol import delta as delta_mod  # see _write_temp

                if len(sig) > MAX_READ_SIG:  # its chunks' index would outgrow the file's pieces
                    raise ProtocolError(
                        "%s: the signature is too large for a delta here; read the "
                        "file in pieces" % path
                    )

                base_sig = delta_mod.Signature.from_bytes(sig)
                fh.seek(0)
                return (
                    item,
                    M.SRC_DELTA,
                    delta_mod.encode_delta(delta_mod.delta_file(fh, base_sig, bufsize=PIECE)),
                )
            want = max(0, st.st_size - offset) if length < 0 else length
            if offset < 0 or want > MAX_READ:
                raise ProtocolError(
                    "%s: bad read range, or more than %d MiB at once: read it in "
                    "pieces" % (path, MAX_READ >> 20)
                )
            fh.seek(offset)
            return item, M.SRC_DATA, fh.read() if length < 0 else fh.read(length)

    # ------------------------------------------------------------------ kept versions
    def _kept_root(self, where: str) -> "Optional[paths.Root]":
        """``.fetchsync/<where>`` (``conflicts`` or ``trash``) as a :class:`paths.Root`, never
        through a symlink; None if there is none (read-only: nothing is made)."""
        if where not in KEPT:
            raise ProtocolError("unknown kept place %r" % (where,))
        self._open()
        if self._meta_fd < 0:
            return None
        shown = os.path.join(self.meta, where)
        try:
            fd = open_dir(where, self._meta_fd)
        except FileNotFoundError:
            return None
        except OSError as exc:
            if exc.errno in paths.NOT_A_DIR:
                raise StoreError(
                    "%s is a symlink or not a directory: fetchsync does not read through it" % shown
                ) from None
            raise
        return paths.Root(fd, shown)

    def kept(self, where: str) -> "Tuple[List[List[Any]], bool]":
        """The files kept in ``.fetchsync/<where>/<time>/<path>``: ``[time, path, size,
        mtime]`` each (at most MAX_KEPT; the flag says some were left out). Walked by
        descriptor, O_NOFOLLOW: a symlink in there is listed as nothing, never followed."""
        root = self._kept_root(where)
        if root is None:
            return [], False
        out = []  # type: List[List[Any]]

        def walk(fd: int, rel: str, stamp: str) -> bool:
            for name in sorted(os.listdir(fd)):
                path = rel + "/" + name if rel else name
                try:
                    paths.validate(path)  # no wire path (too long): not listed
                except PathError:
                    continue
                st = lstat_at(name, fd)
                if st is None:
                    continue
                if stat_mod.S_ISDIR(st.st_mode):
                    try:
                        sub = open_dir(name, fd)
                    except OSError:
                        continue  # swapped for something else meanwhile
                    try:
                        if not walk(sub, path, stamp):
                            return False
                    finally:
                        os.close(sub)
                elif stat_mod.S_ISREG(st.st_mode):
                    if len(out) >= MAX_KEPT:
                        return False
                    out.append([stamp, path, st.st_size, st.st_mtime])
            return True

        try:
            for stamp in sorted(os.listdir(root.fd)):
                try:
                    fd = open_dir(stamp, root.fd)
                except OSError:
                    continue  # not a directory (or a symlink): not one of ours
                try:
                    if not walk(fd, "", stamp):
                        return out, True
                finally:
                    os.close(fd)
        finally:
            os.close(root.fd)
        return out, False

    def read_kept(
        self, where: str, stamp: str, path: str, offset: int, length: int
    ) -> "Tuple[int, bytes]":
        """``(size, bytes)`` of the kept file ``.fetchsync/<where>/<stamp>/<path>`` from
        ``offset`` (at most MAX_READ at once); every component opened O_NOFOLLOW."""
        if "/" in paths.validate(stamp):
            raise PathError("bad kept time %r" % (stamp,))
        paths.validate(path)
        if offset < 0 or not 0 <= length <= MAX_READ:
            raise ProtocolError("bad read range, or more than %d MiB at once" % (MAX_READ >> 20))
        root = self._kept_root(where)
        if root is None:
            raise PathError("nothing is kept in %s" % os.path.join(self.meta, where))
        try:
            with root.parent(stamp + "/" + path) as (dir_fd, name):
                try:
                    fd = os.open(name, O_FILE, dir_fd=dir_fd)
                except OSError as exc:
                    if exc.errno in paths.NOT_A_DIR:
                        raise PathError("%r is not a regular file" % path) from None
                    raise
        finally:
            os.close(root.fd)
        with io.FileIO(fd, "rb", closefd=True) as fh:
            st = os.fstat(fd)
            if not stat_mod.S_ISREG(st.st_mode):
                raise PathError("%r is not a regular file" % path)
            fh.seek(offset)
            return st.st_size, fh.read(length)

    # ------------------------------------------------------------------ writing
    def _writable(self) -> None:
        if self.readonly:
            raise StoreError("the workspace was opened read-only: nothing is written")

    def apply(
        self,
        ops: "List[M.Op]",
        blob: bytes,
        *,
        policy: str = "preserve",
        zpart: "Optional[List[int]]" = None,
        unpacked: "Optional[Tuple[bytearray, Any]]" = None,
    ) -> "List[M.Result]":
        """Apply ``ops`` in order; one result each. Per-file failures are results.

        ``zpart`` = [compressed length, length] says the blob starts with one
        zlib stream, which operations flagged ``z`` address once inflated.
        Their new contents are written to temporaries first, made durable, then
        renamed into place, each after its path's precondition is checked again;
        the renames are made durable before this returns.
        """
        self._writable()
        self._stamp = None  # taken again by this batch's first set-aside
        if unpacked is not None:  # the blob's compressed part, inflated while it waited
            packed, blob = unpacked
        elif zpart is not None:
            packed, blob = unpack_zpart(blob, zpart)
        else:
            packed = bytearray()
        batch = _Batch(self, blob, packed, policy)
        batch.fsync_each = sum(op.kind in (M.WRITE, M.SYMLINK) for op in ops) <= FSYNC_EACH
        meta = self._meta()
        fd = os.open(
            BATCH_MARK, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | _CLOEXEC, 0o600, dir_fd=meta
        )
        os.close(fd)
        try:
            batch.results = [batch.run(op, i) for i, op in enumerate(ops)]
            batch.ops = ops
            batch.commit()
        finally:
            batch.cleanup()
            try:
                os.unlink(BATCH_MARK, dir_fd=meta)
            except FileNotFoundError:
                pass
        self.gen += 1
        batch.gen = self.gen
        self._dirty = True
        self._prune_trash()
        return batch.results  # the batch, its request's data with it, not kept

    def sync(self) -> None:
        """Make everything written so far durable."""
        syncfs(self._root().fd)

    def stamp(self) -> str:
        """The name of this batch's directory in the trash and in conflicts: the time and
        the generation, taken once per batch. Taken at each call, a second ticking over
        between a file's set-aside and its count in ``trash_log`` made the log name a
        directory that does not exist (never pruned: the trash's bound did not hold; the
        cause of a test_trash_chain.py failure under CI's load), and a batch crossing a
        second kept its files in two directories."""
        if self._stamp is None:
            self._stamp = "%s-%06d" % (time.strftime("%Y%m%d-%H%M%S"), self.gen + 1)
        return self._stamp

    def _aside_dir(self, path: str, where: str) -> "Tuple[int, str, str]":
        """``(descriptor, name, path to show)`` of where ``path`` goes in
        ``.fetchsync/<where>/<stamp>/``, its directories made (none through a symlink)."""
        parts = [self.stamp()] + path.split("/")
        fd = self._meta_dir(where)
        try:
            for part in parts[:-1]:
                sub = mkdir_open(part, fd, 0o700)
                os.close(fd)
                fd = sub
        except OSError as exc:
            os.close(fd)
            if exc.errno in paths.NOT_A_DIR:
                raise OSError(
                    errno.ENOTDIR,
                    "%s/%s holds a symlink or a file where fetchsync keeps "
                    "a directory" % (META, where),
                ) from None
            raise
        return fd, parts[-1], os.path.join(META, where, *parts)

    def _set_aside(self, dir_fd: int, name: str, path: str, where: str) -> str:
        """Move what stands at ``path`` (``name`` in ``dir_fd``) to
        ``.fetchsync/<where>/<stamp>/path``; the path to show."""
        size = _size_at(name, dir_fd) if where == "trash" else 0
        dest_fd, dest, shown = self._aside_dir(path, where)
        try:
            os.rename(name, dest, src_dir_fd=dir_fd, dst_dir_fd=dest_fd)
        finally:
            os.close(dest_fd)
        if where == "trash":
            self._trashed(size)
        return shown

    def _trashed(self, size: int) -> None:
        """Count ``size`` bytes put in this batch's trash (bounded: _prune_trash)."""
        top = os.path.join("trash", self.stamp())
        if not self.trash_log or self.trash_log[-1][0] != top:
            self.trash_log.append([top, 0])
        self.trash_log[-1][1] += size

    def _put_back(self, dir_fd: int, name: str, path: str, where: str) -> None:
        """Undo :meth:`_set_aside` (an operation that failed after it)."""
        dest_fd, dest, _shown = self._aside_dir(path, where)
        try:
            os.rename(dest, name, src_dir_fd=dest_fd, dst_dir_fd=dir_fd)
        finally:
            os.close(dest_fd)

    def _keep_copy(self, dir_fd: int, name: str, path: str, where: str) -> str:
        """Like _set_aside, but the file stays where it is too (a hard link, else a copy)."""
        dest_fd, dest, shown = self._aside_dir(path, where)
        try:
            try:
                os.link(name, dest, src_dir_fd=dir_fd, dst_dir_fd=dest_fd, follow_symlinks=False)
                return shown
            except OSError as exc:
                if exc.errno not in (errno.EXDEV, errno.EPERM, errno.EMLINK, errno.ENOTSUP):
                    raise
            st = os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
            if stat_mod.S_ISLNK(st.st_mode):
                os.symlink(os.readlink(name, dir_fd=dir_fd), dest, dir_fd=dest_fd)
                return shown
            src = os.open(name, O_FILE, dir_fd=dir_fd)
            try:
                out_fd = os.open(dest, O_NEW, 0o600, dir_fd=dest_fd)
                try:
                    _copy_fd(src, _Out(out_fd, self.algorithm))
                    os.fchmod(out_fd, stat_mod.S_IMODE(st.st_mode))
                except BaseException:
                    os.close(out_fd)
                    os.unlink(dest, dir_fd=dest_fd)
                    raise
                os.close(out_fd)
            finally:
                os.close(src)
            return shown
        finally:
            os.close(dest_fd)

    def _drop_copy(self, path: str, where: str) -> None:
        """Remove a copy :meth:`_keep_copy` made (the operation it was for failed)."""
        try:
            dest_fd, dest, _shown = self._aside_dir(path, where)
        except OSError:
            return
        try:
            os.unlink(dest, dir_fd=dest_fd)
        except OSError:
            pass
        finally:
            os.close(dest_fd)

    def _prune_trash(self) -> None:
        """The trash within its bounds, oldest batches first, but never a batch of the
        deletion under way: the batch just made (its files were renamed there, not
        copied: no disk it did not use already; they are the way back from this very
        push) and the earlier ones of the same deletion (one push's deletions in several
        batches, the watch agent's ``rm -rf`` seen in bursts: TRASH_CHAIN) as long as
        they are not more than TRASH_KEEP_BATCHES (a deletion of ~200,000 files)."""
        total = sum(n for _d, n in self.trash_log)
        chain = self._deletion_under_way()
        i = 0
        while i < len(self.trash_log) - 1 and (
            len(self.trash_log) > TRASH_KEEP_BATCHES or total > TRASH_KEEP_BYTES
        ):
            top, n = self.trash_log[i]
            if top in chain and len(self.trash_log) <= TRASH_KEEP_BATCHES:
                i += 1
                continue
            del self.trash_log[i]
            try:
                trash = self._meta_dir("trash")
                try:
                    rmtree_at(os.path.basename(top), trash)
                finally:
                    os.close(trash)
            except (OSError, ProtocolError):
                pass
            total -= n
            self._dirty = True

    def _deletion_under_way(self) -> "Set[str]":
        """The newest trash batches each made within TRASH_CHAIN seconds of the next, by
        the time in their names (stamp): by any endpoint, so a deletion that goes on in
        a new session (the watch agent reconnected in the middle of an ``rm -rf``) is
        still one (tests/test_trash_chain_reconnect.py)."""
        chain = set()  # type: Set[str]
        later = None  # type: Optional[float]
        for top, _n in reversed(self.trash_log):
            try:
                at = time.mktime(time.strptime(os.path.basename(top)[:15], "%Y%m%d-%H%M%S"))
            except (ValueError, OverflowError):
                break
            if later is not None and not 0 <= later - at < TRASH_CHAIN:
                break
            chain.add(top)
            later = at
        return chain

    def unsynced_below(self, path: str, dir_fd: int, name: str) -> "List[str]":
        """Files and links under directory ``path`` (``name`` in ``dir_fd``) that differ from
        what was last synced."""
        try:
            fd = open_dir(name, dir_fd)
        except OSError:
            return []
        out = []
        try:
            for rel, entry in scan_fd(fd, prefix=path).entries.items():
                if entry.kind == DIR:
                    continue
                rec = self.synced.get(rel)
                try:
                    cur = self.listed(rel, entry)
                except (OSError, PathError):
                    continue
                if cur is not None and (rec is None or not self._matches(cur, rec)):
                    out.append(rel)
        finally:
            os.close(fd)
        return sorted(out)


class _Refused(Exception):
    pass


class _Batch:
    """One apply() call: operations without content at once, new contents to temporaries;
    then one syncfs, the replacements (each checked again), one syncfs."""

    def __init__(self, store: "Store", blob: "Any", packed: "Any", policy: str) -> None:
        self.s = store
        self.blob = blob
        self.zpart = packed
        self.policy = policy
        self.pending = []  # type: List[Tuple[M.Op, int, str]]  # (op, result index, temporary)
        self.ops = []  # type: List[M.Op]
        self.results = []  # type: List[M.Result]
        self.gen = 0  # the store's generation once this batch is applied
        self.exchanged = False  # the operation being committed has swapped its temporary in
        self.dirs = None  # type: Optional[paths.Dirs]  # the directories written in, checked at each use
        self.fsync_each = False  # each temporary fsynced once written (see FSYNC_EACH)
        self.unsynced = False  # a temporary not fsynced: a syncfs before the renames

    def _at_parent(self, path: str) -> "Optional[Tuple[int, str]]":
        """``(descriptor of path's directory, last component)`` from the batch's checked
        directory descriptors (:class:`paths.Dirs`; not to be closed), or None where the
        caller walks the path afresh (:meth:`paths.Root.parent`)."""
        if self.dirs is None:
            self.dirs = paths.Dirs(self.s._root())
        return self.dirs.parent(path)

    def _view(self, op: "M.Op") -> memoryview:
        """The operation's data, not copied (hashed and written as it lies in the request)."""
        off, length = op.blob
        data = self.zpart if op.z else self.blob
        if off + length > len(data):
            raise ProtocolError("operation on %r points past the request's data" % op.path)
        return memoryview(data)[off : off + length]

    def run(self, op: "M.Op", idx: int) -> "M.Result":
        try:
            return self._run(op, idx)
        except _Refused as exc:
            return M.Result(M.CONFLICT, str(exc))
        except PathError as exc:
            return M.Result(M.PATH_ERROR, str(exc))
        except DeltaError as exc:
            return M.Result(M.BASE_MISMATCH, "delta does not apply: %s" % exc)
        except OSError as exc:
            return _os_error(op, exc)

    def _run(self, op: "M.Op", idx: int) -> "M.Result":
        s = self.s
        if op.kind == M.UPLOAD:
            self._upload(op)
            return M.Result()
        if TEMP_MARK in op.path and any(is_temp(part) for part in op.path.split("/")):
            # our temporaries' names: never synced, and removed by the cleanup
            raise PathError("%r uses a name reserved for fetchsync's temporaries" % op.path)
        if op.kind in (M.DELETE, M.MKDIR, M.CHMOD):
            with s._root().parent(op.path) as (dir_fd, name):
                if op.kind == M.DELETE:
                    return self._delete(op, dir_fd, name)
                if op.kind == M.MKDIR:
                    return self._mkdir(op, dir_fd, name)
                return self._chmod(op, dir_fd, name)
        at = self._at_parent(paths.validate(op.path))
        if at is None:
            with s._root().parent(op.path) as (dir_fd, name):
                return self._content(op, idx, dir_fd, name)
        return self._content(op, idx, at[0], at[1])

    def _content(self, op: "M.Op", idx: int, dir_fd: int, name: str) -> "M.Result":
        """The new content goes to a temporary beside the target, renamed at commit."""
        tmp = _temp_name(name)
        if op.kind == M.SYMLINK:
            os.symlink(op.target, tmp, dir_fd=dir_fd)
            self.unsynced = True
        else:
            try:
                self._write_temp(op, dir_fd, name, tmp)
            except (DeltaError, OSError, ProtocolError):
                raise
            except Exception as exc:  # say, a malformed delta: this operation's failure only
                return M.Result(M.IO_ERROR, "%s: %s" % (op.path, exc))
        self.pending.append((op, idx, tmp))
        return M.Result()

    # -- operations without content: checked and done at once
    def _conflict(self, op: "M.Op", cur: "M.Listed") -> bool:
        """Whether ``cur`` is not what the sender last saw at op.path; raises _Refused when
        the policy refuses."""
        if cur.expectation() == op.expect:
            return False
        if self.policy == "refuse":
            raise _Refused("%s was changed here since the last sync" % op.path)
        return True

    def _dir_aside(self, op: "M.Op", dir_fd: int, name: str) -> str:
        """The directory at op.path goes to the trash, its files edited here (unsynced) to
        the conflicts first; where the first of those went ("" if none)."""
        s = self.s
        unsynced = s.unsynced_below(op.path, dir_fd, name)
        if unsynced and self.policy == "refuse":
            raise _Refused("%s was changed here since the last sync" % unsynced[0])
        kept = ""
        for path in unsynced:
            with s._root().parent(path) as (sub_fd, sub_name):
                kept = kept or s._set_aside(sub_fd, sub_name, path, "conflicts")
        s._set_aside(dir_fd, name, op.path, "trash")
        s._forget_below(op.path)
        return kept[: len(kept) - len(unsynced[0])] + op.path if kept else ""

    def _delete(self, op: "M.Op", dir_fd: int, name: str) -> "M.Result":
        s = self.s
        cur = s._at(op.path, dir_fd, name)
        preserved = ""
        if cur is not None and cur.kind == DIR:
            preserved = self._dir_aside(op, dir_fd, name)
        elif cur is not None:
            if self._conflict(op, cur):
                preserved = s._set_aside(dir_fd, name, op.path, "conflicts")
            else:
                s._set_aside(dir_fd, name, op.path, "trash")
            s._forget_below(op.path)
        s._record(op.path, None)
        return M.Result(preserved=preserved)

    def _mkdir(self, op: "M.Op", dir_fd: int, name: str) -> "M.Result":
        s = self.s
        mode = op.mode or 0o755
        cur = s._at(op.path, dir_fd, name)
        preserved, moved = "", ""
        if cur is not None and cur.kind != DIR:
            # a file or link stands where the directory goes
            moved = "conflicts" if self._conflict(op, cur) else "trash"
            kept = s._set_aside(dir_fd, name, op.path, moved)
            preserved = kept if moved == "conflicts" else ""
            s._forget_below(op.path)
            cur = None
        if cur is None:
            try:
                os.mkdir(name, mode, dir_fd=dir_fd)
            except BaseException:
                if moved:
                    s._put_back(dir_fd, name, op.path, moved)
                raise
        item = s._at(
            op.path, dir_fd, name
        )  # made with the mode asked, unless umask or setgid say otherwise
        if item is None or item.kind != DIR:
            raise OSError(errno.EEXIST, "something else was put there meanwhile")
        if item.mode != mode:
            _chmod_at(dir_fd, name, mode)
            item = s._at(op.path, dir_fd, name)
        s._record(op.path, item)
        return M.Result(preserved=preserved, written=item.to_wire() if item else None)

    def _chmod(self, op: "M.Op", dir_fd: int, name: str) -> "M.Result":
        s = self.s
        cur = s._at(op.path, dir_fd, name)
        if cur is None or cur.kind == LINK:
            return M.Result(M.IO_ERROR, "%s: nothing to chmod" % op.path)
        if self._conflict(op, cur):
            # its content was changed here: a mode alone cannot make it the sender's;
            # the robot's version is kept now, whatever the sender does next
            kept = s._keep_copy(dir_fd, name, op.path, "conflicts") if cur.kind == FILE else ""
            return M.Result(
                M.BASE_MISMATCH,
                "%s was changed here since the last sync%s"
                % (op.path, "; kept at " + kept if kept else ""),
                preserved=kept,
            )
        _chmod_at(dir_fd, name, op.mode)
        item = s._at(op.path, dir_fd, name)
        s._record(op.path, item)
        return M.Result(written=item.to_wire() if item else None)

    # -- content: to a temporary now, renamed at commit
    def _upload(self, op: "M.Op") -> None:
        """A piece of a large file's content, at its offset in an upload part."""
        s = self.s
        view = self._view(op)
        part = "upload-" + op.upload
        tmp_dir = s._meta_dir(TMP)
        try:
            s._uploads.add(part)
            fd = os.open(
                part, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | _CLOEXEC, 0o600, dir_fd=tmp_dir
            )
        finally:
            os.close(tmp_dir)
        try:
            # past the part's end, zeros may stay holes; before it, they overwrite
            out = _Out(fd, s.algorithm, sparse=os.fstat(fd).st_size <= op.size)
            os.lseek(fd, op.size, os.SEEK_SET)
            out.write(view)
            if out.pending_hole:  # the piece ends in a hole: the part reaches its end
                os.ftruncate(fd, op.size + out.size)  # (out.close() would cut it at out.size)
        finally:
            os.close(fd)

    def _write_temp(self, op: "M.Op", dir_fd: int, name: str, tmp: str) -> None:
        s = self.s
        mode = op.mode or 0o644
        fix = mode if mode & _umask() or mode & ~0o777 else None  # else open() makes it so
        if op.source == M.SRC_UPLOAD:
            self._from_upload(op, dir_fd, tmp, mode)
            self.unsynced = True
            return
        verified = op.source in (M.SRC_DATA, M.SRC_STL)
        if verified:
            data = self._view(op)
            if op.source == M.SRC_STL:
                joined = stl.join(data)
                if joined is None:
                    raise DeltaError("the split mesh is not shaped as one")
                data = memoryview(joined)
            # checked before anything is written: most writes are whole data
            if len(data) != op.size or hashing.digest(s.algorithm, data).hex() != op.hash:
                raise DeltaError("reconstructed content does not match its hash")
        fd = os.open(tmp, O_NEW, mode, dir_fd=dir_fd)
        try:
            out = _Out(fd, s.algorithm, hashed=not verified)  # (verified: not hashed twice)
            if verified:
                out.write(data)
            elif op.source == M.SRC_DELTA:
                self._patch(op, dir_fd, name, out)
            elif op.source == M.SRC_ZDICT:
                out.write(self._inflate_with_base(op, dir_fd, name))
            else:  # copy
                try:
                    src, _st = s._open_file(op.from_path)
                except (OSError, PathError):
                    raise DeltaError("the copy's source %r is not here" % op.from_path) from None
                try:
                    _copy_fd(src, out)
                finally:
                    os.close(src)
            digest = out.close()
            if out.size != op.size or (not verified and digest != op.hash):
                raise DeltaError("reconstructed content does not match its hash")
            if fix is not None:
                os.fchmod(fd, fix)
            if self.fsync_each:
                os.fsync(fd)  # durable before it is renamed into place
            else:
                self.unsynced = True
        except BaseException:
            os.close(fd)
            os.unlink(tmp, dir_fd=dir_fd)
            raise
        os.close(fd)

    def _patch(self, op: "M.Op", dir_fd: int, name: str, out: "_Out") -> None:
        """Write the file at ``name`` with the op's delta applied to ``out``."""
        # imported when first needed: ~4 ms of every endpoint start, on the critical
        # path of an initial push, which sends no delta
        from fetchsync.protocol import delta as delta_mod

        d = delta_mod.decode_delta(bytes(self._view(op)), max_size=op.size)
        base = os.open(name, O_FILE, dir_fd=dir_fd)
        try:
            if not stat_mod.S_ISREG(os.fstat(base).st_mode):
                raise DeltaError("the file here is not the delta's base")
            with io.FileIO(base, "rb", closefd=False) as fh:
                delta_mod.patch_to_file(fh, d, out, bufsize=PIECE)  # type: ignore[arg-type]
        finally:
            os.close(base)

    def _inflate_with_base(self, op: "M.Op", dir_fd: int, name: str) -> bytes:
        """The op's content: its blob inflated with the file at ``name`` as the preset
        dictionary. A base that is not the laptop's (its hash checked by the result's) is
        a mismatch: the laptop sends the file whole next."""
        base = os.open(name, O_FILE, dir_fd=dir_fd)
        try:
            st = os.fstat(base)
            if not stat_mod.S_ISREG(st.st_mode) or st.st_size > M.ZDICT_BASE_MAX:
                raise DeltaError("the file here is not the dictionary's base")
            with io.FileIO(base, "rb", closefd=False) as fh:
                zdict = fh.read(M.ZDICT_BASE_MAX + 1)
        finally:
            os.close(base)
        if len(zdict) > M.ZDICT_BASE_MAX:
            raise DeltaError("the file here is not the dictionary's base")
        try:
            d = zlib.decompressobj(-15, zdict=zdict) if zdict else zlib.decompressobj(-15)
            data = d.decompress(bytes(self._view(op)), op.size + 1)
            if not d.eof or d.unconsumed_tail or len(data) != op.size:
                raise DeltaError("dictionary write is truncated or of the wrong size")
        except zlib.error as exc:
            raise DeltaError("dictionary write does not inflate: %s" % exc) from None
        return data

    def _from_upload(self, op: "M.Op", dir_fd: int, tmp: str, mode: int) -> None:
        """The upload part, verified, becomes the temporary."""
        s = self.s
        part = "upload-" + op.upload
        tmp_dir = s._meta_dir(TMP)
        try:
            fd = os.open(part, os.O_RDWR | os.O_NOFOLLOW | _CLOEXEC, dir_fd=tmp_dir)
            try:
                if not stat_mod.S_ISREG(os.fstat(fd).st_mode):
                    raise OSError(errno.EIO, "the upload is not a regular file")
                if os.fstat(fd).st_size < op.size:
                    os.ftruncate(fd, op.size)  # a hole at its end
                got = hashing.file_digest(s.algorithm, fd, PIECE).hex()
                if got != op.hash or os.fstat(fd).st_size != op.size:
                    os.unlink(part, dir_fd=tmp_dir)
                    s._uploads.discard(part)
                    raise OSError(errno.EIO, "uploaded content does not match its hash")
                os.fchmod(fd, mode)
            finally:
                os.close(fd)
            os.rename(part, tmp, src_dir_fd=tmp_dir, dst_dir_fd=dir_fd)
            s._uploads.discard(part)
        finally:
            os.close(tmp_dir)

    # -- commit
    def commit(self) -> None:
        """Make the temporaries durable, rename each into place (checking its path again),
        and make the renames, and the batch's other changes, durable."""
        if not self.pending and not any(op.kind != M.UPLOAD for op in self.ops):
            return  # upload parts only: nothing is reported written yet
        root = self.s._root()
        if self.unsynced:
            syncfs(root.fd)  # the temporaries' content, before any is renamed into place
        self.pending.reverse()  # taken from the end, in order
        while self.pending:
            op, idx, tmp = self.pending[-1]
            try:
                self.results[idx] = self._replace(op, tmp)
            except _Refused as exc:
                self.results[idx] = M.Result(M.CONFLICT, str(exc))
            except PathError as exc:
                self.results[idx] = M.Result(M.PATH_ERROR, str(exc))
            except OSError as exc:
                self.results[idx] = _os_error(op, exc)
            else:
                self.pending.pop()
                continue
            self.pending.pop()
            self._unlink(op.path, tmp)
        syncfs(root.fd)

    def _replace(self, op: "M.Op", tmp: str) -> "M.Result":
        """Rename the temporary over op.path, once what stands there is what the sender
        last saw, or is kept: a version edited here is linked into the conflicts before
        the rename replaces it, and the rename is the only change to op.path."""
        at = self._at_parent(op.path)
        if at is None:
            with self.s._root().parent(op.path) as (dir_fd, name):
                return self._replace_at(op, tmp, dir_fd, name)
        return self._replace_at(op, tmp, at[0], at[1])

    def _replace_at(self, op: "M.Op", tmp: str, dir_fd: int, name: str) -> "M.Result":
        s = self.s
        before = lstat_at(name, dir_fd)
        preserved, aside = self._make_room(op, dir_fd, name)
        self.exchanged = False
        try:
            if aside or not self._swap_in(op, dir_fd, name, tmp, before, preserved):
                os.rename(tmp, name, src_dir_fd=dir_fd, dst_dir_fd=dir_fd)
            elif self.exchanged and lstat_at(tmp, dir_fd) is not None:
                # what the exchange took out changed after it was checked: kept
                preserved = s._set_aside(dir_fd, tmp, op.path, "conflicts")
        except BaseException:
            if aside:
                s._put_back(dir_fd, name, op.path, aside)
            elif self.exchanged and lstat_at(tmp, dir_fd) is not None:
                _renameat2(dir_fd, tmp, name, RENAME_EXCHANGE)  # the robot's version back
            elif preserved:
                s._drop_copy(op.path, "conflicts")
            raise
        item = s._written_at(op.path, dir_fd, name, op.hash if op.kind == M.WRITE else "")
        s._record(op.path, item)
        return M.Result(preserved=preserved, written=item.to_wire() if item else None)

    def _make_room(self, op: "M.Op", dir_fd: int, name: str) -> "Tuple[str, str]":
        """Keep what stands at op.path before it is replaced, as it needs: (where it was kept,
        and which area it was moved to, "" if it stays in place until the rename)."""
        s = self.s
        cur = s._at(op.path, dir_fd, name)
        if cur is not None and cur.kind == DIR and op.expect == M.IS_DIR:
            # a directory becomes a file or link: the old tree goes to the trash
            return self._dir_aside(op, dir_fd, name), "trash"
        if cur is not None and cur.kind == DIR:
            self._conflict(op, cur)  # refused, or made here since the sender looked: kept whole
            preserved = s._set_aside(dir_fd, name, op.path, "conflicts")
            s._forget_below(op.path)
            return preserved, "conflicts"
        if cur is not None and not _same(op, cur) and self._conflict(op, cur):
            return s._keep_copy(dir_fd, name, op.path, "conflicts"), ""
        if cur is not None and not _same(op, cur) and s.keep_replaced:
            # linked into the trash: the swap below replaces it in place (what a save
            # puts there meanwhile is kept as any change after the check)
            s._keep_copy(dir_fd, name, op.path, "trash")
            s._trashed(cur.size if cur.kind == FILE else 0)
        return "", ""

    def _swap_in(
        self,
        op: "M.Op",
        dir_fd: int,
        name: str,
        tmp: str,
        before: "Optional[os.stat_result]",
        preserved: str,
    ) -> bool:
        """Put the temporary in place with renameat2, so nothing the robot does between the
        check and the rename is lost: over nothing, only if nothing appeared meanwhile
        (RENAME_NOREPLACE); over a file, by exchanging the two, the old version then
        deleted only if it is still the one checked (else it stays at the temporary's
        name for the caller to keep). False where renameat2 cannot (a plain rename then)."""
        if before is None:
            if _renameat2(dir_fd, tmp, name, RENAME_NOREPLACE):
                return True
            return False
        if stat_mod.S_ISDIR(before.st_mode) or not _renameat2(dir_fd, tmp, name, RENAME_EXCHANGE):
            return False
        self.exchanged = True
        out = lstat_at(tmp, dir_fd)
        if out is not None and (out.st_ino, out.st_size, out.st_mtime_ns) == (
            before.st_ino,
            before.st_size,
            before.st_mtime_ns,
        ):
            os.unlink(tmp, dir_fd=dir_fd)  # exactly what was checked (and kept, if edited)
        return True

    def _unlink(self, path: str, tmp: str) -> None:
        try:
            with self.s._root().parent(path) as (dir_fd, _name):
                os.unlink(tmp, dir_fd=dir_fd)
        except (OSError, ProtocolError):
            pass

    def cleanup(self) -> None:
        for op, _idx, tmp in self.pending:
            self._unlink(op.path, tmp)
        self.pending = []
        if self.dirs is not None:
            self.dirs.close()
            self.dirs = None


RENAME_NOREPLACE = 1
RENAME_EXCHANGE = 2
# renameat2's system call number (glibc has a wrapper only from 2.28, after Ubuntu 18.04's)
_RENAMEAT2 = {
    "x86_64": 316,
    "aarch64": 276,
    "riscv64": 276,
    "i386": 353,
    "i686": 353,
    "armv6l": 382,
    "armv7l": 382,
    "armv8l": 382,
    "ppc64le": 357,
}
# this machine's number, looked up once (not an uname per renamed file)
_RENAMEAT2_NR = _RENAMEAT2.get(os.uname().machine)
_renameat2_works = True


def _renameat2(dir_fd: int, src: str, dst: str, flags: int) -> bool:
    """renameat2(2) of ``src`` to ``dst`` in ``dir_fd``; False where the kernel or the file
    system cannot (the caller renames plainly); an OSError otherwise (EEXIST: something
    appeared at ``dst`` under RENAME_NOREPLACE)."""
    global _renameat2_works, _libc
    number = _RENAMEAT2_NR
    if not _renameat2_works or number is None:
        return False
    import ctypes

    if _libc is None:
        _libc = ctypes.CDLL(None, use_errno=True)
    if (
        _libc.syscall(
            ctypes.c_long(number),
            ctypes.c_int(dir_fd),
            ctypes.c_char_p(os.fsencode(src)),
            ctypes.c_int(dir_fd),
            ctypes.c_char_p(os.fsencode(dst)),
            ctypes.c_uint(flags),
        )
        == 0
    ):
        return True
    err = ctypes.get_errno()
    if err == errno.ENOSYS:
        _renameat2_works = False
        return False
    if err in (errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False  # not on this file system
    raise OSError(err, os.strerror(err))


def _same(op: "M.Op", cur: "M.Listed") -> bool:
    """Whether ``cur`` is already exactly what ``op`` writes (nothing of the robot's to keep)."""
    if op.kind == M.WRITE:
        return cur.kind == FILE and cur.hash == op.hash
    return op.kind == M.SYMLINK and cur.kind == LINK and cur.target == op.target


def _chmod_at(dir_fd: int, name: str, mode: int) -> None:
    """chmod of ``name`` in ``dir_fd``, never through a symlink: through a descriptor of
    the file itself (an O_PATH one, by /proc, where it cannot be opened for reading)."""
    try:
        fd = os.open(name, O_FILE, dir_fd=dir_fd)
    except OSError as exc:
        if exc.errno != errno.EACCES or not hasattr(os, "O_PATH"):
            raise
        fd = os.open(name, os.O_PATH | os.O_NOFOLLOW | _CLOEXEC, dir_fd=dir_fd)
        try:
            if stat_mod.S_ISLNK(os.fstat(fd).st_mode):
                raise OSError(errno.ELOOP, "a symlink has no mode")
            os.chmod("/proc/self/fd/%d" % fd, mode)
        finally:
            os.close(fd)
        return
    try:
        os.fchmod(fd, mode)
    finally:
        os.close(fd)


def _os_error(op: "M.Op", exc: "OSError") -> "M.Result":
    code = M.NO_SPACE if exc.errno in (errno.ENOSPC, errno.EDQUOT) else M.IO_ERROR
    return M.Result(code, "%s: %s" % (op.path or op.upload, exc.strerror or exc))
