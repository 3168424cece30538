"""Tests of fetchsync.protocol.delta: chunking, signature, delta, patch, encodings.

Every round trip goes through ``check`` which also runs the streaming variants
and the binary encodings, so each mutation case covers all of them.
"""

from __future__ import annotations

import functools
import io
import json
import os
import random
import subprocess
import sys
import zlib
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fetchsync.protocol import delta as D
from fetchsync.protocol import hashing
from fetchsync.protocol.delta import Copy, Delta, Literal, Signature
from fetchsync.protocol.errors import DeltaError, ProtocolError

REPO = Path(__file__).resolve().parent.parent
PY38 = "/root/.pyenv/versions/3.8.18/bin/python3.8"
TARGET, MIN, MAX = D.DEFAULT_PARAMS
SMALL = (64, 16, 256)  # many chunks from little data, for property tests

WORDS = [
    b"int",
    b"return",
    b"self",
    b"value",
    b"ros::NodeHandle",
    b"std::vector<double>",
    b"if",
    b"for",
    b"const",
    b"auto",
    b"publisher_",
    b"msg",
    b"data",
    b"callback",
    b"=",
    b"+",
    b"(",
    b")",
    b"{",
    b"}",
    b";",
    b"0",
    b"1",
    b"rate",
    b"node",
    b"#include",
    b"<ros/ros.h>",
    b"//",
    b"TODO",
    b"x_",
    b"y_",
]


def random_bytes(n: int, seed: int) -> bytes:
    return random.Random(seed).getrandbits(8 * n).to_bytes(n, "little") if n else b""


@functools.lru_cache(maxsize=None)
def source_text(size: int, seed: int = 1) -> bytes:
    """Deterministic text that looks like source code (short indented lines)."""
    r = random.Random(seed)
    out = []
    n = 0
    while n < size:
        k = r.randint(0, 9)
        line = b" " * (4 * r.randint(0, 3)) + b" ".join(r.choice(WORDS) for _ in range(k))
        line += b";\n" if k else b"\n"
        out.append(line)
        n += len(line)
    return b"".join(out)[:size]


def chunks_of(data: bytes, params: D.Params = D.DEFAULT_PARAMS) -> list[tuple[int, bytes]]:
    return list(D._chunks(data, params))


def check(base: bytes, new: bytes, **kw: Any) -> Delta:
    """Assert every way of making and applying the delta gives ``new``; the delta."""
    sig = D.signature(base, **kw)
    d = D.delta(new, sig)
    d.validate()
    assert d.new_size == len(new)
    assert d.base_size == len(base)
    assert D.patch(base, d) == new
    copied, literal = D.stats(d)
    assert copied + literal == len(new)
    # canonical: no empty ops, no two literals in a row, no two contiguous copies
    for a, b in zip(d.ops, d.ops[1:]):
        assert not (type(a) is Literal and type(b) is Literal)
        if type(a) is Copy and type(b) is Copy:
            assert a.offset + a.length != b.offset
    # encodings
    assert D.decode_delta(D.encode_delta(d), max_size=len(new)) == d
    assert Signature.from_bytes(sig.to_bytes()) == sig
    # streaming
    assert D.signature_file(io.BytesIO(base), bufsize=65536, **kw) == sig
    assert D.delta_file(io.BytesIO(new), sig, bufsize=65536) == d
    out = io.BytesIO()
    assert D.patch_to_file(io.BytesIO(base), d, out, bufsize=4096) == len(new)
    assert out.getvalue() == new
    return d


def literal_bytes(d: Delta) -> int:
    return D.stats(d)[1]


def wire_size(d: Delta) -> int:
    return len(zlib.compress(D.encode_delta(d)))


# ---------------------------------------------------------------------------- mutation cases
TEXT = 300_000


def test_identical_is_one_copy() -> None:
    base = source_text(TEXT)
    assert check(base, base).ops == (Copy(0, len(base)),)


def test_identical_binary_without_newlines_is_one_copy() -> None:
    base = random_bytes(100_000, 1).replace(b"\n", b"")
    assert check(base, base).ops == (Copy(0, len(base)),)


def test_empty_base_is_one_literal() -> None:
    new = source_text(5000)
    d = check(b"", new)
    assert d.ops == (Literal(new),)
    assert D.signature(b"").ends == ()


def test_empty_new_has_no_ops() -> None:
    d = check(source_text(5000), b"")
    assert d.ops == ()
    assert d.new_size == 0


