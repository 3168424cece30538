"""What a push puts on the wire: the compression level chosen from the link, and the
bytes of a small edit (over the local robot: the protocol without SSH)."""

from __future__ import annotations

import random
import threading
import time
import zlib
from pathlib import Path
from typing import Any

import pytest
from helpers import tree_of

from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.protocol import messages as M
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State


def _mesh_like(n: int, seed: int) -> bytes:
    """Binary data zlib shrinks by ~10% only (like an STL mesh): above the 85% rule."""
    rng = random.Random(seed)
    return b"".join(rng.randbytes(5) + b"\x00" for _ in range(n // 6))


@pytest.fixture
def push_env(tmp_path: Path):
    src = tmp_path / "ws" / "src"
    src.mkdir(parents=True)
    conns: list[Any] = []

    def syncer() -> sync.Syncer:
        conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
        conns.append(conn)
        return sync.Syncer(
            conn,
            State(tmp_path / "state.sqlite"),
            local_root=str(src),
            remote_workspace="~/ws",
            rules=sync.build_rules(),
        )

    yield src, tmp_path / "robot-home" / "ws" / "src", syncer
    for c in conns:
        c.close()


def test_a_slow_link_gets_level_6_and_slightly_compressible_files_compressed(push_env):
    """Until the robot's answers show a fast link, a batch is deflated at zlib's level 6
    and files that shrink by only ~10% (meshes, recordings) are compressed too, as rsync
    -z does: on Wi-Fi the link, not zlib, is the bottleneck."""
    src, robot_src, syncer = push_env
    mesh = _mesh_like(300 * 1024, 1)
    assert 0.85 < len(zlib.compress(mesh, 1)) / len(mesh) < 0.97
    (src / "mesh.stl").write_bytes(mesh)
    text = b"".join(b"int value_%d = compute(%d, %d);\n" % (i, i * 7, i % 13) for i in range(20000))
    (src / "table.cpp").write_bytes(text)
    report = syncer().push()
    assert report.errors == [] and tree_of(src) == tree_of(robot_src)
    # level 1 or a raw mesh would need more than this
    assert report.bytes_sent < len(zlib.compress(mesh, 6)) + len(zlib.compress(text, 6)) + 4096
    assert report.bytes_sent < len(mesh) + len(zlib.compress(text, 1))


class _Answered:
    def answered(self) -> bool:
        return True


class _FastEndpoint:
    """An endpoint whose answers are all in at once: a link faster than zlib 6."""

    stl = False  # takes no split meshes (Endpoint.stl)

    class conn:  # noqa: N801 - stands for the Connection attribute
        compress = True
        bytes_in = bytes_out = 0
        last_arrival = 0.0  # when the latest answer came

    def __init__(self) -> None:
        self.levels: list[bool] = []

    def send_sync(self, ops: Any, **kw: Any) -> _Answered:
        self.zparts = kw["blob_parts"]
        return _Answered()


def _fast_batcher() -> tuple[_FastEndpoint, sync._Batcher]:
    endpoint = _FastEndpoint()
    batcher = sync._Batcher(
        endpoint,  # type: ignore[arg-type]
        policy="preserve",
        epoch="e",
        gen=0,
        progress=None,
        total=0,
    )
    return endpoint, batcher


def _idle_for(batcher: sync._Batcher, seconds: float) -> None:
    """The sender waiting ``seconds`` for the packer's next batch."""
    waiter = threading.Thread(target=batcher._next_packed)
    waiter.start()
    time.sleep(seconds)
    batcher._to_send.put(None)
    waiter.join()


TEXT = b"".join(b"line %d of a source file\n" % i for i in range(60000))


def test_a_fast_link_is_seen_and_gets_the_fast_level():
    """Once the link sat idle (every batch sent answered, the sender waiting for the
    packer) for FAST_IDLE of the time since the first batch, large batches are deflated
    at level 1 and the 85% rule is back."""
    endpoint, batcher = _fast_batcher()
    assert batcher.slow
    op = M.Op(M.WRITE, "a", expect=M.ABSENT, hash="00", size=len(TEXT), source=M.SRC_DATA)
    batcher._send(batcher._pack(0, [(op, TEXT, True)], [None]))
    _idle_for(batcher, 0.2)
    batcher._send(batcher._pack(1, [(op.but(path="b"), TEXT, True)], [None]))
    assert batcher.slow  # one batch answered: not judged yet
    _idle_for(batcher, 0.2)
    batcher._send(batcher._pack(2, [(op.but(path="c"), TEXT, True)], [None]))
    assert not batcher.slow
    fast = zlib.decompressobj().decompress(b"".join(endpoint.zparts))
    assert fast == TEXT
    assert len(b"".join(endpoint.zparts)) > len(zlib.compress(TEXT, 6))  # level 1's size


def test_a_link_never_idle_keeps_level_6_however_fast_its_answers():
    """Answers all in at once (the rule before called that fast: the robot answering for
    raw bytes faster than half zlib 6's rate), but the sender never waited on an idle
    link: the link is the bottleneck, level 6 costs no time and saves bytes."""
    endpoint, batcher = _fast_batcher()
    op = M.Op(M.WRITE, "a", expect=M.ABSENT, hash="00", size=len(TEXT), source=M.SRC_DATA)
    for k in range(5):
        batcher._send(batcher._pack(k, [(op.but(path=f"p{k}"), TEXT, True)], [None]))
        time.sleep(0.02)
    assert batcher.slow
    assert len(b"".join(endpoint.zparts)) <= len(zlib.compress(TEXT, 6)) + 64


def test_a_batchs_text_goes_into_its_stream_grouped_by_extension():
    endpoint, batcher = _fast_batcher()
    names = ["a/x.cpp", "a/x.yaml", "b/y.cpp", "b/y.launch", "c/z.cpp", "c/z.yaml"]
    items = []
    for n in names:
        data = (n.encode() + b"\n") * 20
        op = M.Op(M.WRITE, n, expect=M.ABSENT, hash="00", size=len(data), source=M.SRC_DATA)
        items.append((op, data, True))
    packed = batcher._pack(0, items, [None] * len(items))
    order = sorted(packed.ops, key=lambda o: o.blob[0])
    assert [o.path for o in order] == [
        "a/x.cpp",
        "b/y.cpp",
        "c/z.cpp",
        "b/y.launch",
        "a/x.yaml",
        "c/z.yaml",
    ]
    stream = zlib.decompressobj().decompress(b"".join(packed.zparts))
    for op, (_, data, _) in zip(packed.ops, items):
        assert stream[op.blob[0] : op.blob[0] + op.blob[1]] == data


def test_shared_packs_make_each_key_once_and_a_failed_maker_leaves_it_to_the_next():
    packs = sync.SharedPacks(max_bytes=10)
    started, release = threading.Event(), threading.Event()
    calls: list[str] = []

    def failing() -> list[bytes]:
        calls.append("failing")
        started.set()
        release.wait(5)
        raise OSError("the maker's read failed")

    def good() -> list[bytes]:
        calls.append("good")
        return [b"stream"]

    errors: list[BaseException] = []

    def first() -> None:
        try:
            packs.get(b"k", failing)
        except OSError as exc:
            errors.append(exc)

    t = threading.Thread(target=first)
    t.start()
    started.wait(5)
    got: list[list[bytes]] = []
    waiter = threading.Thread(target=lambda: got.append(packs.get(b"k", good)))
    waiter.start()
    release.set()
    t.join(5)
    waiter.join(5)
    assert errors and got == [[b"stream"]] and calls == ["failing", "good"]
    assert packs.get(b"k", good) == [b"stream"] and calls == ["failing", "good"]
    assert packs.get(b"other", lambda: [b"another stream"]) == [b"another stream"]
    assert packs.made == 2 and packs.reused == 1
    assert packs.get(b"k", good) == [b"stream"] and calls[-1] == "good"  # dropped: over 10 B


def test_binary_data_goes_at_the_fast_level_in_the_texts_stream(monkeypatch):
    """On a slow link a batch's text is deflated at zlib's level 6 and its binary data
    (a NUL in its first 8 KiB: meshes, maps) at ISA-L's level 1, as small there for a
    tenth of the CPU, in one stream the robot's zlib inflates, each operation pointing
    at its own bytes."""
    endpoint = _FastEndpoint()
    batcher = sync._Batcher(
        endpoint,  # type: ignore[arg-type]
        policy="preserve",
        epoch="e",
        gen=0,
        progress=None,
        total=0,
    )
    level6: list[bytes] = []
    real = zlib.compressobj

    class Spy:
        def __init__(self, *args: Any) -> None:
            self.obj = real(*args)
            self.six = args[:1] == (6,)

        def compress(self, data: bytes) -> bytes:
            if self.six:
                level6.append(data)
            return self.obj.compress(data)

        def flush(self, *mode: int) -> bytes:
            return self.obj.flush(*mode)

    monkeypatch.setattr(sync.zlib, "compressobj", Spy)
    mesh = _mesh_like(200 * 1024, 2)
    text = b"".join(b"double x_%d = %d.5;\n" % (i, i) for i in range(8000))
    ops = [
        M.Op(M.WRITE, p, expect=M.ABSENT, hash="00", size=len(d), source=M.SRC_DATA)
        for p, d in (("mesh.stl", mesh), ("a.cpp", text), ("b.cpp", text[:5000]))
    ]
    packed = batcher._pack(
        0, [(ops[0], mesh, True), (ops[1], text, True), (ops[2], text[:5000], True)], [None] * 3
    )
    assert level6 == [text, text[:5000]]  # the binary data never went through level 6
    stream = zlib.decompress(b"".join(packed.zparts))  # the robot's inflate, checksum included
    assert len(stream) == packed.zpos
    for op, data in zip(packed.ops, (mesh, text, text[:5000])):
        assert op.z and stream[op.blob[0] : op.blob[0] + op.blob[1]] == data
    both = zlib.compress(text, 6) + zlib.compress(mesh, 6)
    assert len(b"".join(packed.zparts)) < len(both) * 1.02


def test_the_engine_imports_its_compressor_only_when_it_compresses():
    """A no-op push compresses nothing: ISA-L is imported at the first compression."""
    import subprocess
    import sys

    code = (
        "import sys; import fetchsync.sync.engine as e; assert 'isal' not in sys.modules;"
        "e._fast(); print('isal' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "True"
