"""Small text files sent as deflate streams with the content the robot holds as the
dictionary (messages.SRC_ZDICT): the robot's rules (store), and a push's bytes and
fall-backs end to end over the local robot."""

from __future__ import annotations

import sqlite3
import zlib
from pathlib import Path
from typing import Any

import pytest
from helpers import tree_of

from fetchsync.link.client import Endpoint
from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.protocol import hashing
from fetchsync.protocol import messages as M
from fetchsync.protocol.errors import ProtocolError
from fetchsync.protocol.store import Store
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State

ALG = "blake2b-128"


def h(data: bytes) -> str:
    return hashing.digest(ALG, data).hex()


def zd(data: bytes, base: bytes) -> bytes:
    c = zlib.compressobj(9, zlib.DEFLATED, -15, 9, zdict=base)
    return c.compress(data) + c.flush()


def zop(path: str, new: bytes, base: bytes, blob: bytes, **kw: Any) -> M.Op:
    return M.Op(
        M.WRITE,
        path,
        expect=M.expect_file(h(base)),
        mode=0o644,
        hash=h(new),
        size=len(new),
        source=M.SRC_ZDICT,
        base=h(base),
        blob=(0, len(blob)),
        **kw,
    )


@pytest.fixture
def store(tmp_path: Path):
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    yield s
    s.unlock()


V1 = b"".join(b"#include <rclcpp/node_%d.hpp>\n" % i for i in range(300))
V2 = V1.replace(b"node_150.hpp", b"node_150_renamed.hpp")


def test_store_inflates_a_dictionary_write_against_the_file_it_holds(store):
    store.apply([M.Op(M.WRITE, "a.h", expect=M.ABSENT, hash=h(V1), size=len(V1),
                      source=M.SRC_DATA, blob=(0, len(V1)))], V1)  # fmt: skip
    blob = zd(V2, V1)
    assert len(blob) < len(zlib.compress(V2, 9)) // 4
    [r] = store.apply([zop("a.h", V2, V1, blob)], blob)
    assert r.ok and (Path(store.root) / "a.h").read_bytes() == V2


@pytest.mark.parametrize("case", ["other base", "short", "long", "garbage"])
def test_store_refuses_a_dictionary_write_that_does_not_inflate_to_its_content(store, case):
    store.apply([M.Op(M.WRITE, "a.h", expect=M.ABSENT, hash=h(V1), size=len(V1),
                      source=M.SRC_DATA, blob=(0, len(V1)))], V1)  # fmt: skip
    if case == "other base":  # made against content the robot does not hold
        blob, op = zd(V2, V1[::-1]), None
    elif case == "short":
        blob = zd(V2, V1)[:-3]
        op = None
    elif case == "long":  # inflates past the size it claims: stopped at size + 1
        blob = zd(V2 * 30, V1)
        op = None
    else:
        blob, op = b"\xff" * 40, None
    op = op or zop("a.h", V2, V1, blob)
    [r] = store.apply([op], blob)
    assert r.code == M.BASE_MISMATCH
    assert (Path(store.root) / "a.h").read_bytes() == V1


def test_a_dictionary_write_without_a_base_or_too_large_is_a_protocol_error():
    op = zop("a.h", V2, V1, b"x").to_wire()
    del op["b"]
    with pytest.raises(ProtocolError):
        M.Op.from_wire(op)
    big = zop("a.h", V2, V1, b"x").but(size=M.ZDICT_SIZE_MAX + 1).to_wire()
    with pytest.raises(ProtocolError):
        M.Op.from_wire(big)


# ------------------------------------------------------------------ end to end
@pytest.fixture
def pusher(tmp_path: Path):
    src = tmp_path / "ws" / "src"
    (src / "pkg").mkdir(parents=True)
    conns: list[Any] = []
    states: list[State] = []

    def push() -> sync.Report:
        conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
        conns.append(conn)
        state = State(tmp_path / "state.sqlite")
        states.append(state)
        s = sync.Syncer(
            conn, state, local_root=str(src), remote_workspace="~/ws", rules=sync.build_rules()
        )
        report = s.push()
        conn.close()
        state.close()
        return report

    yield src, tmp_path / "robot-home" / "ws" / "src", push, tmp_path / "state.sqlite"


