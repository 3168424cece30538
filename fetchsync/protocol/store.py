"""The filesystem endpoint: one synced tree on disk, changed only through operations.

A :class:`Store` owns ``<workspace>/src`` (the synced root) and
``<workspace>/.fetchsync`` (its metadata). It runs on the robot behind the
wire server, and on the laptop for ``pull``: one implementation, both ends.

Rules it keeps:

- Writes go to a temporary beside the target; every temporary of a batch is
  made durable with one ``syncfs`` before any is renamed into place, and the
  renames are made durable with another: a reader never sees a torn file, and
  what was reported written survives a power cut.
- Before a path is replaced or deleted, what stands there is compared with the
  operation's expectation (what the sender last synced). A mismatch means
  someone edited it here: that version is moved to ``.fetchsync/conflicts/``
  (policy ``preserve``) or the operation is refused (policy ``refuse``).
  Deleted paths go to a bounded ``.fetchsync/trash/``. Nothing is lost.
- Nothing is written outside the root, nor through a symlink.
- The index (``.fetchsync/index``, a :mod:`marshal` snapshot, plus
  ``index.log``, the changes made since, appended after every request and
  folded into a new snapshot when it grows) records what was last synced at each
  path, a stat cache for content hashes, an epoch and a generation, so the
  sender can learn in one round trip what changed here since its last sync.
"""

from __future__ import annotations

import errno
import fcntl
import itertools
import marshal
import mmap
import os
import stat as stat_mod
import struct
import threading
import time
from typing import Any, Dict, List, Optional, Tuple

from fetchsync.protocol import hashing, paths, wire
from fetchsync.protocol import messages as M
from fetchsync.protocol.errors import DeltaError, PathError, ProtocolError
from fetchsync.protocol.tree import DIR, FILE, LINK, Entry, scan, stat_path

META = ".fetchsync"
TEMP_MARK = ".fetchsync-tmp-"
TRASH_KEEP_BATCHES = 50
TRASH_KEEP_BYTES = 512 * 1024 * 1024
INDEX_VERSION = 3
INDEX = "index"
JOURNAL = "index.log"
JOURNAL_MIN = 1 << 20  # the journal is folded into a new snapshot past this and half the snapshot
_LEN = struct.Struct(">I")
OLD_INDEXES = ("index.json",)  # earlier formats: dropped (the first push lists in full)
_INDEX_TYPES = (("epoch", str), ("gen", int), ("synced", dict), ("cache", dict), ("trash", list),
                ("serial", str))
READ_BLOCK = 1 << 20
WRITE_APART = 512 * 1024  # files this large are written by a second thread (_Writes)
# ... around the page cache (O_DIRECT), in pieces of this size copied to an aligned buffer
DIRECT_PIECE = 2 * 1024 * 1024
DIRECT_ALIGN = 4096  # a multiple of any disk's logical block; the buffer is page-aligned
_O_DIRECT = getattr(os, "O_DIRECT", 0)
BATCH_MARK = "batch-in-progress"  # while it exists, temporaries may lie in the tree
# how long a directory this endpoint made counts as holding only what it wrote there
# since (see _Batch._check): the next batches of one push, not the next push
MADE_FOR = 10.0


class StoreError(ProtocolError):
    """The store cannot be opened or used at all (not a per-file failure)."""


def is_temp(name: str) -> bool:
    return TEMP_MARK in name and name.startswith(".")


_TEMP_IDS = itertools.count()
_TEMP_SALT = os.urandom(6).hex()


def _temp_name(final_name: str) -> str:
    # unique per process (a random salt, then a counter): no random bytes per file
    return ".%s%s%s%06x" % (final_name[:100], TEMP_MARK, _TEMP_SALT, next(_TEMP_IDS) & 0xFFFFFF)


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


def unpack_zpart(blob: bytes, zpart: Any) -> Tuple[bytes, Any]:
    """A sync request's blob as (its compressed part inflated, the raw rest, not copied)."""
    if not (isinstance(zpart, list) and len(zpart) == 2 and all(isinstance(x, int) for x in zpart)
            and 0 <= zpart[0] <= len(blob) and 0 <= zpart[1] <= wire.MAX_BODY):
        raise ProtocolError("bad compressed-part reference")
    view = memoryview(blob)
    packed = wire.inflate(view[:zpart[0]], zpart[1])
    if len(packed) != zpart[1]:
        raise ProtocolError("compressed part has the wrong length")
    return packed, view[zpart[0]:]


def _rmtree(path: str, ignore_errors: bool = False) -> None:
    """``shutil.rmtree``, imported only for a directory that is not empty (shutil and
    the archive modules it imports cost every endpoint start ~5 ms)."""
    try:
        os.rmdir(path)
        return
    except OSError:
        pass
    import shutil
    shutil.rmtree(path, ignore_errors=ignore_errors)


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


def _fsize(path: str) -> int:
    total = 0
    for dirpath, _dirs, files in os.walk(path):
        for name in files:
            try:
                total += os.lstat(os.path.join(dirpath, name)).st_size
            except OSError:
                pass
    return total