def test_both_empty() -> None:
    assert check(b"", b"") == Delta((), 0, 0)


def test_one_line_inserted_at_the_top_of_2mb_source() -> None:
    base = source_text(2 << 20)
    new = b'#include "fetch_driver/arm.h"\n' + base
    d = check(base, new)
    assert literal_bytes(d) < 2 * TARGET + 100
    assert wire_size(d) < 1500
    assert len(d.ops) == 2


def test_append() -> None:
    base = source_text(TEXT)
    new = base + b"int main() { return 0; }\n"
    d = check(base, new)
    assert literal_bytes(d) < MAX + 100
    assert type(d.ops[0]) is Copy and d.ops[0].offset == 0


def test_insert_in_the_middle() -> None:
    base = source_text(TEXT)
    mid = base.index(b"\n", len(base) // 2) + 1
    new = base[:mid] + b'    ROS_INFO("inserted");\n' + base[mid:]
    d = check(base, new)
    assert literal_bytes(d) < 3 * TARGET
    assert len(d.ops) == 3


def test_insert_in_the_middle_of_a_line() -> None:
    base = source_text(TEXT)
    mid = len(base) // 2
    new = base[:mid] + b"XYZ" + base[mid:]
    assert literal_bytes(check(base, new)) < 3 * TARGET


def test_delete_a_range() -> None:
    base = source_text(TEXT)
    new = base[:100_000] + base[150_000:]
    d = check(base, new)
    assert literal_bytes(d) < 3 * TARGET


def test_swap_two_halves_copies_both() -> None:
    base = source_text(TEXT)
    cut = base.index(b"\n", TEXT // 2) + 1
    new = base[cut:] + base[:cut]
    assert literal_bytes(check(base, new)) < 3 * TARGET


def test_truncate_on_a_chunk_boundary_sends_nothing() -> None:
    base = source_text(TEXT)
    end = D.signature(base).ends[50]
    assert check(base, base[:end]).ops == (Copy(0, end),)


def test_truncate_off_a_chunk_boundary() -> None:
    base = source_text(TEXT)
    end = D.signature(base).ends[50] + 100
    d = check(base, base[:end])
    assert literal_bytes(d) <= MAX
    assert d.ops[0] == Copy(0, D.signature(base).ends[50])


def test_truncate_to_one_byte() -> None:
    base = source_text(TEXT)
    check(base, base[:1])


def test_completely_different() -> None:
    base = source_text(TEXT, seed=1)
    new = random_bytes(TEXT, 2)
    d = check(base, new)
    assert d.ops == (Literal(new),)


def test_binary_without_newlines_is_cut_every_max_bytes() -> None:
    base = random_bytes(100_000, 3).replace(b"\n", b"")
    ends = D.signature(base).ends
    assert ends == tuple(range(MAX, len(base), MAX)) + (len(base),)
    assert literal_bytes(check(base, base + b"more")) <= MAX + 4
    check(base, b"x" + base)  # round trips, though fixed blocks cannot realign


def test_prepend_to_random_binary() -> None:
    base = random_bytes(1 << 20, 4)
    d = check(base, b"\x00\x01prefix" + base)
    assert literal_bytes(d) < 10_000


def test_edits_scattered_in_random_binary() -> None:
    base = random_bytes(1 << 20, 5)
    r = random.Random(5)
    new = bytearray(base)
    for _ in range(10):
        at = r.randrange(len(new))
        new[at : at + r.randrange(50)] = random_bytes(r.randrange(50), r.randrange(1000))
    d = check(base, bytes(new))
    assert literal_bytes(d) < 10 * 3 * TARGET


def test_long_runs_of_zeros() -> None:
    base = bytes(200_000) + source_text(20_000) + bytes(100_000)
    d = check(base, base)
    assert d.ops == (Copy(0, len(base)),)
    new = base[:150_000] + b"\x01" + base[150_000:]
    assert literal_bytes(check(base, new)) <= 2 * MAX
    check(bytes(100), bytes(1 << 20))
    check(bytes(1 << 20), bytes(100))


def test_many_identical_lines() -> None:
    base = b"    }\n" * 100_000
    d = check(base, base)
    assert d.ops == (Copy(0, len(base)),)
    check(base, b"{\n" + base)
    check(base, b"\n" * 50_000)


def test_a_line_longer_than_max() -> None:
    base = source_text(50_000) + b"a" * (3 * MAX + 5) + b"\n" + source_text(50_000, seed=2)
    check(base, base[:60_000] + b"b" + base[60_000:])


def test_cuts_realign_after_an_insert() -> None:
    base = source_text(TEXT)
    new = b"a new first line\n" + base
    old_ends = {e + 17 for e in D.signature(base).ends}
    new_ends = D.signature(new).ends
    assert sum(e in old_ends for e in new_ends) >= len(new_ends) - 2


@pytest.mark.parametrize("data", [source_text(TEXT), random_bytes(TEXT, 6)], ids=["text", "bin"])
def test_chunk_sizes_keep_to_the_parameters(data: bytes) -> None:
    lengths = D.signature(data).lengths()
    assert min(lengths[:-1]) >= MIN
    assert max(lengths) <= MAX
    assert 0.7 * TARGET < len(data) / len(lengths) < 1.3 * TARGET


def test_delta_uses_the_signatures_parameters_and_algorithm() -> None:
    base = source_text(20_000)
    new = base[:5000] + b"changed\n" + base[5000:]
    for name in hashing.available():
        for params in (SMALL, (300, 100, 70_000), (2048, 512, 16384)):
            sig = D.signature(base, algorithm=name, params=params)
            assert sig.algorithm == name and sig.params == params
            assert D.patch(base, D.delta(new, sig)) == new
            check(base, new, algorithm=name, params=params)


def test_algorithms_give_different_digests() -> None:
    base = source_text(5000)
    sigs = {name: D.signature(base, algorithm=name) for name in hashing.available()}
    assert len({s.digests for s in sigs.values()}) == len(sigs)
    for name, sig in sigs.items():
        assert sig.digests[:8] == hashing.chunk_digest(name, base[: sig.ends[0]])


def test_a_chunk_with_a_matching_digest_but_another_length_is_not_copied() -> None:
    base = source_text(5000)
    sig = D.signature(base)
    forged = Signature(
        sig.algorithm, sig.size + 1, sig.params, sig.ends[:-1] + (sig.ends[-1] + 1,), sig.digests
    )
    d = D.delta(base, forged)
    assert D.patch(base + b"?", d) == base
    assert literal_bytes(d) == sig.lengths()[-1]


def test_stats() -> None:
    d = Delta((Copy(0, 10), Literal(b"abc"), Copy(20, 5)), 18)
    assert D.stats(d) == (15, 3)
    assert D.stats(Delta((), 0)) == (0, 0)


# ---------------------------------------------------------------------------- parameters
@pytest.mark.parametrize(
    "params",
    [
        (1024, 256),
        (1024, 256, 8192, 1),
        [1024, 256, 8192],
        (1024.0, 256, 8192),
        (True, 0, 8),
        (256, 256, 8192),
        (1024, 0, 8192),
        (1024, 256, 1000),
        (1024, 256, D.MAX_CHUNK_LIMIT + 1),
        "abc",
        None,
    ],
)
def test_bad_parameters_are_refused(params: Any) -> None:
    with pytest.raises(DeltaError):
        D.check_params(params)
    with pytest.raises(DeltaError):
        D.signature(b"abc", params=params)


def test_parameters_at_the_limits() -> None:
    assert D.check_params((2, 1, 2)) == (2, 1, 2)
    data = source_text(3000)
    check(data, data[100:], params=(2, 1, 2))
    check(data, data[100:], params=(1 << 20, 1, D.MAX_CHUNK_LIMIT))


# ---------------------------------------------------------------------------- signature
@functools.lru_cache(maxsize=None)
def good_signature() -> Signature:
    return D.signature(source_text(20_000), params=SMALL)


def test_signature_roundtrip_uses_two_or_four_byte_lengths() -> None:
    data = source_text(200_000)
    for params, width in ((SMALL, 2), (D.DEFAULT_PARAMS, 2), ((1024, 256, 1 << 17), 4)):
        sig = D.signature(data, params=params)
        raw = sig.to_bytes()
        assert raw[4] == width
        assert len(raw) == D._SIG_HEAD.size + len(sig.algorithm) + sig.count * (width + 8)
        assert Signature.from_bytes(raw) == sig
        assert Signature.from_bytes(bytearray(raw)) == sig
        assert Signature.from_bytes(memoryview(raw)) == sig


def test_signature_repr_is_short() -> None:
    assert len(repr(D.signature(source_text(100_000)))) < 120


@pytest.mark.parametrize(
    "change, message",
    [
        ({"algorithm": "md5"}, "unknown hash algorithm"),
        ({"params": (16, 64, 256)}, "parameters"),
        ({"size": -1}, "bad size"),
        ({"size": True}, "bad size"),
        ({"ends": [1, 2]}, "tuple of integers"),
        ({"ends": (1.0,)}, "tuple of integers"),
        ({"digests": b"x" * 7}, "bytes of digests"),
        ({"digests": bytearray(8)}, "bytes of digests"),
    ],
)
def test_signature_validate_rejects_bad_fields(change: dict[str, Any], message: str) -> None:
    fields = {
        "algorithm": hashing.BLAKE2B_128,
        "size": 10,
        "params": SMALL,
        "ends": (10,),
        "digests": bytes(8),
    }
    Signature(**fields).validate()  # type: ignore[arg-type]
    fields.update(change)
    with pytest.raises(DeltaError, match=message):
        Signature(**fields).validate()  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "ends, size, message",
    [
        ((), 5, "no chunks"),
        ((20, 20, 30), 30, "not increasing"),
        ((30, 20), 20, "not increasing"),
        ((0, 20), 20, "not increasing"),
        ((300,), 300, "longer than MAX"),
        ((20, 300), 300, "longer than MAX"),
        ((10, 30), 30, "shorter than MIN"),
        ((20, 40), 41, "not at the size"),
    ],
)
def test_signature_validate_rejects_bad_ends(
    ends: tuple[int, ...], size: int, message: str
) -> None:
    sig = Signature(hashing.BLAKE2B_128, size, SMALL, ends, bytes(8 * len(ends)))
    with pytest.raises(DeltaError, match=message):
        sig.validate()


def test_signature_last_chunk_may_be_short() -> None:
    Signature(hashing.BLAKE2B_128, 21, SMALL, (20, 21), bytes(16)).validate()
    Signature(hashing.BLAKE2B_128, 0, SMALL, (), b"").validate()


def test_signature_from_truncated_bytes() -> None:
    raw = good_signature().to_bytes()
    for n in range(len(raw)):
        with pytest.raises(DeltaError):
            Signature.from_bytes(raw[:n])
    with pytest.raises(DeltaError):
        Signature.from_bytes(raw + b"\x00")


def test_signature_from_bytes_checks_the_header() -> None:
    raw = bytearray(good_signature().to_bytes())
    for offset, value, message in (
        (0, ord("X"), "bad magic"),
        (3, 2, "bad magic"),
        (4, 3, "width"),
        (D._SIG_HEAD.size, ord("X"), "unknown hash"),
        (5, 200, "do not hold"),
    ):
        bad = bytearray(raw)
        bad[offset] = value
        with pytest.raises(DeltaError, match=message):
            Signature.from_bytes(bytes(bad))


def test_signature_from_bytes_with_a_huge_count_does_not_allocate() -> None:
    head = D._SIG_HEAD.pack(D._SIG_MAGIC, 4, 11, *SMALL, 1 << 60, 0xFFFFFFFF)
    with pytest.raises(DeltaError, match="do not hold"):
        Signature.from_bytes(head + b"blake2b-128")


def test_signature_from_bytes_with_a_non_ascii_name() -> None:
    head = D._SIG_HEAD.pack(D._SIG_MAGIC, 2, 2, *SMALL, 0, 0)
    with pytest.raises(DeltaError, match="ASCII"):
        Signature.from_bytes(head + "é".encode())


def test_signature_from_bytes_checks_lengths_against_params() -> None:
    sig = good_signature()
    raw = bytearray(sig.to_bytes())
    at = D._SIG_HEAD.size + len(sig.algorithm)
    raw[at : at + 2] = (0).to_bytes(2, "little")
    with pytest.raises(DeltaError):
        Signature.from_bytes(bytes(raw))
    raw[at : at + 2] = (MAX + 1).to_bytes(2, "little")
    with pytest.raises(DeltaError):
        Signature.from_bytes(bytes(raw))


# ---------------------------------------------------------------------------- delta validation
@pytest.mark.parametrize(
    "op",
    [
        Copy(-1, 5),
        Copy(0, 0),
        Copy(0, -3),
        Copy(True, 5),
        Copy(0, 2.0),  # type: ignore[arg-type]
        Literal(b""),
        Literal(bytearray(b"ab")),
        Literal("ab"),  # type: ignore[arg-type]
    ],
)
def test_bad_ops_are_refused(op: Any) -> None:
    with pytest.raises(DeltaError):
        op.validate()
    with pytest.raises(DeltaError):
        Delta((op,), 5).validate()


@pytest.mark.parametrize(
    "d, message",
    [
        (Delta((Copy(0, 5),), 6), "make 5 bytes, not 6"),
        (Delta((Literal(b"ab"), Copy(0, 5)), 6), "make 7 bytes"),
        (Delta((Copy(5, 5),), 5, 9), "beyond the base"),
        (Delta(("Copy(0, 5)",), 5), "not an operation"),  # type: ignore[arg-type]
        (Delta([Copy(0, 5)], 5), "tuple"),  # type: ignore[arg-type]
        (Delta((), -1), "bad new size"),
        (Delta((), 0, -1), "bad base size"),
        (Delta((), 0.0), "bad new size"),  # type: ignore[arg-type]
    ],
)
def test_delta_validate(d: Delta, message: str) -> None:
    with pytest.raises(DeltaError, match=message):
        d.validate()
    with pytest.raises(DeltaError):
        D.patch(bytes(100), d)
    with pytest.raises(DeltaError):
        D.encode_delta(d)


def test_patch_refuses_a_copy_beyond_the_base() -> None:
    d = Delta((Literal(b"x"), Copy(95, 10)), 11)
    with pytest.raises(DeltaError, match="beyond"):
        D.patch(bytes(100), d)
    with pytest.raises(DeltaError, match="beyond"):
        D.patch_to_file(io.BytesIO(bytes(100)), d, io.BytesIO())
    assert D.patch(bytes(105), d) == b"x" + bytes(10)


def test_patch_refuses_another_base() -> None:
    base = source_text(10_000)
    d = D.delta(base + b"!", D.signature(base))
    for other in (base[:-1], base + b"x"):
        with pytest.raises(DeltaError, match="made for"):
            D.patch(other, d)
        with pytest.raises(DeltaError, match="made for"):
            D.patch_to_file(io.BytesIO(other), d, io.BytesIO())


def test_patch_to_file_needs_a_positive_bufsize() -> None:
    with pytest.raises(ValueError):
        D.patch_to_file(io.BytesIO(), Delta((), 0), io.BytesIO(), bufsize=0)


def test_literal_repr_is_short() -> None:
    assert repr(Literal(b"x" * 10_000)) == "Literal(<10000 bytes>)"


# ---------------------------------------------------------------------------- delta encoding
@functools.lru_cache(maxsize=None)
def sample_delta() -> Delta:
    base = source_text(20_000)
    new = base[:3000] + b"changed line\n" + base[3100:] + b"tail"
    return D.delta(new, D.signature(base, params=SMALL))


def test_encoding_without_a_base_size_and_with_big_numbers() -> None:
    for d in (
        Delta((Copy(1 << 40, 1 << 33), Literal(b"x")), (1 << 33) + 1),
        Delta((Literal(b"abc"),), 3),
        Delta((), 0),
    ):
        raw = D.encode_delta(d)
        assert D.decode_delta(raw, max_size=1 << 40) == d
        assert D.decode_delta(memoryview(raw), max_size=1 << 40) == d
        assert D.decode_delta(bytearray(raw), max_size=1 << 40) == d


def test_decode_refuses_more_than_max_size() -> None:
    d = sample_delta()
    raw = D.encode_delta(d)
    assert D.decode_delta(raw, max_size=d.new_size) == d
    with pytest.raises(DeltaError, match="allowed"):
        D.decode_delta(raw, max_size=d.new_size - 1)


def test_decode_truncated() -> None:
    raw = D.encode_delta(sample_delta())
    for n in range(len(raw)):
        with pytest.raises(DeltaError):
            D.decode_delta(raw[:n], max_size=1 << 30)


def op_bytes(*ops: bytes, new_size: int = 5, flags: int = 0) -> bytes:
    return D._DELTA_HEAD.pack(D._DELTA_MAGIC, flags, new_size) + b"".join(ops)


@pytest.mark.parametrize(
    "raw, message",
    [
        (b"XSD\x01" + bytes(9), "bad magic"),
        (op_bytes(flags=2), "unknown flags"),
        (op_bytes(flags=1), "truncated header"),
        (op_bytes(b"\x09"), "unknown op"),
        (op_bytes(D._COPY32_S.pack(1, 0, 0)), "empty op"),
        (op_bytes(D._LIT32_S.pack(3, 0)), "empty op"),
        (op_bytes(D._LIT32_S.pack(3, 6) + b"abcdef"), "more than"),
        (op_bytes(D._LIT64_S.pack(4, 1 << 62) + b"abcde"), "runs past the end"),
        (op_bytes(D._COPY64_S.pack(2, 0, 1 << 62)), "more than"),
        (op_bytes(D._COPY32_S.pack(1, 0, 4)), "make 4 bytes, not 5"),
        (op_bytes(D._COPY32_S.pack(1, 10, 5), flags=1)[:-9], "truncated"),
        (op_bytes(D._U64.pack(12) + D._COPY32_S.pack(1, 10, 5), flags=1), "beyond the base"),
    ],
)
def test_decode_refuses_malformed(raw: bytes, message: str) -> None:
    with pytest.raises(DeltaError, match=message):
        D.decode_delta(raw, max_size=1 << 40)


def test_decode_accepts_non_canonical_ops() -> None:
    raw = op_bytes(
        D._LIT32_S.pack(3, 2) + b"ab",
        D._LIT32_S.pack(3, 1) + b"c",
        D._COPY32_S.pack(1, 0, 1),
        D._COPY32_S.pack(1, 1, 1),
        new_size=5,
    )
    d = D.decode_delta(raw, max_size=5)
    assert D.patch(b"xy", d) == b"abcxy"


def test_delta_errors_are_protocol_errors() -> None:
    with pytest.raises(ProtocolError):
        D.decode_delta(b"", max_size=10)


# ---------------------------------------------------------------------------- fuzz
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_decode_random_bytes_raises_only_delta_error(raw: bytes) -> None:
    for data in (raw, D._DELTA_MAGIC + raw, D._DELTA_HEAD.pack(D._DELTA_MAGIC, 1, 50) + raw):
        try:
            d = D.decode_delta(data, max_size=100)
        except DeltaError:
            continue
        d.validate()
        assert d.new_size <= 100


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_signature_from_random_bytes_raises_only_delta_error(raw: bytes) -> None:
    head = D._SIG_HEAD.pack(D._SIG_MAGIC, 2, 11, *SMALL, len(raw), 0)
    for data in (raw, D._SIG_MAGIC + raw, head + b"blake2b-128" + raw):
        try:
            Signature.from_bytes(data).validate()
        except DeltaError:
            pass


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_corrupted_encodings_raise_only_delta_error(data: st.DataObject) -> None:
    sig_raw = bytearray(good_signature().to_bytes())
    delta_raw = bytearray(D.encode_delta(sample_delta()))
    for raw in (sig_raw, delta_raw):
        for _ in range(data.draw(st.integers(1, 4))):
            at = data.draw(st.integers(0, len(raw) - 1))
            raw[at] = data.draw(st.integers(0, 255))
    try:
        Signature.from_bytes(bytes(sig_raw))
    except DeltaError:
        pass
    try:
        D.decode_delta(bytes(delta_raw), max_size=1 << 20)
    except DeltaError:
        pass


# ---------------------------------------------------------------------------- properties
FRAGMENTS = [
    b"",
    b"\n",
    b"}\n",
    b"    return x;\n",
    b"#include <ros/ros.h>\n",
    b"\n\n\n",
    b"a" * 100,
    b"b" * 100 + b"\n",
    bytes(300),
    b"z" * 700 + b"\n",
    source_text(500, seed=11),
    source_text(2000, seed=12),
    source_text(5000, seed=13),
    random_bytes(300, 14),
    random_bytes(3000, 15),
]
pieces = st.one_of(st.sampled_from(FRAGMENTS), st.binary(max_size=50))
contents = st.lists(pieces, max_size=12).map(b"".join)
param_sets = st.sampled_from([SMALL, (32, 8, 40), (2, 1, 3), (300, 40, 300), D.DEFAULT_PARAMS])


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(base=contents, new=contents, params=param_sets)
def test_patch_roundtrip(base: bytes, new: bytes, params: D.Params) -> None:
    sig = D.signature(base, params=params)
    assert Signature.from_bytes(sig.to_bytes()) == sig
    d = D.delta(new, sig)
    assert D.patch(base, d) == new
    assert D.decode_delta(D.encode_delta(d), max_size=len(new)) == d
    assert sum(D.stats(d)) == len(new)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(base=contents, params=param_sets)
def test_a_base_shared_with_new_is_copied(base: bytes, params: D.Params) -> None:
    d = D.delta(base, D.signature(base, params=params))
    assert d.ops == ((Copy(0, len(base)),) if base else ())


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=contents, params=param_sets, bufsize=st.integers(1, 5000))
def test_streaming_cuts_like_in_memory(data: bytes, params: D.Params, bufsize: int) -> None:
    want = chunks_of(data, params)
    got = [
        (o, c) for o, n, _d, c in D.iter_chunks(io.BytesIO(data), params=params, bufsize=bufsize)
    ]
    assert got == want
    assert D.signature_file(io.BytesIO(data), params=params, bufsize=bufsize) == D.signature(
        data, params=params
    )