def _edit(src: Path) -> None:
    for name in ("package.xml", "node.cpp"):
        f = src / "pkg" / name
        f.write_bytes(f.read_bytes().replace(b"1.2.3", b"1.2.4"))


def _tree(src: Path) -> None:
    (src / "pkg" / "package.xml").write_bytes(
        b"<package format='3'>\n  <name>pkg</name>\n  <version>1.2.3</version>\n"
        + b"".join(b"  <depend>dep_%d</depend>\n" % i for i in range(40))
        + b"</package>\n"
    )
    (src / "pkg" / "node.cpp").write_bytes(
        b"// version 1.2.3\n"
        + b"".join(
            b"int f%d(int x) { return x * %d + helper(%d); }\n" % (i, i, i) for i in range(400)
        )
    )


def test_an_edit_of_small_text_files_travels_in_tens_of_bytes(pusher):
    """A one-line change of a 1.3 KB package.xml (under SIG_MIN: it went whole) and of a
    19 KB source (a chunk delta: the changed chunk) costs tens of bytes each."""
    src, robot, push, _ = pusher
    _tree(src)
    assert push().errors == []
    _edit(src)
    r = push()
    noop = push()
    assert r.errors == [] and r.files == 2 and r.deltas == 2
    assert tree_of(src) == tree_of(robot)
    # the sync request: its header (two hashes per file) and both files in ~200 bytes
    assert noop.files == 0
    assert r.bytes_sent - noop.bytes_sent < 800  # 1,033 before, the request included


def test_an_older_robot_gets_a_chunk_delta_from_the_kept_content(pusher, monkeypatch):
    src, robot, push, _ = pusher
    _tree(src)
    push()
    monkeypatch.setattr(Endpoint, "zdict", property(lambda self: False))
    _edit(src)
    r = push()
    assert r.errors == [] and r.files == 2
    assert tree_of(src) == tree_of(robot)


def test_kept_content_that_is_not_what_the_robot_holds_steps_aside(pusher):
    """A state whose kept content does not hash to what the robot holds (a damaged or
    foreign state file) is not used: the file goes whole and lands right."""
    src, robot, push, state_file = pusher
    _tree(src)
    push()
    db = sqlite3.connect(state_file)
    lie = sync.BASE_MAGIC + zlib.compress(b"// version 1.2.3\nsomething else entirely\n")
    n = db.execute("UPDATE entries SET sig=? WHERE path=?", (lie, b"pkg/node.cpp")).rowcount
    db.commit()
    db.close()
    assert n == 1
    _edit(src)
    r = push()
    assert r.errors == [] and r.files == 2 and r.rounds == 1
    assert tree_of(src) == tree_of(robot)


def test_a_large_text_files_delta_keeps_its_new_signature(pusher):
    """A text file over 32 KiB goes as a chunk delta; the signature kept for its next edit
    (taken from the delta's own pass) is the new content's."""
    from fetchsync.protocol import delta

    src, robot, push, state_file = pusher
    big = src / "pkg" / "big.cpp"
    big.write_bytes(b"".join(b"int g%d(int x) { return x + %d; }\n" % (i, i) for i in range(3000)))
    push()
    big.write_bytes(b"// a new first line\n" + big.read_bytes())
    r = push()
    assert r.errors == [] and r.deltas == 1 and tree_of(src) == tree_of(robot)
    state = State(state_file)
    try:
        algorithm = state.get("algorithm")
        assert state.signature("pkg/big.cpp") == (
            delta.signature(big.read_bytes(), algorithm=algorithm).to_bytes()
        )
    finally:
        state.close()
