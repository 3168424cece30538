"""Wire format: a handshake, then length-prefixed, typed frames with request ids.

Handshake (each side sends one, the endpoint first, unprompted)::

    MAGIC (8 bytes) | u16 version | u32 n | n bytes of JSON capabilities

The client scans the endpoint's stdout for MAGIC, skipping at most
``MAX_NOISE`` bytes, because a login shell may print a banner first.

Frame::

    u32 body_len | u8 type | u8 flags | u32 request_id | body

``body`` is ``u32 json_len | JSON header | blob``; with ``FLAG_ZLIB`` the whole
body is zlib-compressed and ``body_len`` is its compressed size. Every length
is checked against a hard cap *before* anything is allocated or read.
Requests and responses are paired by id, so a client may pipeline requests.

While the endpoint works on a request without writing anything (a cold listing of
a huge tree, hashing a large file, a long syncfs), it sends a ``T_PROGRESS`` frame
(header ``{}``, the request's id) every few seconds, so the client's progress
deadline does not end a healthy call. Only to a client that asked for them in its
hello (``"progress": seconds``), after the endpoint offered them in its own: an
older client's reader refuses an unknown frame type.
"""

import fcntl
import json
import struct
import zlib
from typing import Any, Callable, Dict, List, NamedTuple, Optional

from fetchsync.protocol.errors import ProtocolError

MAGIC = b"\x89FSYNC\r\n"
VERSION = 1
MAX_NOISE = 64 * 1024
MAX_HELLO = 64 * 1024
MAX_FRAME = 64 * 1024 * 1024  # compressed or not, on the wire
MAX_BODY = 96 * 1024 * 1024  # after decompression
MAX_HEADER = 32 * 1024 * 1024

FLAG_ZLIB = 0x01  # the whole body is zlib-compressed
FLAG_ZHEAD = 0x02  # only the JSON header is (the blob carries its own compression)

# frame types
T_REQUEST = 1
T_RESPONSE = 2
T_ERROR = 3  # the request failed as a whole; header {"error": str, "kind": str}
T_PROGRESS = 4  # still working on the request: header {}; only if the client asked
FRAME_TYPES = (T_REQUEST, T_RESPONSE, T_ERROR, T_PROGRESS)

_FRAME = struct.Struct(">IBBI")
_U32 = struct.Struct(">I")
_HELLO = struct.Struct(">HI")

COMPRESS_MIN = 512


class Frame(NamedTuple):
    type: int
    req_id: int
    header: "Dict[str, Any]"
    blob: bytes = b""


def _json_default(obj: "Any") -> "Any":
    raise TypeError("not JSON-serialisable: %r" % type(obj))


def encode_frame(
    frame: "Frame", *, compress: bool = False, compress_blob: bool = True, level: int = 1
) -> bytes:
    head = json.dumps(frame.header, separators=(",", ":"), default=_json_default).encode("utf-8")
    flags = 0
    if compress and not compress_blob and len(head) >= COMPRESS_MIN:
        packed_head = zlib.compress(head, level)
        if len(packed_head) < len(head):
            head = packed_head
            flags |= FLAG_ZHEAD
    body = b"".join((_U32.pack(len(head)), head, frame.blob))
    if compress and compress_blob and len(body) >= COMPRESS_MIN:
        packed = zlib.compress(body, level)
        if len(packed) < len(body):
            body = packed
            flags |= FLAG_ZLIB
    if len(body) > MAX_FRAME:
        raise ProtocolError("frame of %d bytes is over the cap of %d" % (len(body), MAX_FRAME))
    return _FRAME.pack(len(body), frame.type, flags, frame.req_id) + body