# ---------------------------------------------------------------------------- streaming
def mixed_data() -> bytes:
    return b"".join(
        [
            source_text(50_000),
            b"q" * 3000 + b"\n",
            random_bytes(40_000, 21),
            bytes(40_000),
            b"\n" * 2000,
            b"L" * (MAX * 3 + 7),
            source_text(30_000, seed=3),
            b"w" * 800,
        ]
    )


@pytest.mark.parametrize("bufsize", [1, 3, 100, 767, 768, 769, 8192, 1 << 20])
def test_iter_chunks_equals_in_memory(bufsize: int) -> None:
    data = mixed_data() if bufsize >= 100 else mixed_data()[:30_000] + b"k" * 2000 + b"\n"
    want = chunks_of(data)
    got = list(D.iter_chunks(io.BytesIO(data), bufsize=bufsize))
    assert [(o, c) for o, _n, _d, c in got] == want
    assert all(n == len(c) for _o, n, _d, c in got)
    sig = D.signature(data)
    assert b"".join(d for _o, _n, d, _c in got) == sig.digests


@pytest.mark.parametrize("bufsize", [1, 7, 100, 333, 4096])
def test_streaming_when_max_cuts_fall_inside_short_lines(bufsize: int) -> None:
    # TARGET = MAX: most chunks reach MAX before a line is accepted, so the
    # cut splits a short line whose start the streaming chunker must keep.
    params = (300, 40, 300)
    data = source_text(20_000)
    got = [
        (o, c) for o, _n, _d, c in D.iter_chunks(io.BytesIO(data), params=params, bufsize=bufsize)
    ]
    assert got == chunks_of(data, params)
    assert sum(len(c) == 300 for _o, c in got) > len(got) // 4


