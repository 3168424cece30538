"""The endpoint's start imports no hashlib: the stub and the loader take SHA-256 from
the interpreter's own ``_sha256`` (``_sha2`` from 3.12), as hashing.py takes ``_blake2``;
importing hashlib loads OpenSSL's ``_hashlib``, 6.9 ms of a ~50 ms start on the bench's
robot, at every connection."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from test_loader_stub import ROOT, start

from fetchsync.protocol import loader, wire


def test_an_endpoint_start_from_the_cache_imports_no_hashlib(tmp_path: Path) -> None:
    home = tmp_path / "home"
    home.mkdir()
    asked, got = start(home)  # the first start caches the loader and the endpoint
    assert got.returncode == 0 and wire.MAGIC in got.stdout, got.stderr
    cmd, _ = loader.loader_spec(f"{sys.executable} -X importtime")
    proc = subprocess.run(
        ["sh", "-c", f"exec {cmd}"],
        input=b"",
        capture_output=True,
        env={"HOME": str(home), "PATH": "/usr/bin:/bin", "PYTHONPATH": ROOT},
        timeout=60,
    )
    assert wire.MAGIC in proc.stdout, proc.stderr[-2000:]  # it said hello
    imported = [
        line.rsplit("|", 1)[-1].strip()
        for line in proc.stderr.decode().splitlines()
        if line.startswith("import time:")
    ]
    assert "fetchsync.protocol.server" in imported  # the endpoint did start
    assert "hashlib" not in imported and "_hashlib" not in imported