def encode_frame_chunks(frame: "Frame", *, compress: bool = False, level: int = 1) -> "List[Any]":
    """:func:`encode_frame`'s frame (its whole body compressed when that is smaller), as
    byte strings to write in order, made without joining the blob into one body or the
    compressed body into one string: the endpoint's answer to a read of a 32 MiB file
    held the file, the body, its compressed form and the frame at once (a pull peaked
    it at 132 MiB; tests/test_endpoint_memory_big.py)."""
    head = json.dumps(frame.header, separators=(",", ":"), default=_json_default).encode("utf-8")
    prefix = _U32.pack(len(head)) + head
    body_len = len(prefix) + len(frame.blob)
    if compress and body_len >= COMPRESS_MIN:
        c = zlib.compressobj(level)
        out = [c.compress(prefix)]
        view = memoryview(frame.blob)
        size = len(out[0])
        shrinks = True
        for start in range(0, len(view), COMPRESS_PIECE):
            if start >= 4 * COMPRESS_PIECE and size >= start:
                shrinks = False  # 4 MiB in and not shrinking (a recording): as it is
                break
            out.append(c.compress(view[start : start + COMPRESS_PIECE]))
            size += len(out[-1])
        if shrinks:
            out.append(c.flush())
            size += len(out[-1])
            if size < body_len:
                if size > MAX_FRAME:
                    raise ProtocolError(
                        "frame of %d bytes is over the cap of %d" % (size, MAX_FRAME)
                    )
                return [_FRAME.pack(size, frame.type, FLAG_ZLIB, frame.req_id)] + [
                    x for x in out if x
                ]
        del out
    if body_len > MAX_FRAME:
        raise ProtocolError("frame of %d bytes is over the cap of %d" % (body_len, MAX_FRAME))
    return [_FRAME.pack(body_len, frame.type, 0, frame.req_id) + prefix, frame.blob]


COMPRESS_PIECE = 1 << 20  # the blob given to one compress() call (its output is joined)


def encode_frame_parts(
    frame: "Frame", blob_parts: "list[bytes]", *, compress: bool = False, level: int = 1
) -> "list[bytes]":
    """A frame whose blob carries its own compression, as byte strings to send in order:
    the blob's parts are not copied into one (a batch's are megabytes)."""
    head = json.dumps(frame.header, separators=(",", ":"), default=_json_default).encode("utf-8")
    flags = 0
    if compress and len(head) >= COMPRESS_MIN:
        packed_head = zlib.compress(head, level)
        if len(packed_head) < len(head):
            head = packed_head
            flags |= FLAG_ZHEAD
    body_len = _U32.size + len(head) + sum(len(p) for p in blob_parts)
    if body_len > MAX_FRAME:
        raise ProtocolError("frame of %d bytes is over the cap of %d" % (body_len, MAX_FRAME))
    return [
        _FRAME.pack(body_len, frame.type, flags, frame.req_id) + _U32.pack(len(head)) + head,
        *blob_parts,
    ]


def decode_body(ftype: int, flags: int, req_id: int, body: bytes) -> "Frame":
    if flags & ~(FLAG_ZLIB | FLAG_ZHEAD) or flags == FLAG_ZLIB | FLAG_ZHEAD:
        raise ProtocolError("unknown frame flags 0x%02x" % flags)
    if ftype not in FRAME_TYPES:
        raise ProtocolError("unknown frame type %d" % ftype)
    if flags & FLAG_ZLIB:
        body = inflate(body, MAX_BODY)
    hlen = _header_length(body[:4], len(body))
    return _frame(ftype, flags, req_id, body[4 : 4 + hlen], body[4 + hlen :])


def _header_length(prefix: bytes, body_len: int) -> int:
    if len(prefix) < 4:
        raise ProtocolError("frame body too short")
    (hlen,) = _U32.unpack(prefix)
    if hlen > MAX_HEADER or 4 + hlen > body_len:
        raise ProtocolError("frame header length %d is out of range" % hlen)
    return int(hlen)


