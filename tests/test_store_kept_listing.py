"""A long-lived endpoint's kept listing (fetchsync.protocol.kept) answers exactly what a
fresh walk (tree.scan_fd) and a fresh Store's drift answer, after any mix of changes
made on the robot between two pushes (edits, new and deleted files and directories,
renames, chmods, symlinks, special files, unreadable directories, ignore files,
temporaries), with the endpoint's own writes in between; on the laptop's Python and
through a real Python 3.6 endpoint."""

from __future__ import annotations

import os
import random
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from test_python36 import PY36
from test_resident_keptscan import change, dirs_of, make_tree

import fetchsync
from fetchsync.protocol import hashing, wire
from fetchsync.protocol import kept as kept_mod
from fetchsync.protocol import messages as M
from fetchsync.protocol.ignore import IgnoreRules, build_rules
from fetchsync.protocol.store import Store, is_temp
from fetchsync.protocol.tree import scan_fd

ALG = "blake2b-128"


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


def _unlock_all(root: Path) -> None:
    for d in dirs_of(root) + [p for p in root.rglob("*") if p.is_dir()]:
        d.chmod(0o755)


def _write_op(store: Store, path: str, n: int) -> None:
    """The endpoint's own write of ``path`` (a temporary renamed into place), as a push's."""
    cur = store.current(path)
    data = b"written by a push %d\n" % n
    op = M.Op(
        M.WRITE,
        path,
        expect=M.ABSENT if cur is None else M.expect_file(cur.hash),
        mode=0o644,
        hash=hashing.digest(ALG, data).hex(),
        size=len(data),
        source=M.SRC_DATA,
        blob=(0, len(data)),
    )
    store.apply([op], data)


@pytest.mark.parametrize("seed", range(5))
def test_the_kept_listing_is_what_a_fresh_walk_finds(tmp_path: Path, seed: int) -> None:
    rng = random.Random(seed)
    ws = tmp_path / "ws"
    root = ws / "src"
    make_tree(root, rng)
    store = Store(str(ws), algorithm=ALG, rules=_rules())
    store.keep_listing()
    try:
        store.lock()
        items, _ = store.listing()
        store.adopt(items)
        store.save_index()
        store.unlock()
        done: list[str] = []
        for n in range(50):
            for k in range(rng.randint(1, 3)):
                done.append(change(root, rng, n * 10 + k))
            store.lock()
            assert store.src is not None
            kept = store._scan()
            fresh = scan_fd(store.src.fd, _rules(), is_temp=is_temp)
            assert kept.entries == fresh.entries, done[-3:]
            assert sorted(kept.skipped) == sorted(fresh.skipped), done[-3:]
            changed, gone = store.drift()
            store.save_index()
            store.unlock()
            assert ([x.to_wire() for x in changed], sorted(gone)) == _fresh_drift(ws), done[-3:]
            store.lock()
            if rng.random() < 0.3:  # the push that follows records the robot's tree
                items, _ = store.listing()
                store.adopt(items)
            if rng.random() < 0.4:
                files = [p for p, e in store._scan().entries.items() if e.kind == "f"]
                if files:
                    _write_op(store, rng.choice(files), n)
            store.save_index()
            store.unlock()
        # most listings walked only where something happened
        assert store.kept_tree.full_scans < 35, store.kept_tree.full_scans
    finally:
        _unlock_all(root)
        store.close()


def test_an_edit_relists_only_its_directory_and_a_write_through_a_hard_link_is_seen(
    tmp_path: Path,
) -> None:
    ws = tmp_path / "ws"
    root = ws / "src"
    make_tree(root, random.Random(1))
    outside = tmp_path / "outside"
    os.link(root / "pkg1" / "src" / "f0.cpp", outside)  # a hard link from outside src/
    store = Store(str(ws), algorithm=ALG, rules=_rules())
    store.keep_listing()
    store.lock()
    store.adopt(store.listing()[0])
    store.save_index()
    store.unlock()
    store.lock()
    for n in range(4):
        with open(root / "pkg2" / "src" / "f0.cpp", "a") as fh:
            fh.write(f"{n}\n")
        with open(outside, "a") as fh:  # no event in any watched directory
            fh.write(f"outside {n}\n")
        assert store.src is not None
        fresh = scan_fd(store.src.fd, _rules(), is_temp=is_temp)
        assert store._scan().entries == fresh.entries
        changed, gone = store.drift()
        assert [x.path for x in changed] == ["pkg1/src/f0.cpp", "pkg2/src/f0.cpp"]
        assert ([x.to_wire() for x in changed], gone) == _fresh_drift(ws)
    assert store.kept_tree.full_scans == 1
    store.close()


