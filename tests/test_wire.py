"""Wire framing: each invariant of the format has its own test."""

import io
import os
import struct
import zlib

import pytest

from fetchsync.protocol import wire
from fetchsync.protocol.errors import ProtocolError


def reader_for(data: bytes) -> wire.Reader:
    return wire.Reader(io.BytesIO(data).read)


def test_frame_round_trip_with_and_without_compression():
    for compress in (False, True):
        frame = wire.Frame(wire.T_REQUEST, 42, {"op": "sync", "n": [1, 2]}, b"x" * 5000)
        got = reader_for(wire.encode_frame(frame, compress=compress)).read_frame()
        assert got == frame


def test_compression_is_used_only_when_it_helps():
    compressible = wire.encode_frame(wire.Frame(1, 1, {}, b"a" * 10000), compress=True)
    random = wire.encode_frame(wire.Frame(1, 1, {}, os.urandom(10000)), compress=True)
    assert compressible[5] & wire.FLAG_ZLIB and len(compressible) < 1000
    assert not random[5] & wire.FLAG_ZLIB


def test_hello_skips_login_noise():
    data = b"Welcome to the robot!\nLast login: yesterday\n" + wire.encode_hello({"a": 1})
    assert reader_for(data).read_hello()["a"] == 1


def test_hello_gives_up_after_too_much_noise():
    with pytest.raises(ProtocolError):
        reader_for(b"x" * (wire.MAX_NOISE + 100) + wire.encode_hello({})).read_hello()


def test_announced_oversize_frame_is_refused_before_reading():
    header = struct.pack(">IBBI", wire.MAX_FRAME + 1, wire.T_REQUEST, 0, 1)
    calls = []

    def recv(n):
        calls.append(n)
        return header if len(calls) == 1 else b""

    with pytest.raises(ProtocolError, match="over the cap"):
        wire.Reader(recv).read_frame()
    assert len(calls) == 1


def test_zip_bomb_is_refused():
    body = zlib.compress(b"\0" * (wire.MAX_BODY + 10))
    data = struct.pack(">IBBI", len(body), wire.T_REQUEST, wire.FLAG_ZLIB, 1) + body
    with pytest.raises(ProtocolError):
        reader_for(data).read_frame()


def test_truncated_frame_is_eof_not_garbage():
    data = wire.encode_frame(wire.Frame(1, 1, {"x": 1}, b"abc"))
    with pytest.raises(EOFError):
        reader_for(data[:-2]).read_frame()


def test_clean_end_between_frames_is_none():
    assert reader_for(b"").read_frame() is None


@pytest.mark.parametrize(
    "mutate",
    [
        lambda b: b[:9] + b"\xff\xff\xff\xff" + b[13:],  # header length out of range
        lambda b: b[:4] + b"\x09" + b[5:],  # unknown type
        lambda b: b[:5] + b"\x80" + b[6:],  # unknown flag
        lambda b: b[:13] + b"{not json" + b[22:],  # header not JSON
    ],
)
def test_corrupt_frames_are_protocol_errors(mutate):
    data = wire.encode_frame(wire.Frame(1, 1, {"k": "vvvvvvvvvv"}, b"blob"))
    with pytest.raises(ProtocolError):
        reader_for(mutate(data)).read_frame()


def test_header_must_be_an_object():
    data = wire.encode_frame(wire.Frame(1, 1, {}, b""))
    body = struct.pack(">I", 2) + b"[]"
    data = struct.pack(">IBBI", len(body), 1, 0, 1) + body
    with pytest.raises(ProtocolError, match="object"):
        reader_for(data).read_frame()


@pytest.mark.parametrize("ftype,flags", [(9, 0), (1, 0x80), (1, wire.FLAG_ZLIB | wire.FLAG_ZHEAD)])
def test_a_bad_header_fails_before_its_body_is_awaited(ftype, flags):
    # garbage from a broken robot: a plausible length must not make us wait
    # for a body that never comes
    header = struct.pack(">IBBI", 1000, ftype, flags, 1)
    calls = []

    def recv(n):
        calls.append(n)
        if len(calls) > 1:
            raise AssertionError("read past the header")
        return header

    with pytest.raises(ProtocolError):
        wire.Reader(recv).read_frame()


def test_pack_sends_barely_compressible_data_raw():
    # ~10% compressible (a mesh's float noise): zlib would cost more time than it saves
    data = b"".join(os.urandom(90) + b"\0" * 10 for _ in range(2000))
    assert 0.85 < len(zlib.compress(data, 1)) / len(data) < 0.95
    assert wire.pack(data) == (data, False)
    text = b"int x = 1;\n" * 20000
    packed, z = wire.pack(text)
    assert z and len(packed) < len(text) // 10


@pytest.mark.parametrize("compress", [False, True])
def test_a_frame_in_parts_is_the_frame_with_its_blob_joined(compress):
    header = {"op": "sync", "ops": [{"k": "w", "p": "a" * 40}] * 20}
    parts = [os.urandom(1000), b"", b"x" * 5000]
    frame = wire.Frame(wire.T_REQUEST, 7, header, b"".join(parts))
    joined = b"".join(wire.encode_frame_parts(frame._replace(blob=b""), parts, compress=compress))
    assert joined == wire.encode_frame(frame, compress=compress, compress_blob=False)
    got = wire.Reader(io.BytesIO(joined).read).read_frame()
    assert (got.header, got.blob, got.req_id) == (header, frame.blob, 7)


class _Trickle:
    """A stream that hands out at most ``step`` bytes per call, like a pipe."""

    def __init__(self, data: bytes, step: int) -> None:
        self.data, self.pos, self.step, self.into_calls = data, 0, step, 0

    def read1(self, n: int) -> bytes:
        out = self.data[self.pos : self.pos + min(n, self.step)]
        self.pos += len(out)
        return out

    def readinto(self, view: memoryview) -> int:
        self.into_calls += 1
        out = self.read1(len(view))
        view[: len(out)] = out
        return len(out)


@pytest.mark.parametrize("step", [1000, 300 * 1024, 1 << 30])
def test_a_large_blob_is_read_in_place_whole(step):
    big = os.urandom(wire.DIRECT_MIN + 12345)
    frames = [
        wire.Frame(wire.T_REQUEST, 1, {"op": "sync"}, big),
        wire.Frame(wire.T_REQUEST, 2, {"op": "ping"}, b"small"),
        wire.Frame(wire.T_REQUEST, 3, {"op": "sync"}, big[::-1]),
    ]
    data = b"".join(wire.encode_frame(f) for f in frames)
    stream = _Trickle(data, step)
    reader = wire.Reader(stream.read1, stream.readinto)
    got = [reader.read_frame() for _ in frames]
    assert got == frames
    assert isinstance(got[0].blob, bytearray) and isinstance(got[1].blob, bytes)
    assert stream.into_calls > 0
    assert reader.read_frame() is None
    assert reader.bytes_in == len(data)


def test_a_large_blob_cut_short_is_eof():
    data = wire.encode_frame(wire.Frame(wire.T_REQUEST, 1, {}, b"z" * (wire.DIRECT_MIN * 2)))
    stream = _Trickle(data[:-10], 64 * 1024)
    with pytest.raises(EOFError):
        wire.Reader(stream.read1, stream.readinto).read_frame()