class Store:
    def __init__(self, workspace: str, *, algorithm: str, rules: Any = None, create: bool = True,
                 meta_dir: Optional[str] = None) -> None:
        self.workspace = workspace
        self.root = os.path.join(workspace, "src")
        self.meta = meta_dir or os.path.join(workspace, META)
        self.algorithm = algorithm
        self.rules = rules
        self._resolver = paths.Resolver(self.root)
        try:
            if create:
                os.makedirs(self.root, exist_ok=True)
            elif not os.path.isdir(self.root):
                raise StoreError("%s does not exist" % self.root)
            st = os.lstat(self.root)
            if not stat_mod.S_ISDIR(st.st_mode):
                raise StoreError("%s is not a directory (a symlink?)" % self.root)
            os.makedirs(os.path.join(self.meta, "tmp"), exist_ok=True)
        except OSError as exc:
            if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
                where = exc.filename or self.root
                raise StoreError("the remote workspace is not writable: cannot create %s: %s; "
                                 "check the permissions of %s on the robot, or pass another "
                                 "--remote-workspace"
                                 % (where, exc.strerror, os.path.dirname(where))) from None
            raise StoreError("cannot use %s: %s" % (self.root, exc.strerror or exc)) from None
        self._lock_fd = -1
        self._open_batches = 0  # begun and not finished: the lock is kept meanwhile
        # upload parts this session started: a client that goes away between
        # the batches of a large file leaves them, with no batch marker to say so
        self._uploads = set()  # type: set
        self.watched = None  # type: Any  # a WatchedTree, see watch()
        self._load_index()

    # ------------------------------------------------------------------ index
    def _index_stamp(self) -> Any:
        stamp = []  # type: List[Optional[Tuple[int, int, int]]]
        for name in (INDEX, JOURNAL):
            try:
                st = os.stat(os.path.join(self.meta, name))
            except OSError:
                stamp.append(None)
            else:
                stamp.append((st.st_ino, st.st_size, st.st_mtime_ns))
        return tuple(stamp)

    def _load_index(self) -> None:
        path = os.path.join(self.meta, INDEX)
        # another writer may have put files in the directories we made
        self.made = {}  # type: Dict[str, float]  # see _Batch._check
        self._loaded_stamp = self._index_stamp()
        self._touched_synced = set()  # type: set  # paths changed since the last save
        self._touched_cache = set()  # type: set
        data = None  # type: Any
        try:
            with open(path, "rb") as fh:
                data = marshal.loads(fh.read())
        except FileNotFoundError:
            for old in OLD_INDEXES:
                try:
                    os.unlink(os.path.join(self.meta, old))
                except OSError:
                    pass
        except (OSError, ValueError, EOFError, TypeError):
            data = None  # a damaged index only costs a full listing
        if (not isinstance(data, dict) or data.get("v") != INDEX_VERSION
                or data.get("algorithm") != self.algorithm
                or not all(isinstance(data.get(k), t) for k, t in _INDEX_TYPES)):
            data = {"v": INDEX_VERSION, "epoch": os.urandom(16).hex(), "gen": 0, "serial": "",
                    "algorithm": self.algorithm, "synced": {}, "cache": {}, "trash": []}
            self._dirty = True
        else:
            self._dirty = False
        self.epoch = data["epoch"]  # type: str
        self.gen = int(data["gen"])
        self.synced = data["synced"]  # type: Dict[str, List[Any]]  # path -> [kind, mode, hash|target]
        self.cache = data["cache"]    # type: Dict[str, List[Any]]  # path -> [size, mtime, ctime, ino, hash]
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
            with open(os.path.join(self.meta, JOURNAL), "rb") as fh:
                buf = fh.read()
        except FileNotFoundError:
            return 0
        except OSError:
            return -1
        pos = 0
        while pos + _LEN.size <= len(buf):
            (n,) = _LEN.unpack_from(buf, pos)
            end = pos + _LEN.size + n
            if end > len(buf):
                break  # torn by a crash mid-append
            try:
                rec = marshal.loads(buf[pos + _LEN.size:end])
                if not (isinstance(rec, dict) and rec.get("serial") == self._serial):
                    break
                epoch, gen, trash = rec["epoch"], rec["gen"], rec["trash"]
                changes = [(self.synced, rec["s"]), (self.cache, rec["c"])]
                if not (isinstance(epoch, str) and isinstance(gen, int) and isinstance(trash, list)
                        and all(isinstance(c, dict) for _t, c in changes)):
                    break
            except (ValueError, EOFError, TypeError, KeyError):
                break
            for table, change in changes:
                for path, value in change.items():
                    if value is None:
                        table.pop(path, None)
                    else:
                        table[path] = value
            self.epoch, self.gen, self.trash_log = epoch, gen, trash
            pos = end
        return pos if pos == len(buf) else -1

    def discard_uploads(self) -> None:
        """Remove the upload parts this session started and never used (its client left)."""
        for part in list(self._uploads):
            try:
                os.unlink(part)
            except OSError:
                pass
        self._uploads.clear()

    def save_index(self) -> None:
        """Record what changed since the last save: a journal record of the touched paths,
        or, once the journal outgrows half the snapshot, a new snapshot.

        Rewriting the whole index after every request cost a one-file save ~0.3 s
        of the robot's time on 100,000 files; a record costs what it holds.
        """
        if not self._dirty:
            return
        if self._journal_size < 0 or self._journal_size > max(JOURNAL_MIN, self._snapshot_size // 2):
            self._write_snapshot()
        else:
            rec = marshal.dumps({
                "serial": self._serial, "epoch": self.epoch, "gen": self.gen, "trash": self.trash_log,
                "s": {p: self.synced.get(p) for p in self._touched_synced},
                "c": {p: self.cache.get(p) for p in self._touched_cache}})
            fd = os.open(os.path.join(self.meta, JOURNAL), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
            try:
                _write_all(fd, _LEN.pack(len(rec)) + rec)
            finally:
                os.close(fd)
            self._journal_size += _LEN.size + len(rec)
        self._touched_synced.clear()
        self._touched_cache.clear()
        self._dirty = False
        self._loaded_stamp = self._index_stamp()

    def _write_snapshot(self) -> None:
        self._serial = os.urandom(16).hex()
        blob = marshal.dumps({"v": INDEX_VERSION, "epoch": self.epoch, "gen": self.gen,
                              "algorithm": self.algorithm, "serial": self._serial,
                              "synced": self.synced, "cache": self.cache, "trash": self.trash_log})
        path = os.path.join(self.meta, INDEX)
        with open(path + ".tmp", "wb") as fh:
            fh.write(blob)
        os.replace(path + ".tmp", path)
        # the old journal's records name the old snapshot: a crash before this
        # line leaves them ignored, never applied to the new one
        with open(os.path.join(self.meta, JOURNAL + ".tmp"), "wb"):
            pass
        os.replace(os.path.join(self.meta, JOURNAL + ".tmp"), os.path.join(self.meta, JOURNAL))
        self._snapshot_size = len(blob)
        self._journal_size = 0

    def _set_cache(self, path: str, value: Optional[List[Any]]) -> None:
        self._set_row(self.cache, self._touched_cache, path, value)

    def _set_synced(self, path: str, value: Optional[List[Any]]) -> None:
        self._set_row(self.synced, self._touched_synced, path, value)

    def _set_row(self, table: Dict[str, Any], touched: set, path: str,
                 value: Optional[List[Any]]) -> None:
        """Set or drop (None) ``path``'s row in one of the index's tables, for the journal."""
        if value is None:
            if table.pop(path, None) is None:
                return
        else:
            table[path] = value
        touched.add(path)
        self._dirty = True

    def _clean_temps(self) -> None:
        for dirpath, dirs, files in os.walk(self.root):
            for name in files + dirs:
                if is_temp(name):
                    full = os.path.join(dirpath, name)
                    try:
                        if os.path.isdir(full) and not os.path.islink(full):
                            _rmtree(full)
                        else:
                            os.unlink(full)
                    except OSError:
                        pass
        _rmtree(os.path.join(self.meta, "tmp"), ignore_errors=True)
        os.makedirs(os.path.join(self.meta, "tmp"), exist_ok=True)
        try:
            os.unlink(os.path.join(self.meta, BATCH_MARK))
        except FileNotFoundError:
            pass

    # ------------------------------------------------------------------ locking
    def lock(self, timeout: float = 30.0) -> None:
        if self._lock_fd >= 0:
            return
        fd = os.open(os.path.join(self.meta, "lock"), os.O_RDWR | os.O_CREAT, 0o600)
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
                    raise StoreError("another fetchsync is writing to %s" % self.workspace)
                time.sleep(0.05)
        self._lock_fd = fd
        if os.path.exists(os.path.join(self.meta, BATCH_MARK)):
            # left by a writer that died mid-batch (a live one would hold the
            # lock): its temporaries are garbage now, and only now
            self._clean_temps()
        if self._index_stamp() != self._loaded_stamp:
            self._load_index()  # someone else wrote since we loaded

    def unlock(self) -> None:
        if self._lock_fd >= 0 and not self._open_batches:
            os.close(self._lock_fd)
            self._lock_fd = -1

    # ------------------------------------------------------------------ reading
    def hash_file(self, path: str, entry: Entry) -> str:
        """Content hash of the file at ``path`` (stat-cached)."""
        cached = self.cache.get(path)
        if (cached is not None and cached[0] == entry.size and cached[1] == entry.mtime_ns
                and cached[2] == entry.ctime_ns and cached[3] == entry.ino
                and not self._racy(entry)):
            return cached[4]
        with open(self._resolver.full(path), "rb") as fh:
            digest = hashing.file_digest(self.algorithm, fh).hex()
        self._set_cache(path, [entry.size, entry.mtime_ns, entry.ctime_ns, entry.ino, digest])
        return digest

    @staticmethod
    def _racy(entry: Entry) -> bool:
        # a file modified within the last 2 s may change again without its
        # mtime moving on coarse-timestamp filesystems: do not trust the cache
        return time.time_ns() - entry.mtime_ns < 2_000_000_000

    def listed(self, path: str, entry: Optional[Entry]) -> Optional[M.Listed]:
        if entry is None:
            return None
        if entry.kind == FILE:
            return M.Listed(path, FILE, entry.mode, entry.size, hash=self.hash_file(path, entry))
        if entry.kind == LINK:
            return M.Listed(path, LINK, target=entry.target)
        return M.Listed(path, DIR, entry.mode)

    def written(self, path: str, digest: str) -> Optional[M.Listed]:
        """What stands at ``path`` right after we wrote content with hash ``digest`` there.

        The content was verified against its hash before the rename, so it is
        not read again: the stat cache learns the hash directly.
        """
        entry = stat_path(self._resolver.full(path))
        if entry is None or entry.kind != FILE or not digest:
            return self.listed(path, entry)
        self._set_cache(path, [entry.size, entry.mtime_ns, entry.ctime_ns, entry.ino, digest])
        return M.Listed(path, FILE, entry.mode, entry.size, hash=digest)

    def current(self, path: str) -> Optional[M.Listed]:
        return self.listed(path, stat_path(self._resolver.full(path)))

    def listing(self) -> Tuple[List[M.Listed], List[Tuple[str, str]]]:
        """Everything under the root, with content hashes."""
        result = scan(self.root, self.rules, is_temp=is_temp)
        out = []
        live = set()
        for path, entry in result.entries.items():
            try:
                item = self.listed(path, entry)
            except OSError:
                continue  # vanished or unreadable: it is reported as skipped
            if item is not None:
                out.append(item)
                live.add(path)
        for path in [p for p in self.cache if p not in live]:
            self._set_cache(path, None)
        out.sort(key=lambda x: x.path)
        return out, result.skipped

    def drift(self) -> Tuple[List[M.Listed], List[str]]:
        """What differs on disk from what was last synced: (changed or new, gone).

        This runs on every push, so unchanged entries cost a stat comparison
        against the cache and nothing more.
        """
        entries = self._current_entries()
        racy_before = time.time_ns() - 2_000_000_000
        synced, cache = self.synced, self.cache
        changed = []
        for path, e in entries.items():
            rec = synced.get(path)
            if e.kind == FILE:
                c = cache.get(path)
                if (c is not None and c[0] == e.size and c[1] == e.mtime_ns and c[2] == e.ctime_ns
                        and c[3] == e.ino and e.mtime_ns < racy_before):
                    digest = c[4]
                else:
                    try:
                        digest = self.hash_file(path, e)
                    except OSError:
                        continue  # vanished or unreadable while we looked
                if rec is not None and rec[0] == FILE and rec[2] == digest and rec[1] == e.mode:
                    continue
                changed.append(M.Listed(path, FILE, e.mode, e.size, hash=digest))
            elif e.kind == LINK:
                if rec is not None and rec[0] == LINK and rec[2] == e.target:
                    continue
                changed.append(M.Listed(path, LINK, target=e.target))
            else:
                if rec is not None and rec[0] == DIR and rec[1] == e.mode:
                    continue
                changed.append(M.Listed(path, DIR, e.mode))
        gone = [p for p in synced if p not in entries]
        return changed, gone

    def watch(self) -> bool:
        """Scan now and keep the scan current with inotify, for a later :meth:`drift`."""
        from fetchsync.protocol.watched import Unavailable, WatchedTree
        try:
            tree = WatchedTree(self.root, self.rules, is_temp)
        except (Unavailable, OSError):
            return False
        if tree.watch.lost:  # over the user's inotify watch limit: give them back
            tree.close()
            return False
        self.watched = tree
        return True

    def _current_entries(self) -> Dict[str, Entry]:
        tree = self.watched
        if tree is not None:
            if tree.refresh():
                return tree.entries
            tree.close()
            self.watched = None
        return scan(self.root, self.rules, is_temp=is_temp).entries

    @staticmethod
    def _matches(item: M.Listed, rec: List[Any]) -> bool:
        kind, mode, extra = rec
        if item.kind != kind:
            return False
        if kind == FILE:
            return item.hash == extra and item.mode == mode
        if kind == LINK:
            return item.target == extra
        return item.mode == mode

    def _record(self, path: str, item: Optional[M.Listed]) -> None:
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

    def adopt(self, items: List[M.Listed]) -> int:
        """Record ``items`` as synced where the disk still holds exactly them."""
        n = 0
        for item in items:
            cur = self.current(item.path)
            if cur is not None and self._matches(cur, [item.kind, item.mode, item.hash or item.target]):
                self._record(item.path, cur)
                n += 1
        self.gen += 1
        self._dirty = True
        return n

    def signature(self, path: str) -> Tuple[bytes, str]:
        """The delta signature of the file at ``path``, and its content hash."""
        full = self._resolver.full(path)
        entry = stat_path(full)
        if entry is None or entry.kind != FILE:
            raise PathError("%r is not a regular file" % path)
        with open(full, "rb") as fh:
            data = fh.read()
        digest = hashing.digest(self.algorithm, data).hex()
        from fetchsync.protocol import delta as delta_mod  # see _write_file

        return delta_mod.signature(data, algorithm=self.algorithm).to_bytes(), digest

    def read(self, path: str, *, sig: Optional[bytes] = None, offset: int = 0,
             length: int = -1) -> Tuple[M.Listed, str, bytes]:
        """Content of a file: (what it is, "data" or "delta", payload)."""
        full = self._resolver.full(path)
        entry = stat_path(full)
        if entry is None or entry.kind != FILE:
            raise PathError("%r is not a regular file" % path)
        item = self.listed(path, entry)
        assert item is not None
        with open(full, "rb") as fh:
            if sig is not None:
                from fetchsync.protocol import delta as delta_mod  # see _write_file

                base_sig = delta_mod.Signature.from_bytes(sig)
                return item, M.SRC_DELTA, delta_mod.encode_delta(delta_mod.delta(fh.read(), base_sig))
            fh.seek(offset)
            return item, M.SRC_DATA, fh.read() if length < 0 else fh.read(length)

    # ------------------------------------------------------------------ writing
    def apply(self, ops: List[M.Op], blob: bytes, *, policy: str = "preserve",
              zpart: Optional[List[int]] = None,
              unpacked: Optional[Tuple[bytes, Any]] = None) -> List[M.Result]:
        """Apply ``ops`` in order; one result each. Per-file failures are results.

        ``zpart`` = [compressed length, length] says the blob starts with one
        zlib stream, which operations flagged ``z`` address once inflated.
        """
        return self.finish(self.begin(ops, blob, policy=policy, zpart=zpart, unpacked=unpacked))

    def begin(self, ops: List[M.Op], blob: bytes, *, policy: str = "preserve",
              zpart: Optional[List[int]] = None,
              unpacked: Optional[Tuple[bytes, Any]] = None, join: bool = True) -> "_Batch":
        """The first half of :meth:`apply`: run ``ops``, their content written to
        temporaries; nothing is renamed into place until :meth:`finish`.

        A batch begun while another awaits its ``finish`` must not touch the
        paths that one will rename (see :meth:`_Batch.blocks`). ``join=False``
        returns while its large files may still be written by a second thread:
        the caller calls the batch's ``join_writes`` before anything else of it.
        """
        if unpacked is not None:  # the blob's compressed part, inflated while it waited
            packed, blob = unpacked
        elif zpart is not None:
            packed, blob = unpack_zpart(blob, zpart)
        else:
            packed = b""
        batch = _Batch(self, blob, policy)
        batch.zpart = packed
        if not self._open_batches:
            with open(os.path.join(self.meta, BATCH_MARK), "wb"):
                pass
        self._open_batches += 1
        batch.ops = ops
        try:
            batch.results = [batch.run(op) for op in ops]
        except BaseException:
            batch.join_writes()
            self._close(batch)
            raise
        if join:
            batch.join_writes()
        self.gen += 1
        batch.gen = self.gen
        self._dirty = True
        return batch

    def finish(self, batch: "_Batch", *, synced: bool = False, durable: bool = True) -> List[M.Result]:
        """Rename a begun batch's temporaries into place; its results, completed.

        ``synced``: a syncfs begun after :meth:`begin` returned has completed
        (:meth:`sync_in_background`), so the temporaries are durable already.
        ``durable=False`` leaves the renames to the next syncfs: the caller
        must not report them before one completes.
        """
        try:
            batch.commit(batch.results, synced=synced, durable=durable)
        finally:
            self._close(batch)
        self._dirty = True
        self._prune_trash()
        return batch.results

    def _close(self, batch: "_Batch") -> None:
        batch.cleanup()
        self._open_batches -= 1
        if not self._open_batches:
            try:
                os.unlink(os.path.join(self.meta, BATCH_MARK))
            except FileNotFoundError:
                pass

    def sync(self) -> None:
        """Make everything written so far durable."""
        rootfd = os.open(self.root, os.O_RDONLY)
        try:
            syncfs(rootfd)
        finally:
            os.close(rootfd)

    def sync_in_background(self, batch: "Optional[_Batch]" = None) -> "_BackgroundSync":
        """:meth:`sync` in a thread, so the next batch's files are written meanwhile;
        after ``batch``'s large files are written, when it was begun without joining them."""
        if batch is None:
            return _BackgroundSync(self.sync)

        def run() -> None:
            batch.join_writes()
            self.sync()
        return _BackgroundSync(run)

    def stamp(self) -> str:
        return "%s-%06d" % (time.strftime("%Y%m%d-%H%M%S"), self.gen + 1)

    def _aside(self, path: str, where: str) -> Tuple[str, str]:
        """Where ``path`` goes in ``.fetchsync/<where>/<stamp>/``: (full path, path to show)."""
        rel = os.path.join(where, self.stamp(), path)
        dest = os.path.join(self.meta, rel)
        os.makedirs(os.path.dirname(dest), exist_ok=True)
        shown = os.path.join(META, rel) if self.meta == os.path.join(self.workspace, META) else dest
        return dest, shown

    def _set_aside(self, path: str, where: str) -> str:
        """Move what stands at ``path`` to ``.fetchsync/<where>/<stamp>/path``."""
        dest, shown = self._aside(path, where)
        src = self._resolver.full(path)
        try:
            os.rename(src, dest)
        except OSError as exc:
            if exc.errno != errno.EXDEV:
                raise
            import shutil
            if os.path.isdir(src) and not os.path.islink(src):
                shutil.copytree(src, dest, symlinks=True)
                shutil.rmtree(src)
            else:
                shutil.copy2(src, dest, follow_symlinks=False)
                os.unlink(src)
        self._resolver.forget(path)
        if where == "trash":
            top = os.path.join(where, self.stamp())
            if not self.trash_log or self.trash_log[-1][0] != top:
                self.trash_log.append([top, 0])
            self.trash_log[-1][1] += _fsize(dest) if os.path.isdir(dest) else os.lstat(dest).st_size
        return shown

    def _keep_copy(self, path: str, where: str) -> str:
        """Like _set_aside, but the file stays where it is too (a hard link, else a copy)."""
        dest, shown = self._aside(path, where)
        src = self._resolver.full(path)
        try:
            os.link(src, dest)
        except OSError:
            import shutil
            shutil.copy2(src, dest, follow_symlinks=False)
        return shown

    def _prune_trash(self) -> None:
        total = sum(n for _d, n in self.trash_log)
        while self.trash_log and (len(self.trash_log) > TRASH_KEEP_BATCHES or total > TRASH_KEEP_BYTES):
            top, n = self.trash_log.pop(0)
            _rmtree(os.path.join(self.meta, top), ignore_errors=True)
            total -= n
            self._dirty = True

    def unsynced_below(self, path: str) -> List[str]:
        """Files under directory ``path`` that differ from what was last synced."""
        out = []
        top = self._resolver.full(path)
        for dirpath, dirs, files in os.walk(top):
            for name in files + [d for d in dirs if os.path.islink(os.path.join(dirpath, d))]:
                full = os.path.join(dirpath, name)
                rel = os.path.relpath(full, self.root).replace(os.sep, "/")
                try:
                    cur = self.current(rel)
                except OSError:
                    continue
                rec = self.synced.get(rel)
                if cur is not None and (rec is None or not self._matches(cur, rec)):
                    out.append(rel)
        return out


class _Batch:
    """One apply() call: temporaries first, one syncfs, renames, one syncfs."""

    def __init__(self, store: Store, blob: bytes, policy: str) -> None:
        self.s = store
        self.blob = blob
        self.policy = policy
        self.renames = []  # type: List[Tuple[str, str, str, int, str]]  # (tmp, final, path, result index, hash)
        self.zpart = b""
        self.n = 0
        self.changed = False  # an operation other than an upload part may have changed the tree
        self.ops = []  # type: List[M.Op]
        self.results = []  # type: List[M.Result]
        self.gen = 0  # the store's generation once this batch is applied
        # directories made lately and the files written into them: the store's, see _check
        self.made = store.made
        self.writes = None  # type: Optional[_Writes]

    def _blob(self, op: M.Op) -> bytes:
        return bytes(self._view(op))

    def _view(self, op: M.Op) -> memoryview:
        """The operation's data, not copied (hashed and written as it lies in the request)."""
        off, length = op.blob
        data = self.zpart if op.z else self.blob
        if off + length > len(data):
            raise ProtocolError("operation on %r points past the request's data" % op.path)
        return memoryview(data)[off:off + length]

    def run(self, op: M.Op) -> M.Result:
        idx = self.n
        self.n += 1
        if op.kind != M.UPLOAD:
            self.changed = True
        try:
            return self._run(op, idx)
        except PathError as exc:
            return M.Result(M.PATH_ERROR, str(exc))
        except DeltaError as exc:
            return M.Result(M.BASE_MISMATCH, "delta does not apply: %s" % exc)
        except OSError as exc:
            return _os_error(op, exc)

    def _move_aside(self, path: str, where: str) -> str:
        self.made.clear()
        return self.s._set_aside(path, where)

    def _check(self, op: M.Op) -> Tuple[Optional[M.Listed], str]:
        """Compare what stands at op.path with op.expect; preserve or refuse on mismatch.

        Returns what now stands there and where a conflicting version went.
        """
        i = op.path.rfind("/")
        if i > 0 and op.path not in self.made:
            made = self.made.get(op.path[:i])
            if made is not None and time.monotonic() - made < MADE_FOR:
                # in a directory this endpoint made empty moments ago, at a path
                # it has not written since: what the lstat below would find is
                # what a concurrent writer could add between it and the rename
                # as well, so it is not asked for (an initial push's files, in
                # the directories its first batch made). The map is emptied when
                # anything is moved aside, which may take one of them with it,
                # and when another writer was here (Store._load_index).
                return None, ""
        cur = self.s.current(op.path)
        if cur is None:
            return None, ""  # nothing here: nothing to lose
        if cur.kind == DIR:
            if op.kind in (M.MKDIR, M.CHMOD):
                return cur, ""  # the directory stays
            # it will be replaced or deleted: its files edited here are kept
            # apart from the bounded trash, one by one
            unsynced = self.s.unsynced_below(op.path)
            if not unsynced:
                return cur, ""
            if self.policy == "refuse":
                raise _Refused("%s was changed here since the last sync" % unsynced[0])
            where = ""
            for path in unsynced:
                where = self._move_aside(path, "conflicts")
            return cur, where[: len(where) - len(unsynced[-1])] + op.path
        if op.kind == M.CHMOD or cur.expectation() == op.expect:
            return cur, ""
        if self.policy == "refuse":
            raise _Refused("%s was changed here since the last sync" % op.path)
        if cur.kind == FILE and op.kind == M.WRITE and op.source == M.SRC_DELTA and op.base == cur.hash:
            # the delta was made against exactly this version: keep it by a
            # link (the rename below replaces only the directory entry) and
            # patch from it
            return cur, self.s._keep_copy(op.path, "conflicts")
        where = self._move_aside(op.path, "conflicts")
        self.s._forget_below(op.path)
        return None, where

    def _run(self, op: M.Op, idx: int) -> M.Result:
        s = self.s
        if op.kind == M.UPLOAD:
            part = os.path.join(s.meta, "tmp", "upload-" + op.upload)
            s._uploads.add(part)
            fd = os.open(part, os.O_WRONLY | os.O_CREAT, 0o600)
            try:
                os.lseek(fd, op.size, os.SEEK_SET)
                _write_large(fd, self._view(op))
            finally:
                os.close(fd)
            return M.Result()
        if TEMP_MARK in op.path and any(is_temp(part) for part in op.path.split("/")):
            # our temporaries' names: never synced, and removed by the cleanup
            raise PathError("%r uses a name reserved for fetchsync's temporaries" % op.path)
        s._resolver.check_parents(op.path)
        try:
            cur, preserved = self._check(op)
        except _Refused as exc:
            return M.Result(M.CONFLICT, str(exc))
        full = s._resolver.full(op.path)
        if op.kind == M.DELETE:
            if cur is not None:
                self._move_aside(op.path, "trash")
                s._forget_below(op.path)
            s._record(op.path, None)
            return M.Result(preserved=preserved)
        if op.kind == M.MKDIR:
            if cur is not None and cur.kind != DIR:
                self._move_aside(op.path, "trash")
                cur = None
            if cur is None:
                os.mkdir(full, op.mode or 0o755)
                self.made[op.path] = time.monotonic()
                item = s.current(op.path)  # made with the mode asked, unless umask or setgid say otherwise
                if item is not None and item.kind == DIR:
                    s._resolver.known_dir(op.path)  # its files' parent needs no lstat of its own
            if cur is not None or item is None or item.mode != (op.mode or 0o755):
                os.chmod(full, op.mode or 0o755)
                item = s.current(op.path)
            s._record(op.path, item)
            return M.Result(preserved=preserved, written=item.to_wire() if item else None)
        if op.kind == M.CHMOD:
            if cur is None or cur.kind == LINK:
                return M.Result(M.IO_ERROR, "%s: nothing to chmod" % op.path)
            os.chmod(full, op.mode)
            item = s.current(op.path)
            s._record(op.path, item)
            return M.Result(preserved=preserved, written=item.to_wire() if item else None)
        if cur is not None and cur.kind == DIR:
            # a directory becomes a file or link: the old tree goes to the trash
            self._move_aside(op.path, "trash")
            s._forget_below(op.path)
            cur = None
        parent_dir = os.path.dirname(full)
        tmp = os.path.join(parent_dir, _temp_name(os.path.basename(full)))
        if op.kind == M.SYMLINK:
            os.symlink(op.target, tmp)
        else:
            # written here, in this thread: a pool of writers made threads
            # creating files in one directory spin on its lock in the kernel,
            # and cost more CPU than it saved (measured on a 7,000-file push)
            try:
                self._write_file(op, cur, tmp, idx)
            except (DeltaError, OSError):
                raise  # the operation's result, made by run()
            except Exception as exc:  # say, a malformed delta: this operation's failure only
                return M.Result(M.IO_ERROR, "%s: %s" % (op.path, exc))
        self.renames.append((tmp, full, op.path, idx, op.hash if op.kind == M.WRITE else ""))
        return M.Result(preserved=preserved)

    def _write_file(self, op: M.Op, cur: Optional[M.Listed], tmp: str, idx: int) -> None:
        s = self.s
        if op.source == M.SRC_UPLOAD:
            part = os.path.join(s.meta, "tmp", "upload-" + op.upload)
            os.chmod(part, op.mode or 0o644)
            with open(part, "rb") as fh:
                got = hashing.file_digest(s.algorithm, fh).hex()
            if got != op.hash:
                os.unlink(part)
                raise OSError(errno.EIO, "uploaded content does not match its hash")
            os.rename(part, tmp)
            s._uploads.discard(part)
            return
        if op.source == M.SRC_DATA:
            data = self._view(op)  # type: Any
        elif op.source == M.SRC_DELTA:
            if cur is None or cur.kind != FILE or cur.hash != op.base:
                raise DeltaError("the file here is not the delta's base")
            with open(s._resolver.full(op.path), "rb") as fh:
                base = fh.read()
            # imported when first needed: ~4 ms of every endpoint start, on the critical
            # path of an initial push, which sends no delta
            from fetchsync.protocol import delta as delta_mod

            data = delta_mod.patch(base, delta_mod.decode_delta(self._blob(op), max_size=op.size))
        else:  # copy
            src = s.current(op.from_path)
            if src is None or src.kind != FILE or src.hash != op.base:
                raise DeltaError("the copy's source %r is not what was expected" % op.from_path)
            with open(s._resolver.full(op.from_path), "rb") as fh:
                data = fh.read()
        if len(data) != op.size or hashing.digest(s.algorithm, data).hex() != op.hash:
            raise DeltaError("reconstructed content does not match its hash")
        mode = op.mode or 0o644
        fix = mode if mode & _umask() or mode & ~0o777 else None  # else open() makes it so
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
        if len(data) >= WRITE_APART:
            if self.writes is None:
                self.writes = _Writes()
            self.writes.put(fd, data, fix, tmp, idx)
            return
        try:
            _write_all(fd, data)
            if fix is not None:
                os.fchmod(fd, fix)
        except BaseException:
            os.close(fd)
            os.unlink(tmp)
            raise
        os.close(fd)

    def join_writes(self) -> None:
        """Wait for the large files' content; a write that failed fails its operation."""
        writes, self.writes = self.writes, None
        self.blob = self.zpart = b""  # written: the request's data may go
        if writes is None:
            return
        failed = writes.join()
        if failed:
            self.renames = [r for r in self.renames if r[3] not in failed]
            for idx, exc in failed.items():
                if idx < len(self.results):  # else the batch failed as a whole
                    self.results[idx] = _os_error(self.ops[idx], exc)

    def commit(self, results: List[M.Result], *, synced: bool = False, durable: bool = True) -> None:
        if not self.changed:
            return  # upload parts only: nothing is reported written yet
        rootfd = os.open(self.s.root, os.O_RDONLY)
        made = self.made
        try:
            if self.renames and not synced:
                syncfs(rootfd)  # the temporaries' content, before any is renamed into place
            for tmp, full, path, idx, digest in self.renames:
                try:
                    os.rename(tmp, full)
                except OSError as exc:
                    # say, a directory made at that path later in the batch: the
                    # temporary must not stay behind
                    results[idx] = M.Result(M.IO_ERROR, "%s: %s" % (path, exc.strerror))
                    try:
                        os.unlink(tmp)
                    except OSError:
                        pass
                    continue
                if made and path.rpartition("/")[0] in made:
                    made[path] = 0.0  # ours now: a later operation on it looks at it
                item = self.s.written(path, digest)
                self.s._record(path, item)
                results[idx] = M.Result(results[idx].code, results[idx].message, results[idx].preserved,
                                        item.to_wire() if item else None)
            self.renames = []
            if durable:
                syncfs(rootfd)
        finally:
            os.close(rootfd)

    def blocks(self, ops: List[M.Op]) -> bool:
        """Whether ``ops``, begun before this batch's renames, could see or change
        what they will rename: the same path, a path under one (a file that becomes
        a directory), a directory above one that is replaced or deleted, a copy's
        source. Uploads write only to the upload area."""
        pending = set(r[2] for r in self.renames)
        if not pending:
            return False
        above = set()  # type: set
        for path in pending:
            above.update(paths.ancestors(path))
        for op in ops:
            if op.kind == M.UPLOAD:
                continue
            if op.path in pending or (op.path in above and op.kind not in (M.MKDIR, M.CHMOD)) \
                    or (op.from_path and op.from_path in pending) \
                    or any(a in pending for a in paths.ancestors(op.path)):
                return True
        return False

    def cleanup(self) -> None:
        for tmp, _full, _path, _idx, _digest in self.renames:
            try:
                os.unlink(tmp)
            except OSError:
                pass


class _Refused(Exception):
    pass


class _BackgroundSync:
    """``sync()`` run in a thread (the syncfs call lets go of the GIL meanwhile)."""

    def __init__(self, sync: Any) -> None:
        self._sync = sync
        self._done = threading.Event()
        self._error = None  # type: Optional[BaseException]
        threading.Thread(target=self._run, name="fetchsync-syncfs", daemon=True).start()

    def _run(self) -> None:
        try:
            self._sync()
        except BaseException as exc:  # raised by wait(): nothing is reported unsynced
            self._error = exc
        finally:
            self._done.set()

    def wait(self) -> None:
        self._done.wait()
        if self._error is not None:
            raise self._error


def _os_error(op: M.Op, exc: OSError) -> M.Result:
    code = M.NO_SPACE if exc.errno in (errno.ENOSPC, errno.EDQUOT) else M.IO_ERROR
    return M.Result(code, "%s: %s" % (op.path or op.upload, exc.strerror or exc))


class _Writes:
    """A batch's large files, written to their temporaries by a second thread while the
    serving thread goes on with the batch's other operations (``os.write`` lets go of
    the GIL). The robot's serving thread is a push's critical path, and copying the
    content into the page cache was a third of its time; small files stay on it (a
    pool of writers creating files in one directory cost more than it saved)."""

    def __init__(self) -> None:
        self._jobs = []  # type: List[Any]
        self._cond = threading.Condition()
        self._failed = {}  # type: Dict[int, OSError]
        self._thread = threading.Thread(target=self._run, name="fetchsync-write", daemon=True)
        self._thread.start()

    def put(self, fd: int, data: Any, fix: Optional[int], tmp: str, idx: int) -> None:
        with self._cond:
            self._jobs.append((fd, data, fix, tmp, idx))
            self._cond.notify()

    def join(self) -> Dict[int, OSError]:
        """Wait for every write; the failed ones by operation index (their temporaries removed)."""
        self.put(-1, b"", None, "", -1)
        self._thread.join()
        return self._failed

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._jobs:
                    self._cond.wait()
                fd, data, fix, tmp, idx = self._jobs.pop(0)
            if fd < 0:
                return
            try:
                _write_large(fd, data)
                if fix is not None:
                    os.fchmod(fd, fix)
            except OSError as exc:
                self._failed[idx] = exc
            except BaseException as exc:  # noqa: BLE001  (this thread must not die with fds open)
                self._failed[idx] = OSError(errno.EIO, str(exc))
            finally:
                os.close(fd)
            if idx in self._failed:
                try:
                    os.unlink(tmp)
                except OSError:
                    pass


_direct_buffers = []  # type: List[Any]  # aligned buffers not in use (see _write_large)
_direct_lock = threading.Lock()


def _write_large(fd: int, data: Any) -> None:
    """Write a large file's content (or a piece of it) to ``fd``, at its offset, around the
    page cache.

    Copying a file's content into the page cache and writing it back costs the
    robot's CPUs about as much as everything else a push of large files does
    (100 MB here: 0.25 CPU-s buffered and flushed, 0.02 CPU-s direct; the disk's
    own DMA does the rest). Its content must reach the disk before the rename
    anyway (the batch's syncfs, which then only flushes the metadata and the
    disk's cache). The part of whole blocks goes with O_DIRECT from an aligned
    buffer; the tail, and everything on a file system that refuses O_DIRECT
    (tmpfs, ...) or at an unaligned offset, through the page cache."""
    view = memoryview(data)
    whole = len(view) - len(view) % DIRECT_ALIGN
    done = 0
    if _O_DIRECT and whole:
        flags = fcntl.fcntl(fd, fcntl.F_GETFL)
        try:
            fcntl.fcntl(fd, fcntl.F_SETFL, flags | _O_DIRECT)
        except OSError:
            whole = 0  # not on this file system
        if whole:
            with _direct_lock:
                buf = _direct_buffers.pop() if _direct_buffers else None
            try:
                if buf is None:
                    buf = mmap.mmap(-1, DIRECT_PIECE)
                while done < whole:
                    n = min(DIRECT_PIECE, whole - done)
                    buf[:n] = view[done:done + n]
                    try:
                        wrote = os.write(fd, memoryview(buf)[:n])
                    except OSError as exc:
                        if exc.errno != errno.EINVAL:
                            raise
                        break  # the file system took the flag but not the write: the page cache
                    done += wrote
                    if wrote != n:
                        break  # a short write (a full disk): the rest says why, through the page cache
            finally:
                fcntl.fcntl(fd, fcntl.F_SETFL, flags)
                if buf is not None:
                    with _direct_lock:
                        _direct_buffers.append(buf)
    _write_all(fd, view[done:])


def _write_all(fd: int, data: Any) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]
