"""The typed endpoint client (``fetchsync.link.client``) and the transports' capabilities.

The client has one method per request the robot's endpoint serves and checks every
answer as it arrives: a robot that lies about an answer's shape is a ProtocolError,
one line and exit 7 at the CLI, never a traceback. Tested against the real endpoint
(the ``local`` robot), and against one that lies (a Server subclass run in its place).
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import pytest
from helpers import fetchsync, local_env, make_workspace, tree_of, without_where

from fetchsync.errors import ProtocolError, RemoteError
from fetchsync.link import client as C
from fetchsync.link.connection import Connection
from fetchsync.link.transport import Capabilities, LocalTransport
from fetchsync.protocol import messages as M
from fetchsync.protocol import wire
from fetchsync.protocol.ignore import build_rules
from fetchsync.protocol.server import Server

REPO = Path(__file__).resolve().parent.parent


def test_the_client_mirrors_the_servers_requests() -> None:
    served = {name[3:] for name in dir(Server) if name.startswith("do_")}
    assert set(C.REQUESTS) == served
    for name in served - {"bye", "list"}:  # bye: Connection.close; list: Endpoint.listing
        assert callable(getattr(C.Endpoint, name)), name
    assert callable(C.Endpoint.listing)


def test_transports_declare_what_they_can_do() -> None:
    from fetchsync.link.mux import MuxTransport
    from fetchsync.link.ssh import SSHTransport

    assert SSHTransport.capabilities == Capabilities(keepalive=True)
    assert LocalTransport.capabilities == MuxTransport.capabilities == Capabilities()
    for cls in (SSHTransport, LocalTransport, MuxTransport):
        assert callable(cls.is_alive) and callable(cls.exec) and callable(cls.close)


@pytest.fixture
def endpoint(tmp_path: Path):
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    try:
        yield C.Endpoint(conn)
    finally:
        conn.close()


def test_every_request_round_trips_typed(endpoint: C.Endpoint, tmp_path: Path) -> None:
    src = tmp_path / "robot-home" / "ws" / "src"
    opened = endpoint.open("~/ws", rules=build_rules())
    assert opened.workspace == str(tmp_path / "robot-home" / "ws")
    assert isinstance(opened.epoch, str) and isinstance(opened.gen, int) and not opened.readonly
    content = b"line\n" * 5000
    h = endpoint.conn.algorithm
    from fetchsync.protocol import hashing

    digest = hashing.digest(h, content).hex()
    ops = [
        M.Op(M.MKDIR, "pkg", expect=M.ABSENT, mode=0o755),
        M.Op(
            M.WRITE,
            "pkg/a.txt",
            expect=M.ABSENT,
            mode=0o644,
            hash=digest,
            size=len(content),
            source=M.SRC_DATA,
            blob=(0, len(content)),
        ),
    ]
    applied = endpoint.send_sync(
        ops, policy="preserve", epoch=opened.epoch, gen=opened.gen, blob_parts=[content]
    ).wait()
    assert not applied.stale and [r.code for r in applied.results] == [M.OK, M.OK]
    assert (src / "pkg" / "a.txt").read_bytes() == content
    stale = endpoint.send_sync(
        ops, policy="preserve", epoch=opened.epoch, gen=opened.gen, blob_parts=[content]
    ).wait()
    assert stale.stale and stale.results == []

    listing = endpoint.listing()
    assert listing.full and [e.path for e in listing.entries] == ["pkg", "pkg/a.txt"]
    drift = endpoint.listing(since=(applied.epoch, applied.gen))
    assert not drift.drifted and drift.epoch == applied.epoch

    [whole, piece, missing] = endpoint.read(["pkg/a.txt", ("pkg/a.txt", 5, 10), "nope"])
    assert isinstance(whole, C.Content) and whole.data == content
    assert whole.listed == M.Listed("pkg/a.txt", "f", 0o644, len(content), hash=digest)
    assert isinstance(piece, C.Content) and piece.data == content[5:15]
    assert isinstance(missing, C.Failed) and "nope" in missing.message
    [signed, unsigned] = endpoint.sigs(["pkg/a.txt", "nope"])
    assert isinstance(signed, C.Signed) and signed.hash == digest and signed.signature
    assert isinstance(unsigned, C.Failed)
    adopted = endpoint.adopt([whole.listed])
    assert adopted.adopted >= 0 and adopted.epoch == applied.epoch
    assert endpoint.kept("trash") == C.KeptList([], False)
    endpoint.ping()


def test_a_missing_workspace_is_a_remote_error(endpoint: C.Endpoint) -> None:
    with pytest.raises(RemoteError, match="does not exist"):
        endpoint.open("~/nowhere", create=False, readonly=True)


def frame(header: dict, blob: bytes = b"") -> wire.Frame:
    return wire.Frame(wire.T_RESPONSE, 1, header, blob)


@pytest.mark.parametrize(
    "header, says",
    [
        ({"epoch": "e", "gen": "7", "full": True, "entries": []}, "'gen' is not an integer"),
        ({"epoch": "e", "gen": True, "full": True, "entries": []}, "'gen' is not an integer"),
        ({"epoch": 3, "gen": 1, "full": True, "entries": []}, "'epoch' is not a string"),
        ({"epoch": "e", "gen": 1, "full": True, "entries": {}}, "'entries' is not a list"),
        ({"epoch": "e", "gen": 1, "full": True, "entries": [["../x", "f", 0, 0, ""]]}, None),
        ({"epoch": "e", "gen": 1, "full": False, "gone": ["/etc"]}, None),
        ({"epoch": "e", "gen": 1, "full": True, "skipped": [["a"]]}, "skipped"),
    ],
)
def test_a_malformed_listing_is_a_protocol_error(header: dict, says: str | None) -> None:
    with pytest.raises(ProtocolError, match=says):
        C.Listing.from_frame(frame(header))


def test_a_sync_answer_must_answer_every_operation() -> None:
    ops = [M.Op(M.MKDIR, "a", expect=M.ABSENT), M.Op(M.MKDIR, "b", expect=M.ABSENT)]
    with pytest.raises(ProtocolError, match="1 results for 2 operations"):
        C.Applied.from_frame(frame({"epoch": "e", "gen": 1, "results": [0]}), ops)
    ok = C.Applied.from_frame(frame({"epoch": "e", "gen": 1, "results": [0, {"c": "io"}]}), ops)
    assert ok.results[0] == M.Result(M.OK, "", "", ["a", "d", 0, 0, ""])
    assert ok.results[1].code == M.IO_ERROR


@pytest.mark.parametrize(
    "item",
    [
        {"c": "ok", "l": ["a", "f", 0, 4, "h"]},  # no blob reference
        {"c": "ok", "l": ["a", "f", 0, 4, "h"], "bl": [2, 4]},  # past the blob's end
        {"c": "ok", "l": ["a", "f", 0, 4, "h"], "bl": [-1, 1]},
        {"c": "ok", "l": ["a", "f", 0, 4, "h"], "bl": [0, True]},
        {"c": "ok", "bl": [0, 4]},  # no listing entry
        "ok",
    ],
)
def test_a_malformed_read_answer_is_a_protocol_error(item: object) -> None:
    conn = _Answering(frame({"items": [item]}, b"data"))
    with pytest.raises(ProtocolError):
        C.Endpoint(conn).read(["a"])  # type: ignore[arg-type]


def test_a_read_answer_must_answer_every_item() -> None:
    conn = _Answering(frame({"items": []}))
    with pytest.raises(ProtocolError, match="0 answers to 1 items"):
        C.Endpoint(conn).read(["a"])  # type: ignore[arg-type]


class _Answering:
    """A connection that answers every request with one frame (a unit test's fake)."""

    algorithm = "sha256"

    def __init__(self, answer: wire.Frame) -> None:
        self.answer = answer

    def send(self, header: dict, blob: bytes = b"", **_kw: object) -> int:
        return 1

    def wait(self, req_id: int) -> wire.Frame:
        return self.answer

    def answered(self, req_id: int) -> bool:
        return True


# --------------------------------------------------------------------------- a lying robot
LIAR = """
import sys
from fetchsync.protocol.server import main, Server

MODE = sys.argv[1]


class Liar(Server):
    def do_list(self, h, blob):
        out, data = Server.do_list(self, h, blob)
        if MODE == "list_gen":
            out["gen"] = "seven"
        return out, data

    def do_read(self, h, blob):
        out, data = Server.do_read(self, h, blob)
        if MODE == "read_no_blob":
            for item in out["items"]:
                item.pop("bl", None)
        return out, data

    def do_sync(self, h, blob):
        out, data = Server.do_sync(self, h, blob)
        if MODE == "sync_short" and out.get("results"):
            out["results"] = out["results"][:-1]
        return out, data


import fetchsync.protocol.server as s

s.Server = Liar
main()
"""


@pytest.fixture
def robot(tmp_path: Path):
    """A workspace on the laptop and one on the ``local`` robot, both synced."""
    ws = make_workspace(tmp_path / "ws")
    env = local_env(tmp_path)
    fetchsync("push", env=env)  # the honest endpoint
    return env, ws


def liar(env: dict, tmp_path: Path, mode: str) -> dict:
    script = tmp_path / "liar.py"
    script.write_text(LIAR)
    wrapper = tmp_path / f"lying-python-{mode}"
    wrapper.write_text(
        "#!/bin/sh\n"
        f"PYTHONPATH={shlex.quote(str(REPO))} exec {shlex.quote(sys.executable)} "
        f"{shlex.quote(str(script))} {mode}\n"
    )
    wrapper.chmod(0o755)
    return dict(env, FETCHSYNC_REMOTE_PYTHON=str(wrapper))


@pytest.mark.parametrize(
    "verb, mode, says",
    [
        ("push", "list_gen", "the robot's answer to 'list' is malformed: 'gen' is not an integer"),
        ("pull", "read_no_blob", "the robot's answer to 'read' is malformed"),
        ("push", "sync_short", "the robot's answer to 'sync' is malformed"),
    ],
)
def test_a_lying_robots_malformed_answer_is_one_line_and_exit_7(
    robot, tmp_path: Path, verb: str, mode: str, says: str
) -> None:
    env, ws = robot
    edited = next(p for p in sorted((ws / "src").rglob("*")) if p.is_file())
    if verb == "push":
        edited.write_bytes(edited.read_bytes() + b"# an edit\n")
    else:
        edited.unlink()  # the pull brings it back: a read
    before = tree_of(ws / "src")
    args = ("pull", "--yes") if verb == "pull" else ("push",)
    proc = fetchsync(*args, env=liar(env, tmp_path, mode), check=False)
    err = proc.stderr.decode("utf-8", "replace")
    assert proc.returncode == 7, (proc.returncode, err)
    assert "Traceback" not in err and len(without_where(err)) == 1, err
    assert says in err
    assert tree_of(ws / "src") == before
