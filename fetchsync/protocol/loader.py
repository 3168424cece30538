"""Delivery of the robot-side endpoint over the connection itself.

The client runs a short loader with ``python3 -c`` on the robot. The loader
refuses a Python older than 3.8 with a message that says so (the endpoint
itself would fail with a SyntaxError that says nothing useful), then looks
for the endpoint (a zip of ``fetchsync.protocol``) in the user's cache
directory under its content hash; when it is missing it says ``NEED`` and
reads exactly that many bytes from stdin, checks their hash and caches them.
Nothing is installed with root and nothing is downloaded by the robot.
"""

from __future__ import annotations

import hashlib
import io
import os
import shlex
import zipfile
from typing import Tuple

NEED = b"FSYNC-NEED\n"

LOADER = r"""
import sys, os, hashlib
if sys.version_info < (3, 8):
    sys.exit("python %d.%d.%d on the robot is too old, fetchsync needs python3 >= 3.8: install one (apt install python3.8) and set FETCHSYNC_REMOTE_PYTHON=python3.8" % tuple(sys.version_info[:3]))
h, n = sys.argv[1], int(sys.argv[2])
d = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "fetchsync")
p = os.path.join(d, "endpoint-" + h[:32] + ".pyz")
if not os.path.isfile(p):
    o = sys.stdout.buffer
    o.write(b"FSYNC-NEED\n")
    o.flush()
    b = sys.stdin.buffer.read(n)
    if hashlib.sha256(b).hexdigest() != h:
        sys.exit("fetchsync: the endpoint was damaged in transit")
    os.makedirs(d, exist_ok=True)
    t = p + ".%d.tmp" % os.getpid()
    with open(t, "wb") as f:
        f.write(b)
    os.replace(t, p)
sys.path.insert(0, p)
from fetchsync.protocol.server import main
main()
""".strip()

_PACKAGE_INIT = b'"""fetchsync robot-side endpoint (the protocol package only)."""\n'
_cache = None  # type: Tuple[bytes, str] | None


def endpoint_archive() -> Tuple[bytes, str]:
    """The endpoint as a deterministic zip, and its sha256 (hex)."""
    global _cache
    if _cache is not None:
        return _cache
    here = os.path.dirname(os.path.abspath(__file__))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        def add(name: str, data: bytes) -> None:
            info = zipfile.ZipInfo(name, date_time=(2020, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, data)
        add("fetchsync/__init__.py", _PACKAGE_INIT)
        for name in sorted(os.listdir(here)):
            if name.endswith(".py"):
                with open(os.path.join(here, name), "rb") as fh:
                    add("fetchsync/protocol/" + name, fh.read())
    data = buf.getvalue()
    _cache = (data, hashlib.sha256(data).hexdigest())
    return _cache


def loader_command(python: str = "python3") -> Tuple[str, bytes]:
    """The remote command line that starts the endpoint, and the archive to send on NEED."""
    data, digest = endpoint_archive()
    cmd = "%s -c %s %s %d" % (python, shlex.quote(LOADER), digest, len(data))
    return cmd, data
