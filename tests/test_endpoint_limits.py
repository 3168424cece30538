"""The endpoint's limits: bounded memory for any file size (issue 22, item 19), sparse
files kept sparse (item 20), a legal 255-byte name in multi-byte characters (item 23)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from endpoint_client import ALG, Endpoint

from fetchsync.protocol import delta as delta_mod
from fetchsync.protocol import hashing
from fetchsync.protocol import messages as M
from fetchsync.protocol.store import Store

MiB = 1 << 20


def h(data: bytes) -> str:
    return hashing.digest(ALG, data).hex()


@pytest.fixture
def store(tmp_path: Path):
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    yield s
    s.unlock()


def test_a_255_byte_name_in_multibyte_characters_syncs(store):
    name = "\u65e5" * 85  # 255 bytes in UTF-8, 85 characters
    assert len(os.fsencode(name)) == 255
    data = b"content\n"
    ops = [
        M.Op(M.MKDIR, name, expect=M.ABSENT, mode=0o755),
        M.Op(
            M.WRITE,
            name + "/" + name,
            expect=M.ABSENT,
            mode=0o644,
            hash=h(data),
            size=len(data),
            source=M.SRC_DATA,
            blob=(0, len(data)),
        ),
        M.Op(M.SYMLINK, name + "/" + "\U0001f916" * 63 + "abc", expect=M.ABSENT, target=name),
    ]
    results = store.apply(ops, data)
    assert all(r.ok for r in results), results
    assert (Path(store.root) / name / name).read_bytes() == data


def _allocated(path: Path) -> int:
    return os.stat(path).st_blocks * 512


def test_sparse_files_stay_sparse(store):
    """Runs of zeros arrive as holes: written whole, and through an upload in pieces."""
    size = 16 * MiB
    data = bytearray(size)
    data[:4096] = b"x" * 4096
    data[size // 2 : size // 2 + 10] = b"middle bit"
    data[-5:] = b"tail\n"
    data = bytes(data)
    op = M.Op(
        M.WRITE,
        "whole.img",
        expect=M.ABSENT,
        mode=0o644,
        hash=h(data),
        size=size,
        source=M.SRC_DATA,
        blob=(0, size),
    )
    assert store.apply([op], data)[0].ok
    whole = Path(store.root) / "whole.img"
    assert whole.read_bytes() == data and _allocated(whole) <= 1 * MiB
    # in pieces, as a large file's upload: holes inside and at the end
    end_zero = data[: 8 * MiB - 16] + b"x" * 16 + bytes(5 * MiB)
    pieces = [
        M.Op(M.UPLOAD, "", upload="u1", size=off, blob=(0, 4 * MiB))
        for off in range(0, 8 * MiB, 4 * MiB)
    ]
    for piece in pieces:
        blob = end_zero[piece.size : piece.size + 4 * MiB]
        assert store.apply([piece], blob)[0].ok
    last = M.Op(
        M.WRITE,
        "upload.img",
        expect=M.ABSENT,
        mode=0o600,
        hash=h(end_zero),
        size=len(end_zero),
        source=M.SRC_UPLOAD,
        upload="u1",
    )
    assert store.apply([last], b"")[0].ok
    up = Path(store.root) / "upload.img"
    assert up.read_bytes() == end_zero and _allocated(up) <= 1 * MiB


@pytest.mark.slow
def test_a_one_line_edit_of_a_large_file_keeps_the_endpoint_small(tmp_path):
    """Signature, read and delta apply go through the file in pieces: the endpoint's
    peak memory stays far below the file's size (the old one read it whole, twice)."""
    size = 256 * MiB
    ws = tmp_path / "ws"
    (ws / "src").mkdir(parents=True)
    big = ws / "src" / "big.log"
    block = b"".join(
        b"%08d the quick brown fox jumps over the lazy dog\n" % i for i in range(20000)
    )
    old_line = block[: block.index(b"\n") + 1]
    assert old_line.endswith(b"\n")
    with open(big, "wb") as fh:
        while fh.tell() < size:
            fh.write(block)
    size = big.stat().st_size
    home = tmp_path / "home"
    home.mkdir()
    new_line = b"00000000 an edited first line\n"
    hasher = hashing.new(ALG)
    hasher.update(new_line)
    with open(big, "rb") as fh:
        fh.seek(len(old_line))
        while True:
            piece = fh.read(8 * MiB)
            if not piece:
                break
            hasher.update(piece)
    new_size = size - len(old_line) + len(new_line)
    d = delta_mod.Delta(
        (delta_mod.Literal(new_line), delta_mod.Copy(len(old_line), size - len(old_line))),
        new_size,
        size,
    )
    blob = delta_mod.encode_delta(d)
    with Endpoint(str(home)) as ep:
        f = ep.request({"op": "open", "workspace": str(ws)})
        assert f.type == 2
        f = ep.request({"op": "list"})
        assert f.type == 2
        [entry] = [e for e in f.header["entries"] if e[0] == "big.log"]
        f = ep.request({"op": "sigs", "items": [{"p": "big.log"}]})
        assert f.type == 2 and f.header["items"][0]["h"] == entry[4]
        f = ep.request({"op": "read", "items": [{"p": "big.log", "off": size - 100, "len": 100}]})
        assert f.type == 2 and len(f.blob) == 100
        op = M.Op(
            M.WRITE,
            "big.log",
            expect=M.expect_file(entry[4]),
            mode=0o644,
            hash=hasher.digest().hex(),
            size=new_size,
            source=M.SRC_DELTA,
            base=entry[4],
            blob=(0, len(blob)),
        )
        f = ep.request({"op": "sync", "ops": [op.to_wire()]}, blob)
        assert f.type == 2 and M.Result.from_wire(f.header["results"][0], op).ok, f.header
        peak = ep.peak_rss()
    with open(big, "rb") as fh:
        assert fh.read(len(new_line)) == new_line
    assert big.stat().st_size == new_size
    assert peak < 64 * MiB, f"the endpoint peaked at {peak // MiB} MiB for a {size // MiB} MiB file"


def test_reads_larger_than_a_piece_are_refused_not_loaded(store):
    """A whole read of a file larger than MAX_READ, or a delta against a huge signature,
    is a per-file error asking for pieces: the endpoint never loads a whole large file."""
    from fetchsync.protocol import store as store_mod
    from fetchsync.protocol.errors import ProtocolError

    big = Path(store.root) / "big.bin"
    with open(big, "wb") as fh:
        fh.truncate(store_mod.MAX_READ + 1)
    with pytest.raises(ProtocolError, match="pieces"):
        store.read("big.bin")
    assert len(store.read("big.bin", offset=store_mod.MAX_READ - 10)[2]) == 11
    assert len(store.read("big.bin", offset=0, length=1000)[2]) == 1000
    with pytest.raises(ProtocolError, match="pieces"):
        store.read("big.bin", sig=b"\0" * (store_mod.MAX_READ_SIG + 1))
