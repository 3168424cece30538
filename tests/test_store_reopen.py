"""A re-open of the same workspace in one endpoint session keeps its Store only when
that is exactly what a fresh open would load.

The resident and the watch agent keep one robot endpoint across pushes and open the
workspace again at each push; the endpoint then keeps its Store instead of reading the
index again (Server.do_open). Another endpoint (a push from another laptop or process,
a ``fetchsync pull``) may write the store between two pushes: the kept Store must see
it (Store.lock compares the index files with the ones it loaded or saved last, held
open so their inodes cannot be reused). Checked with two real endpoints (the ``local``
robot) alternating on one robot tree, and in-process for which Store is kept.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from fetchsync.link import client as C
from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.protocol import hashing, wire
from fetchsync.protocol import messages as M
from fetchsync.protocol.ignore import build_rules
from fetchsync.protocol.server import Server
from fetchsync.protocol.store import Store

ALG = "blake2b-128"


def _write(path: str, data: bytes, expect: str, alg: str = ALG) -> M.Op:
    return M.Op(
        M.WRITE,
        path,
        expect=expect,
        mode=0o644,
        hash=hashing.digest(alg, data).hex(),
        size=len(data),
        source=M.SRC_DATA,
        blob=(0, len(data)),
    )


def test_two_endpoints_alternating_each_see_the_others_writes(tmp_path: Path) -> None:
    home = tmp_path / "robot-home"
    conns = [Connection.open(LocalTransport(home)) for _ in range(2)]
    try:
        ends = [C.Endpoint(c) for c in conns]
        rules = build_rules()
        src = home / "ws" / "src"
        last: tuple[str, int] | None = None
        content = {"f": b""}
        for rnd in range(8):
            me = ends[rnd % 2]
            opened = me.open("~/ws", rules=rules)  # from the third round on: a re-open
            if last is not None:
                # the other endpoint's batch is seen: its generation, and its writes
                # recorded as synced (a stale index would list them as the robot's drift)
                assert (opened.epoch, opened.gen) == last
            listing = me.listing(since=(opened.epoch, opened.gen))
            if last is not None:
                assert not listing.drifted, (rnd, listing)
            data = b"round %d\n" % rnd
            alg = me.algorithm
            expect = M.expect_file(hashing.digest(alg, content["f"]).hex()) if rnd else M.ABSENT
            ops = [
                M.Op(M.MKDIR, f"d{rnd}", expect=M.ABSENT, mode=0o755),
                _write("f", data, expect, alg),
            ]
            applied = me.sync(
                ops, policy="preserve", epoch=opened.epoch, gen=opened.gen, blob_parts=[data]
            )
            assert not applied.stale
            assert all(r.code == M.OK and not r.preserved for r in applied.results), applied
            content["f"] = data
            last = (applied.epoch, applied.gen)
            assert (src / "f").read_bytes() == data
        # a robot-side edit between two pushes is still the drift it was
        (src / "f").write_bytes(b"edited on the robot\n")
        opened = ends[0].open("~/ws", rules=rules)
        listing = ends[0].listing(since=(opened.epoch, opened.gen))
        assert [e.path for e in listing.entries] == ["f"] and not listing.full
    finally:
        for c in conns:
            c.close()


class _Null:
    def write(self, data: bytes) -> None:
        pass

    def flush(self) -> None:
        pass


def _server() -> Server:
    srv = Server(None, _Null())  # type: ignore[arg-type]
    srv.algorithm = ALG
    return srv


def _ask(srv: Server, header: dict[str, Any], blob: bytes = b"") -> dict[str, Any]:
    frame = srv.dispatch(wire.Frame(wire.T_REQUEST, 1, header, blob))
    assert frame.type == wire.T_RESPONSE, frame.header
    return frame.header


def test_the_store_is_kept_only_for_the_same_open(tmp_path: Path) -> None:
    ws = str(tmp_path / "ws")
    srv = _server()
    rules = build_rules().to_wire()
    first = _ask(srv, {"op": "open", "workspace": ws, "rules": rules})
    kept = srv.store
    again = _ask(srv, {"op": "open", "workspace": ws, "rules": rules})
    assert srv.store is kept and (again["epoch"], again["gen"]) == (first["epoch"], first["gen"])
    # other options: a new store, as before
    _ask(srv, {"op": "open", "workspace": ws, "rules": None})
    assert srv.store is not kept
    kept = srv.store
    _ask(srv, {"op": "open", "workspace": ws, "readonly": True})
    assert srv.store is not kept
    kept = srv.store
    _ask(srv, {"op": "open", "workspace": ws, "readonly": True})
    assert srv.store is kept
    # a change of its own left unsaved (a request that failed midway): a fresh store
    _ask(srv, {"op": "open", "workspace": ws})
    kept = srv.store
    assert kept is not None
    kept._dirty = True
    _ask(srv, {"op": "open", "workspace": ws})
    assert srv.store is not None and srv.store is not kept
    srv.store.close()


def test_a_kept_store_reloads_an_index_another_endpoint_replaced(tmp_path: Path) -> None:
    """Another writer's snapshot (not only a journal record) between two opens: the kept
    store reads it, epoch and records, as a fresh one would."""
    ws = str(tmp_path / "ws")
    ours, theirs = _server(), _server()
    _ask(ours, {"op": "open", "workspace": ws})
    _ask(theirs, {"op": "open", "workspace": ws})
    opened = _ask(theirs, {"op": "list", "mode": "full"})
    data = b"theirs\n"
    op = _write("g", data, M.ABSENT)
    header: dict[str, Any] = {"op": "sync", "ops": [op.to_wire()], "policy": "preserve"}
    header.update(epoch=opened["epoch"], gen=opened["gen"], require_fresh=True)
    synced = _ask(theirs, header, data)
    assert theirs.store is not None
    theirs.store.lock()
    theirs.store._write_snapshot()  # the journal folded: new index and journal files
    theirs.store.unlock()
    again = _ask(ours, {"op": "open", "workspace": ws})
    assert (again["epoch"], again["gen"]) == (synced["epoch"], synced["gen"])
    assert ours.store is not None and ours.store.synced.get("g") is not None
    # it holds the files it loaded now (their inodes cannot go to another file)
    ours.store.lock()
    assert ours.store._held_stamp() == ours.store._index_stamp()
    ours.store.unlock()
    ours.store.close()
    theirs.store.close()


def test_a_store_dropped_without_close_gives_its_descriptors_back(tmp_path: Path) -> None:
    """The laptop's pull only unlocks its Store: the index files it holds (and a kept
    listing's inotify descriptor) go with it, not at the process's end."""
    import gc

    ws = str(tmp_path / "ws")
    fds = len(os.listdir("/proc/self/fd"))
    for _ in range(20):
        store = Store(ws, algorithm=ALG)
        store.keep_listing()
        store.lock()
        store.drift()
        store.save_index()
        store.unlock()
        del store
    gc.collect()
    assert len(os.listdir("/proc/self/fd")) <= fds
