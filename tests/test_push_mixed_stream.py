"""Attack on the mixed-level stream (90c24e1): a batch's text deflated at zlib 6, ended
by a sync flush, then its binary data as raw deflate at level 1, then the checksum made
over both. Whatever the mix (text only, binary only, both; the NUL at 8 KiB's edge or
past it; one byte; either compressor; either level), the robot's own unpacking
(store.unpack_zpart: the length, the stream's end and its checksum checked) must give
back every operation's bytes exactly."""

from __future__ import annotations

import random
import zlib

import pytest

from fetchsync.protocol import messages as M
from fetchsync.protocol import stl
from fetchsync.protocol.store import unpack_zpart
from fetchsync.sync import engine as sync


class _Endpoint:
    stl = True  # takes split meshes (Endpoint.stl): those come back joined

    class conn:  # noqa: N801 - stands for the Connection attribute
        compress = True
        bytes_in = bytes_out = 0
        last_arrival = 0.0  # when the latest answer came


def _part(rng: random.Random) -> bytes:
    kind = rng.randrange(7)
    n = rng.choice([1, 2, 100, 8191, 8192, 8193, 20000, 70000])
    if kind == 0:  # text
        words = [b"int", b"x_%d" % rng.randrange(99), b"=", b";\n", b"  ", b"ros::"]
        out = b" ".join(rng.choice(words) for _ in range(n // 3 + 1))[:n]
        return out or b"x"
    if kind == 1:  # random bytes with NULs: a mesh
        return bytes(rng.randrange(256) if rng.random() > 0.2 else 0 for _ in range(n))
    if kind == 2:  # a NUL right at the 8 KiB edge, or just past it (then it is text)
        edge = rng.choice([8191, 8192])
        return b"a" * edge + b"\0" + b"b" * rng.randrange(3)
    if kind == 3:
        return b"\0" * n  # zeros only
    if kind == 4:
        return rng.randbytes(n).replace(b"\0", b"\1")  # no NUL: text by the test, incompressible
    if kind == 5:
        return b"\0" if rng.random() < 0.5 else _mesh(rng, n // 50)
    return b"line\n" * (n // 5 + 1)


def _mesh(rng: random.Random, n: int) -> bytes:
    """A binary STL of ``n`` triangles (sent split when the batch's level is 6)."""
    return b"solid".ljust(80, b"\0") + n.to_bytes(4, "little") + rng.randbytes(50 * n)


@pytest.mark.parametrize("compressor", ["isal", "zlib"])
def test_every_mix_of_text_and_binary_comes_back_whole_through_the_robots_unpacking(
    monkeypatch, compressor
):
    if compressor == "isal":
        from isal import isal_zlib  # a dependency: never skipped

        monkeypatch.setattr(sync, "_deflate", isal_zlib)
    else:
        monkeypatch.setattr(sync, "_deflate", zlib)
    rng = random.Random(90)
    batcher = sync._Batcher(
        _Endpoint(),  # type: ignore[arg-type]
        policy="preserve",
        epoch="e",
        gen=0,
        progress=None,
        total=0,
    )
    kinds = set()
    split = 0
    for round_ in range(120):
        datas = [_part(rng) for _ in range(rng.randrange(1, 7))]
        kinds.add(tuple(sorted({sync._binary(d) for d in datas})))
        ops = [
            M.Op(M.WRITE, f"f{i}", expect=M.ABSENT, hash="00", size=len(d), source=M.SRC_DATA)
            for i, d in enumerate(datas)
        ]
        for level6 in (True, False):
            batcher.slow = level6
            packed = batcher._pack(round_, [(op, d, True) for op, d in zip(ops, datas)], [])
            blob = b"".join(packed.zparts) + b"".join(packed.raw)
            zlen = sum(len(p) for p in packed.zparts)
            stream, rest = unpack_zpart(blob, [zlen, packed.zpos])
            assert len(rest) == sum(len(r) for r in packed.raw)
            for op, data in zip(packed.ops, datas):
                where = stream if op.z else rest
                got = bytes(where[op.blob[0] : op.blob[0] + op.blob[1]])
                if op.source == M.SRC_STL:
                    split += 1
                    got = bytes(stl.join(got) or b"")
                assert got == data, (
                    round_,
                    level6,
                    [(len(d), sync._binary(d)) for d in datas],
                )
    assert kinds == {(False,), (True,), (False, True)}  # text only, binary only, both
    assert split
