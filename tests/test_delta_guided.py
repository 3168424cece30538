"""delta_and_signature's guided chunking cuts exactly where the chunker cuts.

The new signature a push stores is the base of the next delta: were one cut
placed differently from :func:`signature`'s, the next edit would find fewer
copies. These tests compare it byte for byte with the full chunker's over
edits of every kind, including data with long lines, no newlines (MAX cuts),
repeated lines and several edited regions, and check that a signature the
chunker did not make (a robot's lie) still gives a delta that patches right.
"""

from __future__ import annotations

import random

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fetchsync.protocol import delta as D
from fetchsync.protocol import hashing

SMALL = (64, 16, 256)
PARAMS = [D.DEFAULT_PARAMS, SMALL, (40, 8, 48)]


def _text(rng: random.Random, size: int) -> bytes:
    out, n = [], 0
    while n < size:
        kind = rng.random()
        if kind < 0.05:
            line = b"x" * rng.randrange(200, 3000)  # a long line: over MIN, TARGET, MAX
        elif kind < 0.15:
            line = b"}"  # a frequent short line
        elif kind < 0.2:
            line = b""
        else:
            line = b"%d = %d;" % (rng.randrange(1000), rng.randrange(10**6))
        out.append(line + b"\n")
        n += len(line) + 1
    return b"".join(out)


def _binary(rng: random.Random, size: int) -> bytes:
    return rng.getrandbits(8 * size).to_bytes(size, "little") if size else b""


def _no_newlines(rng: random.Random, size: int) -> bytes:
    return bytes(rng.randrange(1, 10) for _ in range(size))


def _edit(rng: random.Random, data: bytes, edits: int) -> bytes:
    for _ in range(edits):
        at = rng.randrange(len(data) + 1)
        kind = rng.randrange(4)
        piece = rng.choice([b"// a line\n", b"\n", b"y" * rng.randrange(1, 600), b"a\nb\nc"])
        if kind == 0:
            data = data[:at] + piece + data[at:]
        elif kind == 1:
            data = data[:at] + data[at + rng.randrange(1, 2000) :]
        elif kind == 2:
            data = data[:at] + piece + data[at + len(piece) :]
        else:
            data = piece + data if rng.random() < 0.5 else data + piece
    return data


def _same_as_apart(base: bytes, new: bytes, params: D.Params, alg: str) -> None:
    sig = D.signature(base, algorithm=alg, params=params)
    d, new_sig = D.delta_and_signature(new, sig)
    assert new_sig.to_bytes() == D.signature(new, algorithm=alg, params=params).to_bytes()
    assert d == D.delta(new, sig)
    assert D.patch(base, d) == new


@pytest.mark.parametrize("params", PARAMS)
@pytest.mark.parametrize("make", [_text, _binary, _no_newlines])
def test_guided_cuts_equal_the_chunkers_over_random_edits(params, make):
    rng = random.Random(hash((params, make.__name__)) & 0xFFFF)
    for size in (0, 1, 300, 5000, 60000):
        base = make(rng, size)
        for edits in (0, 1, 2, 5):
            _same_as_apart(base, _edit(rng, base, edits), params, hashing.FALLBACK)


@pytest.mark.parametrize("alg", hashing.available())
def test_guided_cuts_equal_the_chunkers_for_a_line_on_top_of_a_large_source(alg):
    rng = random.Random(3)
    base = _text(rng, 400_000)
    for new in (
        b"// generated, revision 1\n" + base,
        base[:200_000] + b"int x;\n" + base[200_000:],
        base + b"// end\n",
        base[:-5000],
        base[1:],
        base[:100_000] + base[100_000:][::-1],
        base * 2,
    ):
        _same_as_apart(base, new, D.DEFAULT_PARAMS, alg)


def test_a_repeated_chunk_does_not_put_the_guesses_out_of_step():
    """Equal chunks at several places of the base: a resumption at one of them guesses
    the chunk after that one, which may not be the one after the edited place."""
    unit = b"".join(b"line %d of a block;\n" % i for i in range(200))
    base = unit * 6 + b"tail\n" * 50
    for new in (unit * 3 + b"// new\n" + unit * 3 + b"tail\n" * 50, unit + base, base[:-7]):
        for params in PARAMS:
            _same_as_apart(base, new, params, hashing.FALLBACK)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    base=st.lists(st.sampled_from([b"a", b"bb\n", b"\n", b"}\n", b"x" * 50, b"long line\n"])),
    cuts=st.lists(st.tuples(st.integers(0, 2000), st.binary(max_size=60)), max_size=4),
)
def test_guided_cuts_equal_the_chunkers_property(base, cuts):
    old = b"".join(base)
    new = old
    for at, piece in cuts:
        at %= len(new) + 1
        new = new[:at] + piece + new[at + len(piece) // 2 :]
    for params in PARAMS:
        _same_as_apart(old, new, params, hashing.FALLBACK)


def test_a_signature_the_chunker_did_not_make_still_patches_right():
    """A robot may send any well-formed signature: the cuts then differ from the
    chunker's, but every digest names its own bytes, so deltas stay correct."""
    rng = random.Random(5)
    base = _text(rng, 50_000)
    digest = hashing.chunk_digester(hashing.FALLBACK)
    lo, hi = D.DEFAULT_PARAMS[1:]
    ends, end = [], 0
    while end < len(base):
        end = min(len(base), end + rng.randrange(lo, hi))
        ends.append(end)
    starts = [0, *ends[:-1]]
    lie = D.Signature(
        hashing.FALLBACK,
        len(base),
        D.DEFAULT_PARAMS,
        tuple(ends),
        b"".join(digest(base[a:b]) for a, b in zip(starts, ends)),
    )
    lie.validate()
    new = b"// top\n" + base[:30_000] + b"mid\n" + base[30_000:]
    d, new_sig = D.delta_and_signature(new, lie)
    assert D.patch(base, d) == new
    new_sig.validate()
    ends2 = (0, *new_sig.ends)
    for i in range(new_sig.count):
        chunk = new[ends2[i] : ends2[i + 1]]
        assert new_sig.digests[8 * i : 8 * i + 8] == digest(chunk)
    newer = new[:1000] + b"again\n" + new[1000:]
    assert D.patch(new, D.delta(newer, new_sig)) == newer


@pytest.mark.parametrize("params", [SMALL, (40, 8, 48)])
def test_a_chunk_equal_to_the_bases_after_a_longer_line_does_not_resume_the_guesses(params):
    """A long line made longer by a multiple of MAX: the chunks cut inside it and the one
    ending it are the base's, but the next line's seed (the long line's length) is not,
    so the chunker may cut the next lines elsewhere: equal bytes alone do not put it back
    in step, the line before the cut must lie within the chunk too."""
    hi = params[2]
    for seed in range(60):
        rng = random.Random(seed)
        head = b"".join(b"a%d;\n" % rng.randrange(1000) for _ in range(40))
        # lines whose cut the seed decides: at least MIN long, shorter than TARGET - MIN
        tail = b"".join(b"y" * rng.randrange(1, 60) + b";\n" for _ in range(300))
        n = rng.randrange(300, 1500)
        base = head + b"x" * n + b"\n" + tail
        for k in (1, 2, 3):
            _same_as_apart(
                base, b"zz\n" + head + b"x" * (n + k * hi) + b"\n" + tail, params, "blake2b-128"
            )