@pytest.mark.parametrize("params", [(4, 1, 4), (6, 1, 6), (8, 2, 8), (16, 2, 20)])
def test_streaming_with_tiny_chunks_and_blocks(params: D.Params) -> None:
    # Every line length around TARGET - MIN, every block boundary, every cut kind.
    r = random.Random(sum(params))
    data = bytes(r.choice(b"ab\n\n") for _ in range(20_000))
    want = chunks_of(data, params)
    for bufsize in (1, 2, 3, 5):
        got = [
            (o, c)
            for o, _n, _d, c in D.iter_chunks(io.BytesIO(data), params=params, bufsize=bufsize)
        ]
        assert got == want, bufsize


class ShortReads(io.RawIOBase):
    """A raw file that returns fewer bytes than asked, as pipes and sockets do."""

    def __init__(self, data: bytes) -> None:
        self._data = data
        self._pos = 0
        self._r = random.Random(0)

    def readable(self) -> bool:
        return True

    def readinto(self, buf: Any) -> int:
        n = min(len(buf), self._r.randint(1, 3000), len(self._data) - self._pos)
        buf[:n] = self._data[self._pos : self._pos + n]
        self._pos += n
        return n


def test_short_reads_cut_like_in_memory() -> None:
    data = mixed_data()
    assert D.signature_file(ShortReads(data)) == D.signature(data)  # type: ignore[arg-type]


