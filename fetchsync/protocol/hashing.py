"""Content hashes: the algorithms both ends know, negotiation, and digests.

Two algorithms, both with 16-byte digests:

- ``"xxh3-128"``: xxHash's XXH3 128-bit, several times faster than BLAKE2;
  offered only when the optional ``xxhash`` package is importable here.
- ``"blake2b-128"``: ``hashlib.blake2b(digest_size=16)``; always available
  (standard library), so two ends can always agree on something.

Each end lists what it has (:func:`available`, best first) in the handshake
and both pick the same one with :func:`negotiate`. Digests of whole files are
16 bytes; digests of delta chunks (:func:`chunk_digest`) are the first 8 bytes
of the same digest, enough to find a chunk again within one file: a delta is
always checked against the whole file's 16-byte digest after it is applied.

Every function hashes a whole buffer in one C call; nothing here loops over
bytes in Python. Standard library only, Python 3.6 (runs on the robot).
"""

import os
from typing import Any, BinaryIO, Callable, Sequence, Union

try:
    from typing import Protocol  # novermin
except ImportError:  # Python < 3.8 (the robot's may be 3.6): the class only documents
    Protocol = object  # type: ignore[assignment]

from fetchsync.protocol.errors import ProtocolError

_xxhash: "Any"
try:  # hashlib's own, without importing hashlib (and OpenSSL's _hashlib): ~3 ms of each start
    from _blake2 import blake2b
except ImportError:  # pragma: no cover - a Python built without it
    from hashlib import blake2b

try:  # optional accelerator; the handshake only offers it when both ends have it
    import xxhash as _xxhash
except ImportError:  # pragma: no cover - depends on the environment
    _xxhash = None

XXH3_128 = "xxh3-128"
BLAKE2B_128 = "blake2b-128"

#: Every algorithm name this version understands, best first.
KNOWN = (XXH3_128, BLAKE2B_128)
#: Always available on every end (standard library).
FALLBACK = BLAKE2B_128
DIGEST_SIZE = 16
CHUNK_DIGEST_SIZE = 8

DEFAULT_BUFSIZE = 1 << 20

#: What the digest functions take: any bytes-like object.
Buffer = Union[bytes, bytearray, memoryview]
#: What :func:`file_digest` reads: a binary file object or an OS file descriptor.
Source = Union[BinaryIO, int]


class Hasher(Protocol):
    """What :func:`new` returns: ``update(data)`` then ``digest()`` (16 bytes)."""

    def update(self, data: "Buffer") -> None: ...

    def digest(self) -> bytes: ...


def _has_xxh3(module: "Any") -> bool:
    return module is not None and hasattr(module, "xxh3_128") and hasattr(module, "xxh3_128_digest")


def available() -> "list[str]":
    """The algorithms this end can compute, in preference order."""
    if _has_xxh3(_xxhash):
        return [XXH3_128, BLAKE2B_128]
    return [BLAKE2B_128]


def negotiate(ours: "Sequence[str]", theirs: "Sequence[str]") -> str:
    """The first of ``ours`` (our preference order) that ``theirs`` also has."""
    for name in ours:
        if name in theirs:
            return name
    raise ProtocolError(
        "no common hash algorithm: we have {}, the peer has {}".format(
            ", ".join(ours) or "none", ", ".join(theirs) or "none"
        )
    )


def _check(name: str) -> None:
    if name == XXH3_128 and _has_xxh3(_xxhash):
        return
    if name == BLAKE2B_128:
        return
    if name in KNOWN:
        raise ProtocolError(f"hash algorithm {name!r} is not available here (needs xxhash)")
    raise ProtocolError(f"unknown hash algorithm {name!r}")


def new(name: str) -> "Hasher":
    """A fresh incremental hasher: ``update(data)``, then ``digest()`` (16 bytes)."""
    _check(name)
    if name == XXH3_128:
        hasher: "Hasher" = _xxhash.xxh3_128()
        return hasher
    return blake2b(digest_size=DIGEST_SIZE)


def digester(name: str) -> "Callable[[Buffer], bytes]":
    """A one-shot function ``data -> 16-byte digest`` (one C call per buffer)."""
    _check(name)
    if name == XXH3_128:
        return _xxhash.xxh3_128_digest  # type: ignore[no-any-return]

    def blake2b_128(data: "Buffer") -> bytes:
        return blake2b(data, digest_size=DIGEST_SIZE).digest()

    return blake2b_128


def chunk_digester(name: str) -> "Callable[[Buffer], bytes]":
    """A one-shot function ``data -> 8-byte chunk digest`` (see :func:`chunk_digest`)."""
    _check(name)
    if name == XXH3_128:
        xxh3_128_digest = _xxhash.xxh3_128_digest

        def xxh3_64of128(data: "Buffer") -> bytes:
            return xxh3_128_digest(data)[:CHUNK_DIGEST_SIZE]  # type: ignore[no-any-return]

        return xxh3_64of128

    def blake2b_64of128(data: "Buffer") -> bytes:
        return blake2b(data, digest_size=DIGEST_SIZE).digest()[:CHUNK_DIGEST_SIZE]

    return blake2b_64of128


def digest(name: str, data: "Buffer") -> bytes:
    """The 16-byte digest of ``data`` (any bytes-like object)."""
    return digester(name)(data)


def chunk_digest(name: str, data: "Buffer") -> bytes:
    """The 8-byte digest of a delta chunk: the first half of :func:`digest`."""
    return digester(name)(data)[:CHUNK_DIGEST_SIZE]


def file_digest(name: str, source: "Source", bufsize: int = DEFAULT_BUFSIZE) -> bytes:
    """The 16-byte digest of everything left to read in ``source``.

    ``source`` is a binary file object (read with ``readinto`` into one reused
    buffer when it has it) or an OS file descriptor. Memory use is ``bufsize``.
    """
    if bufsize <= 0:
        raise ValueError("bufsize must be positive")
    hasher = new(name)
    update = hasher.update
    if isinstance(source, int):
        while True:
            block = os.read(source, bufsize)
            if not block:
                break
            update(block)
        return hasher.digest()
    readinto = getattr(source, "readinto", None)
    if readinto is None:
        while True:
            block = source.read(bufsize)
            if not block:
                break
            update(block)
        return hasher.digest()
    buf = bytearray(bufsize)
    view = memoryview(buf)
    while True:
        n = readinto(buf)
        if not n:
            break
        update(view[:n])
    return hasher.digest()