def test_steps_aside_where_inotify_cannot_see(tmp_path: Path) -> None:
    """Not a local file system, or a mount inside the tree: a full walk every time."""
    ws = tmp_path / "ws"
    make_tree(ws / "src", random.Random(2))
    store = Store(str(ws), algorithm=ALG, rules=_rules())
    store.keep_listing()
    store.lock()
    store.drift()
    store.drift()
    assert store.kept_tree.full_scans == 1
    real = kept_mod.LOCAL_FILE_SYSTEMS
    kept_mod.LOCAL_FILE_SYSTEMS = frozenset()  # as if on NFS
    try:
        store.drift()
        store.drift()
    finally:
        kept_mod.LOCAL_FILE_SYSTEMS = real
    assert store.kept_tree.full_scans == 3
    info = tmp_path / "mountinfo"
    src = os.path.realpath(ws / "src")
    info.write_text(
        f"1 0 8:1 / / rw - ext4 /dev/sda1 rw\n2 1 0:5 / {src}/pkg0 rw - nfs host:/x rw\n"
    )
    with pytest.raises(kept_mod._StepAside):
        kept_mod._check_mounts(src, str(info))
    store.close()


def test_the_watches_are_given_back_when_used_up(tmp_path: Path, monkeypatch: Any) -> None:
    ws = tmp_path / "ws"
    make_tree(ws / "src", random.Random(3))
    store = Store(str(ws), algorithm=ALG, rules=_rules())
    store.keep_listing()
    real = kept_mod._inotify()

    class Limited:
        def __init__(self) -> None:
            self.left = 3
            self.tries = 0

        def inotify_init1(self, flags: int) -> int:
            return int(real.inotify_init1(flags))

        def inotify_add_watch(self, fd: int, path: bytes, mask: int) -> int:
            self.tries += 1
            if self.left <= 0:
                import ctypes

                ctypes.set_errno(28)  # ENOSPC
                return -1
            self.left -= 1
            return int(real.inotify_add_watch(fd, path, mask))

    limited = Limited()
    monkeypatch.setattr(kept_mod, "_inotify", lambda: limited)
    store.lock()
    want = scan_fd(store._root().fd, _rules(), is_temp=is_temp)
    assert store._scan().entries == want.entries
    tries = limited.tries
    assert store.kept_tree.gave_up and store.kept_tree._fd < 0
    assert store._scan().entries == want.entries
    assert limited.tries == tries  # none taken again
    store.close()


# ------------------------------------------------------------------ a real 3.6 endpoint


class _Endpoint:
    def __init__(self, python: str, home: Path) -> None:
        pkg = os.path.dirname(os.path.dirname(fetchsync.__file__))
        env = dict(os.environ, HOME=str(home), PYTHONPATH=pkg)
        self.proc = subprocess.Popen(
            [python, "-c", "from fetchsync.protocol.server import main; main()"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=env,
        )
        assert self.proc.stdout is not None and self.proc.stdin is not None
        self.reader = wire.Reader(self.proc.stdout.read1)  # type: ignore[attr-defined]
        self.reader.read_hello()
        self.proc.stdin.write(wire.encode_hello({"algorithm": ALG}))
        self.proc.stdin.flush()
        self.next_id = 1

    def ask(self, header: dict[str, Any], blob: bytes = b"") -> dict[str, Any]:
        req_id, self.next_id = self.next_id, self.next_id + 1
        assert self.proc.stdin is not None
        frame = wire.Frame(wire.T_REQUEST, req_id, header, blob)
        self.proc.stdin.write(wire.encode_frame(frame))
        self.proc.stdin.flush()
        got = self.reader.read_frame()
        assert got is not None and got.type == wire.T_RESPONSE, got and got.header
        return got.header

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(30)


@pytest.mark.parametrize(
    "python",
    [
        pytest.param(sys.executable, id="laptop"),
        pytest.param(
            PY36,
            id="py36",
            marks=pytest.mark.skipif(
                not os.path.exists(PY36) and not os.environ.get("CI"), reason="no Python 3.6"
            ),
        ),
    ],
)
def test_a_long_lived_endpoint_lists_what_a_fresh_one_lists(tmp_path: Path, python: str) -> None:
    rng = random.Random(7)
    home = tmp_path / "home"
    ws = home / "ws"
    root = ws / "src"
    make_tree(root, rng)
    rules = build_rules(()).to_wire()
    end = _Endpoint(python, home)
    try:
        opened = end.ask({"op": "open", "workspace": str(ws), "rules": rules})
        listing = end.ask({"op": "list", "mode": "full"})
        entries = listing["entries"]
        end.ask({"op": "adopt", "entries": entries})
        done: list[str] = []
        for n in range(30):
            for k in range(rng.randint(1, 3)):
                done.append(change(root, rng, n * 10 + k))
            opened = end.ask({"op": "open", "workspace": str(ws), "rules": rules})
            since = {"epoch": opened["epoch"], "gen": opened["gen"]}
            got = end.ask({"op": "list", "mode": "drift", **since})
            assert not got["full"]
            changed, gone = _fresh_drift(ws)
            assert (got["entries"], sorted(got["gone"])) == (changed, gone), done[-3:]
            if rng.random() < 0.3:
                full = end.ask({"op": "list", "mode": "full"})
                end.ask({"op": "adopt", "entries": full["entries"]})
    finally:
        end.close()
        _unlock_all(root)
    shutil.rmtree(home, ignore_errors=True)