def _frame(ftype: int, flags: int, req_id: int, raw_head: bytes, blob: bytes) -> "Frame":
    if flags & FLAG_ZHEAD:
        raw_head = inflate(raw_head, MAX_HEADER)
    try:
        header = json.loads(raw_head.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ProtocolError("frame header is not JSON: %s" % exc) from None
    if not isinstance(header, dict):
        raise ProtocolError("frame header is not an object")
    return Frame(ftype, req_id, header, blob)


def inflate(data: "bytes | memoryview", limit: int) -> bytes:
    """zlib-decompress ``data``, refusing output over ``limit`` bytes or a truncated stream."""
    try:
        d = zlib.decompressobj()
        out = d.decompress(data, limit)
        if d.unconsumed_tail or not d.eof:
            raise ProtocolError("compressed data is truncated or over %d bytes" % limit)
    except zlib.error as exc:
        raise ProtocolError("corrupt compressed data: %s" % exc) from None
    return out


def inflate_exact(data: "bytes | memoryview", size: int) -> bytearray:
    """zlib-decompress ``data`` into exactly ``size`` bytes (else ProtocolError), grown
    piece by piece as it comes (garbage claiming a large size allocates nothing): one
    ``decompress`` call's output is built in blocks and joined at its end (Python 3.11),
    so a 32 MiB part peaked at ~2.4x its size besides its compressed bytes
    (tests/test_endpoint_memory_big.py)."""
    out = bytearray()
    pos = 0
    view = memoryview(data)
    try:
        d = zlib.decompressobj()
        for start in range(0, len(view), INFLATE_IN):
            tail = view[start : start + INFLATE_IN]  # type: Any
            while tail and not d.eof:
                piece = d.decompress(tail, INFLATE_OUT)
                if len(piece) > size - pos:
                    raise ProtocolError("compressed data is over %d bytes" % size)
                out += piece
                pos += len(piece)
                tail = d.unconsumed_tail
        while not d.eof:  # what it holds of the input consumed (a match's end)
            piece = d.decompress(b"", INFLATE_OUT)
            if not piece or len(piece) > size - pos:
                break
            out += piece
            pos += len(piece)
    except zlib.error as exc:
        raise ProtocolError("corrupt compressed data: %s" % exc) from None
    if not d.eof or pos != size:
        raise ProtocolError("compressed data is truncated or not %d bytes" % size)
    return out


INFLATE_IN = 256 * 1024  # compressed bytes given to one call (unconsumed_tail is a copy)
INFLATE_OUT = 4 << 20  # the most one call makes


# Compress only what a sample shows shrinks below this. zlib -1 runs at ~100 MB/s,
# so sparing 10% (meshes, point clouds) costs more time than it saves on any
# link faster than ~10 MB/s (Wi-Fi's order), and it competes for the CPU with
# reading and hashing.
WORTH_COMPRESSING = 0.85


def compressible(data: bytes, *, level: int = 1, worth: float = WORTH_COMPRESSING) -> bool:
    """Whether a sample of ``data`` (32 KiB: its start, and its middle when it is
    larger) shrinks to ``worth`` of its size or less, enough to make compressing all
    of it worth the time."""
    half = len(data) // 2
    sample = data[:32768] if len(data) <= 65536 else data[:16384] + data[half : half + 16384]
    return len(zlib.compress(sample, level)) <= worth * len(sample)


def pack(data: bytes, *, level: int = 1) -> "tuple[bytes, bool]":
    """``data`` zlib-compressed when a sample shows it shrinks, and whether it was."""
    if len(data) < COMPRESS_MIN or not compressible(data, level=level):
        return data, False  # already compressed (images, archives, bags): do not waste time
    packed = zlib.compress(data, level)
    return (packed, True) if len(packed) < len(data) else (data, False)


# A blob at least this large is read straight into a buffer of its own, when the
# reader can (see Reader): gathering megabytes in the reader's buffer and copying
# them out doubled the endpoint's memory traffic and its peak during a push
DIRECT_MIN = 256 * 1024


class Reader:
    """Reads frames from a ``recv(n) -> bytes`` function (``b""`` at EOF).

    With ``recv_into(view) -> int`` (the bytes it put in ``view``, 0 at EOF), a
    frame's large blob is read into a ``bytearray`` of its own, not copied.
    """

    def __init__(
        self,
        recv: "Callable[[int], bytes]",
        recv_into: "Optional[Callable[[memoryview], Optional[int]]]" = None,
    ) -> None:
        self._recv = recv
        self._recv_into = recv_into
        self._buf = bytearray()
        self.bytes_in = 0

    def _fill(self, n: int) -> bool:
        while len(self._buf) < n:
            chunk = self._recv(max(n - len(self._buf), 1 << 16))
            if not chunk:
                return False
            self.bytes_in += len(chunk)
            self._buf += chunk
        return True

    def _take(self, n: int) -> bytes:
        if not self._fill(n):
            raise EOFError("stream ended after %d of %d bytes" % (len(self._buf), n))
        buf = self._buf
        if len(buf) == n:
            out = bytes(buf)
            buf.clear()
            return out
        view = memoryview(buf)
        out = bytes(view[:n])  # one copy (a slice of the bytearray would be a second)
        view.release()
        del buf[:n]
        return out

    def read_hello(self) -> "Dict[str, Any]":
        """Skip noise up to MAGIC, then read the peer's hello."""
        while True:
            idx = self._buf.find(MAGIC)
            if idx > MAX_NOISE:
                raise ProtocolError(
                    "no fetchsync endpoint answered (got %r...)" % bytes(self._buf[:80])
                )
            if idx >= 0:
                del self._buf[: idx + len(MAGIC)]
                break
            if len(self._buf) > MAX_NOISE + len(MAGIC):
                raise ProtocolError(
                    "no fetchsync endpoint answered (got %r...)" % bytes(self._buf[:80])
                )
            if not self._fill(len(self._buf) + 1):
                noise = bytes(self._buf[:200]).decode("utf-8", "replace").strip()
                raise EOFError("endpoint ended before its hello" + (": " + noise if noise else ""))
        version, n = _HELLO.unpack(self._take(_HELLO.size))
        if n > MAX_HELLO:
            raise ProtocolError("hello of %d bytes is over the cap" % n)
        try:
            hello = json.loads(self._take(n).decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as exc:
            raise ProtocolError("hello is not JSON: %s" % exc) from None
        if not isinstance(hello, dict):
            raise ProtocolError("hello is not an object")
        hello["version"] = version
        return hello

    def read_frame(self) -> "Optional[Frame]":
        """The next frame, or None at a clean end of stream (between frames)."""
        if not self._buf and not self._fill(1):
            return None
        blen, ftype, flags, req_id = _FRAME.unpack(self._take(_FRAME.size))
        # every header field is checked before the body is waited for: garbage
        # must end in an error, not in waiting for bytes that never come
        if blen > MAX_FRAME:
            raise ProtocolError(
                "frame of %d bytes announced, over the cap of %d" % (blen, MAX_FRAME)
            )
        if ftype not in FRAME_TYPES:
            raise ProtocolError("unknown frame type %d" % ftype)
        if flags & ~(FLAG_ZLIB | FLAG_ZHEAD) or flags == FLAG_ZLIB | FLAG_ZHEAD:
            raise ProtocolError("unknown frame flags 0x%02x" % flags)
        if flags & FLAG_ZLIB:
            return decode_body(ftype, flags, req_id, self._take(blen))
        # taken apart, so the blob (up to 8 MiB of a push) is not copied once more
        hlen = _header_length(self._take(min(4, blen)), blen)
        raw_head = self._take(hlen)
        return _frame(ftype, flags, req_id, raw_head, self._take_blob(blen - 4 - hlen))

    def _take_blob(self, n: int) -> "Any":
        """``n`` bytes: a bytearray read in place when that is worth it, else bytes."""
        if self._recv_into is None or n < DIRECT_MIN:
            return self._take(n)
        out = bytearray(n)
        have = min(len(self._buf), n)
        out[:have] = self._buf[:have]
        del self._buf[:have]
        view = memoryview(out)
        pos = have
        try:
            while pos < n:
                got = self._recv_into(view[pos:])
                if not got:
                    raise EOFError("stream ended after %d of %d bytes" % (pos, n))
                pos += got
                self.bytes_in += got
        finally:
            view.release()
        return out


PIPE_SIZE = 1 << 20
_F_SETPIPE_SZ = 1031  # Linux; not named in Python 3.8's fcntl


def widen_pipe(fd: int) -> None:
    """Give the pipe at ``fd`` PIPE_SIZE bytes instead of 64 KiB: a push streams ~100 MB
    through the pipes between sshd and the endpoint, or to a ProxyCommand, and each full
    pipe wakes both ends. The kernel caps the size (/proc/sys/fs/pipe-max-size, 1 MiB by
    default) and refuses it on a non-pipe or another OS: the default serves then."""
    try:
        fcntl.fcntl(fd, _F_SETPIPE_SZ, PIPE_SIZE)
    except (OSError, ValueError):
        pass


def encode_hello(caps: "Dict[str, Any]") -> bytes:
    body = json.dumps(caps, separators=(",", ":")).encode("utf-8")
    return MAGIC + _HELLO.pack(VERSION, len(body)) + body
