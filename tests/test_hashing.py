"""Tests of fetchsync.protocol.hashing: names, negotiation, digests."""

from __future__ import annotations

import hashlib
import io
import os
from typing import Any

import pytest

from fetchsync.protocol import hashing
from fetchsync.protocol.errors import ProtocolError

xxhash: Any
try:
    import xxhash
except ImportError:  # pragma: no cover - xxhash is a laptop dependency
    xxhash = None

DATA = bytes(range(256)) * 1000 + b"tail"


def algorithms() -> list[str]:
    return hashing.available()


@pytest.fixture
def no_xxhash(monkeypatch: pytest.MonkeyPatch) -> None:
    """This end as a robot without xxhash."""
    monkeypatch.setattr(hashing, "_xxhash", None)


def test_available_prefers_xxh3_and_always_has_blake2b() -> None:
    names = hashing.available()
    assert names[-1] == hashing.BLAKE2B_128
    assert (hashing.XXH3_128 in names) == (xxhash is not None)
    if xxhash is not None:
        assert names[0] == hashing.XXH3_128
    assert set(names) <= set(hashing.KNOWN)


def test_available_without_xxhash(no_xxhash: None) -> None:
    assert hashing.available() == [hashing.BLAKE2B_128]
    with pytest.raises(ProtocolError, match="not available"):
        hashing.new(hashing.XXH3_128)
    with pytest.raises(ProtocolError):
        hashing.digest(hashing.XXH3_128, b"x")
    assert (
        hashing.digest(hashing.BLAKE2B_128, b"x") == hashlib.blake2b(b"x", digest_size=16).digest()
    )


def test_negotiate_takes_our_first_choice_they_have() -> None:
    ours = [hashing.XXH3_128, hashing.BLAKE2B_128]
    assert hashing.negotiate(ours, [hashing.BLAKE2B_128, hashing.XXH3_128]) == hashing.XXH3_128
    assert hashing.negotiate(ours, [hashing.BLAKE2B_128]) == hashing.BLAKE2B_128
    assert hashing.negotiate([hashing.BLAKE2B_128], ours) == hashing.BLAKE2B_128


def test_negotiate_fails_without_a_common_algorithm() -> None:
    with pytest.raises(ProtocolError, match="no common hash algorithm"):
        hashing.negotiate([hashing.BLAKE2B_128], ["md5"])
    with pytest.raises(ProtocolError):
        hashing.negotiate([], [hashing.BLAKE2B_128])


@pytest.mark.parametrize("name", ["md5", "", "BLAKE2B-128", "sha256"])
def test_unknown_algorithm_is_a_protocol_error(name: str) -> None:
    for call in (hashing.new, hashing.digester, hashing.chunk_digester):
        with pytest.raises(ProtocolError, match="unknown"):
            call(name)
    with pytest.raises(ProtocolError):
        hashing.file_digest(name, io.BytesIO(b""))


def test_blake2b_128_is_blake2b_with_a_16_byte_digest() -> None:
    assert (
        hashing.digest(hashing.BLAKE2B_128, DATA) == hashlib.blake2b(DATA, digest_size=16).digest()
    )
    assert hashing.digest(hashing.BLAKE2B_128, b"").hex() == "cae66941d9efbd404e4d88758ea67670"


@pytest.mark.skipif(xxhash is None, reason="xxhash not installed")
def test_xxh3_128_is_xxhash_xxh3_128() -> None:
    assert hashing.digest(hashing.XXH3_128, DATA) == xxhash.xxh3_128_digest(DATA)
    assert hashing.digest(hashing.XXH3_128, b"").hex() == "99aa06d3014798d86001c324468d497f"


@pytest.mark.parametrize("name", algorithms())
def test_incremental_equals_one_shot(name: str) -> None:
    h = hashing.new(name)
    for i in range(0, len(DATA), 1000):
        h.update(DATA[i : i + 1000])
    assert h.digest() == hashing.digest(name, DATA)
    assert len(h.digest()) == hashing.DIGEST_SIZE == 16
    assert hashing.digester(name)(DATA) == hashing.digest(name, DATA)


@pytest.mark.parametrize("name", algorithms())
def test_chunk_digest_is_the_first_8_bytes(name: str) -> None:
    assert hashing.chunk_digest(name, DATA) == hashing.digest(name, DATA)[:8]
    assert hashing.chunk_digester(name)(DATA) == hashing.chunk_digest(name, DATA)
    assert len(hashing.chunk_digest(name, b"")) == hashing.CHUNK_DIGEST_SIZE == 8


@pytest.mark.parametrize("name", algorithms())
def test_digest_takes_any_bytes_like(name: str) -> None:
    want = hashing.digest(name, DATA)
    assert hashing.digest(name, bytearray(DATA)) == want
    assert hashing.digest(name, memoryview(DATA)) == want


@pytest.mark.parametrize("name", algorithms())
@pytest.mark.parametrize("bufsize", [1, 7, 4096, 1 << 20])
def test_file_digest_of_a_file_object(name: str, bufsize: int) -> None:
    data = DATA if bufsize > 1 else DATA[:5000]
    assert hashing.file_digest(name, io.BytesIO(data), bufsize) == hashing.digest(name, data)


@pytest.mark.parametrize("name", algorithms())
def test_file_digest_of_a_real_file_and_its_descriptor(name: str, tmp_path: object) -> None:
    path = os.path.join(str(tmp_path), "f")
    with open(path, "wb") as fh:
        fh.write(DATA)
    want = hashing.digest(name, DATA)
    with open(path, "rb") as fh:
        assert hashing.file_digest(name, fh, 1000) == want
    with open(path, "rb", buffering=0) as fh:
        assert hashing.file_digest(name, fh, 1000) == want
    fd = os.open(path, os.O_RDONLY)
    try:
        assert hashing.file_digest(name, fd, 1000) == want
        os.lseek(fd, 100, os.SEEK_SET)
        assert hashing.file_digest(name, fd) == hashing.digest(name, DATA[100:])
    finally:
        os.close(fd)


class ReadOnly:
    """A file object with ``read`` but no ``readinto``."""

    def __init__(self, data: bytes) -> None:
        self._io = io.BytesIO(data)

    def read(self, n: int) -> bytes:
        return self._io.read(min(n, 333))


@pytest.mark.parametrize("name", algorithms())
def test_file_digest_reads_only_the_rest(name: str) -> None:
    fh = io.BytesIO(DATA)
    fh.seek(1234)
    assert hashing.file_digest(name, fh) == hashing.digest(name, DATA[1234:])
    assert hashing.file_digest(name, ReadOnly(DATA)) == hashing.digest(name, DATA)  # type: ignore[arg-type]
    assert hashing.file_digest(name, io.BytesIO(b"")) == hashing.digest(name, b"")


def test_file_digest_needs_a_positive_bufsize() -> None:
    with pytest.raises(ValueError):
        hashing.file_digest(hashing.BLAKE2B_128, io.BytesIO(b"x"), 0)
