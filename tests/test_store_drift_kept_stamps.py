"""A kept listing's drift (Store.drift, looking again only at what moved) reports a robot-
side edit that keeps the file's size and puts its mtime back (``touch -r``, ``cp -p``,
``rsync -t``), also made by renaming another file over it with the same stamps: only the
ctime (and for a rename the inode) moved, and inotify's event is all the kept walk has
besides its restat. Each drift is compared with a fresh Store's."""

from __future__ import annotations

import os
import random
import time
from pathlib import Path

from test_resident_keptscan import make_tree
from test_store_drift_kept import OLD, _drift, _kept_store, _settle

from fetchsync.protocol.store import RACY_NS


def _files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file() and not p.is_symlink())


def test_a_same_size_edit_with_its_stamps_put_back_is_reported(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    root = ws / "src"
    make_tree(root, random.Random(7))
    _settle(root)
    time.sleep(RACY_NS / 1e9 + 0.1)  # ctimes settled too: the hashes are cached
    store = _kept_store(ws)
    try:
        victims = [p for p in _files(root) if p.stat().st_size > 4][:2]
        in_place, renamed = victims
        before = in_place.stat()
        data = in_place.read_bytes()
        in_place.write_bytes(bytes([data[0] ^ 1]) + data[1:])  # same size
        os.utime(in_place, ns=(before.st_atime_ns, before.st_mtime_ns))
        before = renamed.stat()
        data = renamed.read_bytes()
        other = renamed.with_name(".swap")
        other.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
        os.utime(other, ns=(before.st_atime_ns, before.st_mtime_ns))
        os.rename(other, renamed)
        changed, _gone = _drift(store, ws)  # == a fresh Store's
        rel = {p.relative_to(root).as_posix() for p in victims}
        assert rel <= {x[0] if isinstance(x, list) else x.path for x in changed}, changed
        # and again, settled: found unchanged from then on
        for p in victims:
            os.utime(p, (OLD, OLD))
        _drift(store, ws)
    finally:
        store.close()
