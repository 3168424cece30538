"""Binary STL meshes, their records split so deflate finds what repeats in them.

A binary STL is an 80-byte header, a little-endian u32 triangle count ``n`` and ``n``
records of 50 bytes: a normal (3 float32), three vertices (9 float32), a u16 attribute.
Deflate sees little of what repeats in them: the normals of a flat face are the same
floats record after record, 38 bytes apart, and most attribute words are 0. ``split``
lays the records out as the header, then the 12 normal bytes of each record as 12
planes (byte 0 of every record, byte 1, ...), then the vertices as they are (36-byte
rows: a vertex shared by neighbouring triangles stays a 12-byte match), then the 2
attribute bytes as 2 planes. ``join`` puts them back.

ISA-L's level 1 (what binary data travels at), level-6 sizes in brackets:

==========================  ============  ===============  ===========================
binary STLs                 raw           plain            split
==========================  ============  ===============  ===========================
ros-industrial/universal_r  4.66 MB (53)  2.119 (2.025)    1.912 (1.819)  -9.8%
fetchrobotics/fetch_ros     2.03 MB (23)  0.808 (0.721)    0.709 (0.651)  -12%
frankaemika/franka_ros      0.12 MB (9)   0.054 (0.053)    0.051 (0.050)  -6%
husky/husky                 3.60 MB (22)  1.353 (1.211)    1.005 (0.905)  -26%
PR2/pr2_common              6.65 MB (47)  2.107 (1.840)    1.701 (1.517)  -19%
bench tree (2,000 files)    13.8 MB (5)   12.553 (12.596)  12.067 (11.927) -3.9%
==========================  ============  ===============  ===========================

All 50 bytes of a record as planes (HDF5's shuffle) is 11.15 MB on the bench's
random floats but 20-66% LARGER than plain on four of the five real repositories
(universal_robot 3.36 vs 2.03 MB at level 6): it breaks the shared vertices apart.

Only a file whose size is exactly ``84 + 50 * n`` with ``n`` from its header is split
(anything else travels as it is); the receiver checks the same and the content's hash
after ``join`` as for any write, so a wrong split cannot land. Both ends: Python 3.6,
standard library, memory of one more copy of the file (at most SIZE_MAX).
"""

import struct
from typing import List, Optional, Union

Bytes = Union[bytes, bytearray, memoryview]

HEADER = 84
RECORD = 50
NORMAL = 12  # bytes of a record that go as planes before the rows ...
ATTR = 48  # ... and those from here on, after them
SIZE_MAX = 8 * 1024 * 1024  # the largest file split: its join holds one more copy on the robot

_COUNT = struct.Struct("<I")


def triangles(data: "Bytes") -> int:
    """The triangle count of ``data`` if it is shaped as a binary STL (at most SIZE_MAX
    bytes), else -1."""
    size = len(data)
    if size < HEADER or size > SIZE_MAX:
        return -1
    (n,) = _COUNT.unpack_from(data, 80)
    return n if size == HEADER + RECORD * n else -1


def split(data: bytes) -> "Optional[bytes]":
    """``data``'s records split (see the module), or None if it is not a binary STL with
    at least one triangle."""
    n = triangles(data)
    if n < 1:
        return None
    width = ATTR - NORMAL
    rows = bytearray(width * n)
    for j in range(width):
        rows[j::width] = data[HEADER + NORMAL + j :: RECORD]
    parts: "List[Bytes]" = [data[:HEADER]]
    parts += [data[HEADER + j :: RECORD] for j in range(NORMAL)]
    parts.append(rows)
    parts += [data[HEADER + j :: RECORD] for j in range(ATTR, RECORD)]
    return b"".join(parts)


def join(blob: "Bytes") -> "Optional[bytearray]":
    """The file ``split`` made ``blob`` of, or None if ``blob`` cannot be one (its size
    and its header's count disagree, or it is over SIZE_MAX)."""
    n = triangles(blob)
    if n < 0:
        return None
    out = bytearray(len(blob))
    view = memoryview(blob)
    out[:HEADER] = view[:HEADER]
    pos = HEADER
    for j in range(NORMAL):
        out[HEADER + j :: RECORD] = view[pos : pos + n]
        pos += n
    width = ATTR - NORMAL
    rows = view[pos : pos + width * n].tobytes()
    for j in range(width):
        out[HEADER + NORMAL + j :: RECORD] = rows[j::width]
    pos += width * n
    for j in range(ATTR, RECORD):
        out[HEADER + j :: RECORD] = view[pos : pos + n]
        pos += n
    return out
