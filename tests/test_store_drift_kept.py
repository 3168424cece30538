"""Store.drift with a kept listing looks again only at what moved since its last drift
(the kept walk's changed entries, the index rows changed, what it did not find unchanged
last time): on a settled tree (mtimes older than RACY_NS, as a robot's tree is between
two pushes) every drift still answers what a fresh Store's drift answers."""

from __future__ import annotations

import os
import random
import time
from pathlib import Path
from typing import Any

from test_resident_keptscan import change, make_tree

from fetchsync.protocol.ignore import IgnoreRules, build_rules
from fetchsync.protocol.store import FILE, Store

ALG = "blake2b-128"
OLD = time.time() - 3600  # long settled: the inline check trusts the stat cache


def _rules() -> IgnoreRules:
    return IgnoreRules.from_wire(build_rules(()).to_wire())  # as the endpoint gets them


def _fresh_drift(ws: Path) -> tuple[list[Any], list[str]]:
    store = Store(str(ws), algorithm=ALG, rules=_rules(), readonly=True)
    try:
        store.lock()
        changed, gone = store.drift()
        return [x.to_wire() for x in changed], sorted(gone)
    finally:
        store.close()


def _settle(root: Path) -> None:
    """Every path modified in the last RACY_NS and more made older (the others left
    alone: their ctime stays, so the kept walk finds them unchanged)."""
    for dirpath, dirnames, filenames in os.walk(root):
        for name in filenames + dirnames:
            full = os.path.join(dirpath, name)
            if os.lstat(full).st_mtime > OLD + 600:
                os.utime(full, (OLD, OLD), follow_symlinks=False)


def _kept_store(ws: Path) -> Store:
    store = Store(str(ws), algorithm=ALG, rules=_rules())
    store.keep_listing()
    store.lock()
    store.adopt(store.listing()[0])
    store.save_index()
    for _ in range(2):  # the walk, then a kept listing that found every entry unchanged
        assert store.drift() == ([], [])
    return store


def _drift(store: Store, ws: Path) -> tuple[list[Any], list[str]]:
    changed, gone = store.drift()
    store.save_index()
    got = [x.to_wire() for x in changed], sorted(gone)
    assert got == _fresh_drift(ws)
    return got


def test_a_write_through_a_hard_link_to_a_settled_file_is_reported(tmp_path: Path) -> None:
    """No event in any watched directory: only the kept walk's restat sees it move."""
    ws = tmp_path / "ws"
    root = ws / "src"
    make_tree(root, random.Random(3))
    outside = tmp_path / "outside"
    os.link(root / "pkg1" / "src" / "f0.cpp", outside)
    _settle(root)
    store = _kept_store(ws)
    try:
        for n in range(3):
            with open(outside, "a") as fh:
                fh.write(f"outside {n}\n")
            os.utime(outside, (OLD + n + 1, OLD + n + 1))  # settled again, another stat
            changed, _gone = _drift(store, ws)
            assert [c[0] for c in changed] == ["pkg1/src/f0.cpp"]
        assert store.kept_tree.full_scans == 1
    finally:
        store.close()


def test_a_row_changed_under_a_settled_entry_is_looked_at_again(tmp_path: Path) -> None:
    """An index row that changes while its file stays (here: the row dropped, as a
    forget does) makes the next drift look at that file again."""
    ws = tmp_path / "ws"
    root = ws / "src"
    make_tree(root, random.Random(4))
    _settle(root)
    store = _kept_store(ws)
    try:
        files = sorted(p for p, rec in store.synced.items() if rec[0] == FILE)
        store._set_synced(files[0], None)
        store.save_index()
        changed, _gone = _drift(store, ws)
        assert [c[0] for c in changed] == [files[0]]
    finally:
        store.close()


def test_another_endpoints_index_is_looked_at_whole(tmp_path: Path) -> None:
    """Another endpoint's save of the index (a row dropped, its file left): the kept
    store reads the index again, and drifts over every entry again."""
    ws = tmp_path / "ws"
    root = ws / "src"
    make_tree(root, random.Random(6))
    _settle(root)
    store = _kept_store(ws)
    try:
        store.unlock()
        other = Store(str(ws), algorithm=ALG, rules=_rules())
        try:
            other.lock()
            files = sorted(p for p, rec in other.synced.items() if rec[0] == FILE)
            other._set_synced(files[-1], None)
            other.save_index()
            other.unlock()
        finally:
            other.close()
        store.lock()
        changed, _gone = _drift(store, ws)
        assert [c[0] for c in changed] == [files[-1]]
    finally:
        store.close()


def test_random_changes_to_a_settled_tree(tmp_path: Path) -> None:
    """Changes of every kind (test_resident_keptscan.change), each round settled again,
    with the endpoint's own adoption of what it lists now and then."""
    rng = random.Random(5)
    ws = tmp_path / "ws"
    root = ws / "src"
    make_tree(root, rng)
    _settle(root)
    store = _kept_store(ws)
    try:
        for n in range(40):
            for k in range(rng.randint(1, 3)):
                change(root, rng, n * 10 + k)
            _settle(root)
            _drift(store, ws)
            if rng.random() < 0.3:
                store.adopt(store.listing()[0])
                store.save_index()
    finally:
        for d in [root, *(p for p in root.rglob("*") if p.is_dir() and not p.is_symlink())]:
            d.chmod(0o755)
        store.close()