def test_streaming_memory_is_bounded() -> None:
    chunker = D._Chunker(D.DEFAULT_PARAMS)
    block = 4096
    biggest = 0
    for data in (b"n" * (1 << 20), source_text(1 << 20), random_bytes(1 << 20, 8), bytes(1 << 20)):
        for at in range(0, len(data), block):
            chunker.feed(data[at : at + block])
            biggest = max(biggest, len(chunker._buf))
    assert biggest <= MAX + TARGET + block


def test_streaming_starts_at_the_current_position() -> None:
    data = source_text(50_000)
    fh = io.BytesIO(b"header" + data)
    fh.seek(6)
    assert D.signature_file(fh) == D.signature(data)


def test_delta_file_and_patch_to_file_on_real_files(tmp_path: Path) -> None:
    base = mixed_data()
    new = base[:70_000] + b"inserted\n" + base[90_000:] + b"end"
    (tmp_path / "base").write_bytes(base)
    (tmp_path / "new").write_bytes(new)
    with open(tmp_path / "base", "rb") as fh:
        sig = D.signature_file(fh, bufsize=10_000)
    with open(tmp_path / "new", "rb") as fh:
        d = D.delta_file(fh, sig, bufsize=10_000)
    assert d == D.delta(new, D.signature(base))
    with open(tmp_path / "base", "rb") as src, open(tmp_path / "out", "wb") as out:
        assert D.patch_to_file(src, d, out, bufsize=1000) == len(new)
    assert (tmp_path / "out").read_bytes() == new


