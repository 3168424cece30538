"""Store.drift's inline skip of unchanged entries says what Store._drifted says of each.

drift runs at every push and skips, without a call, a file whose stat cache row matches
its stat (and is not racy) and whose synced record matches the cached hash and mode,
and a directory whose synced record has its mode. Compared here, over random changes
(content, mode, kind, cache rows made stale or racy, records missing), with the plain
loop over every entry that drift was before.
"""

from __future__ import annotations

import os
import random
import time
from pathlib import Path
from typing import Any

import pytest

from fetchsync.protocol import messages as M
from fetchsync.protocol.store import Store
from fetchsync.protocol.tree import FILE

ALG = "blake2b-128"


def _reference(store: Store) -> tuple[list[M.Listed], list[str]]:
    entries = store._scan().entries
    changed = [
        item
        for path, e in entries.items()
        if (item := store._drifted(path, e, store.synced.get(path))) is not None
    ]
    return changed, [p for p in store.synced if p not in entries]


def _key(result: tuple[list[M.Listed], list[str]]) -> tuple[list[Any], list[str]]:
    changed, gone = result
    return sorted(x.to_wire() for x in changed), sorted(gone)


@pytest.mark.parametrize("seed", range(4))
def test_drift_says_what_the_plain_loop_says(tmp_path: Path, seed: int) -> None:
    rnd = random.Random(seed)
    src = tmp_path / "ws" / "src"
    src.mkdir(parents=True)
    names = [f"d{i % 4}/f{i}" for i in range(40)]
    old = time.time() - 3600
    for name in names:
        (src / name).parent.mkdir(exist_ok=True)
        (src / name).write_bytes(b"x" * rnd.randrange(50))
        os.utime(src / name, (old, old))
    store = Store(str(tmp_path / "ws"), algorithm=ALG)
    store.lock()
    items, _ = store.listing()
    store.adopt(items)
    for _round in range(12):
        for name in rnd.sample(names, 6):
            path = src / name
            what = rnd.randrange(7)
            if what == 0 and path.exists():
                path.write_bytes(b"edited %d" % rnd.randrange(1000))
            elif what == 1 and path.exists():
                path.chmod(rnd.choice([0o600, 0o644, 0o755]))
            elif what == 2:
                # same size and times as its cache row, other content: only a racy
                # mtime makes it hashed again (git's racily-clean file)
                if path.exists() and name in store.cache:
                    row = store.cache[name]
                    path.write_bytes(bytes(len(path.read_bytes())).replace(b"\0", b"y"))
                    st = path.stat()
                    store.cache[name] = [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino]
                    store.cache[name].append(row[4])
            elif what == 3 and name in store.cache:
                store.cache[name] = [0, 0, 0, 0, "0" * 32]  # a stale row
            elif what == 4:
                store.synced.pop(name, None)
            elif what == 5 and path.exists():
                path.unlink()
            elif what == 6:
                path.parent.chmod(rnd.choice([0o700, 0o755]))
        got = _key(store.drift())  # first: the plain loop's hashing fills the cache
        assert got == _key(_reference(store))
        if rnd.random() < 0.5:  # the robot's state caught up, as a push leaves it
            items, _ = store.listing()
            store.adopt(items)
            for name in names:
                if (src / name).exists() and rnd.random() < 0.2:
                    os.utime(src / name, (old, old))
                    store.cache.pop(name, None)
    store.close()


def test_a_racy_file_is_hashed_again(tmp_path: Path) -> None:
    """A file rewritten with its size within the mtime its cache row holds: a fresh
    mtime is not trusted, so drift reports the new content."""
    src = tmp_path / "ws" / "src"
    src.mkdir(parents=True)
    (src / "a").write_bytes(b"one")
    store = Store(str(tmp_path / "ws"), algorithm=ALG)
    store.lock()
    items, _ = store.listing()
    store.adopt(items)
    old = next(x.hash for x in items if x.path == "a")  # (a racy hash is not cached)
    (src / "a").write_bytes(b"two")
    st = (src / "a").stat()
    store.cache["a"] = [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, old]
    changed, _gone = store.drift()
    assert [(x.path, x.kind) for x in changed] == [("a", FILE)]
    store.close()