def test_streaming_needs_a_positive_bufsize() -> None:
    with pytest.raises(ValueError):
        D.signature_file(io.BytesIO(b"x"), bufsize=0)


# ---------------------------------------------------------------------------- Python 3.8
PY38_SCRIPT = r"""
import io, json, random, sys
sys.path.insert(0, sys.argv[1])
from fetchsync.protocol import delta as D, hashing

r = random.Random(7)
parts = [b"    x = f(y)\n", b"}\n", b"\n", b"#include <a>\n", b"q" * 900 + b"\n"]
base = b"".join(r.choice(parts) for _ in range(20000)) + bytes(30000)
base += r.getrandbits(8 * 50000).to_bytes(50000, "little")
new = base[:1000] + b"edit\n" + base[5000:] + b"end"
sig = D.signature(base)
assert D.signature_file(io.BytesIO(base), bufsize=777) == sig
d = D.delta(new, sig)
assert D.patch(base, d) == new
out = io.BytesIO()
D.patch_to_file(io.BytesIO(base), d, out)
assert out.getvalue() == new
enc = D.encode_delta(d)
assert D.decode_delta(enc, max_size=len(new)) == d
assert D.Signature.from_bytes(sig.to_bytes()) == sig
print(json.dumps({
    "version": list(sys.version_info[:2]),
    "available": hashing.available(),
    "signature": hashing.digest("blake2b-128", sig.to_bytes()).hex(),
    "delta": hashing.digest("blake2b-128", enc).hex(),
}))
"""


@pytest.mark.skipif(not os.path.exists(PY38), reason="no Python 3.8 at " + PY38)
def test_python38_runs_the_engine_and_agrees(tmp_path: Path) -> None:
    script = tmp_path / "engine38.py"
    script.write_text(PY38_SCRIPT)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    proc = subprocess.run(
        [PY38, "-I", str(script), str(REPO)], capture_output=True, env=env, timeout=60, check=False
    )
    assert proc.returncode == 0, proc.stderr.decode(errors="replace")
    theirs = json.loads(proc.stdout)
    assert theirs["version"] == [3, 8]
    assert hashing.BLAKE2B_128 in theirs["available"]
    # the same script here must give the same bytes, so the two ends agree
    ours = subprocess.run(
        [sys.executable, "-I", str(script), str(REPO)],
        capture_output=True,
        env=env,
        timeout=60,
        check=False,
    )
    assert ours.returncode == 0, ours.stderr.decode(errors="replace")
    mine = json.loads(ours.stdout)
    assert (theirs["signature"], theirs["delta"]) == (mine["signature"], mine["delta"])


def test_signature_file_bytes_is_the_signatures_wire_form():
    """The endpoint's compact signer makes exactly what Signature.to_bytes makes."""
    import io as _io
    import os as _os

    from fetchsync.protocol import delta as _d

    for size in (0, 1, 255, 5000, 300_000):
        data = _os.urandom(size // 2) + b"ab" * (size // 4)
        want = _d.signature(data, algorithm="blake2b-128").to_bytes()
        assert (
            _d.signature_file_bytes(_io.BytesIO(data), algorithm="blake2b-128", bufsize=4096)
            == want
        )


@pytest.mark.parametrize("alg", hashing.available())
def test_delta_and_signature_in_one_pass_equal_the_two_made_apart(alg):
    rng = random.Random(7)
    text = b"".join(b"line %d: %d\n" % (i, rng.randrange(10**6)) for i in range(20000))
    for old, new in [
        (text, b"// a line on top\n" + text),
        (text, text[:5000] + text[9000:]),
        (b"", b"abc"),
        (b"abc", b""),
        (b"", b""),
        (bytes(rng.randrange(256) for _ in range(30000)), text[:40000]),
    ]:
        sig = D.signature(old, algorithm=alg)
        d, new_sig = D.delta_and_signature(new, sig)
        assert new_sig.to_bytes() == D.signature(new, algorithm=alg).to_bytes()
        assert D.patch(old, d) == new and d == D.delta(new, sig)
