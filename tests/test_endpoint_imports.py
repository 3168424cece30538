"""The robot's endpoint starts without the standard library's ``dataclasses`` (and the
``inspect``, ``ast``, ``dis`` it imports): 16 ms of CPU of every endpoint start, before
its hello (protocol/compat.py). Imported from the endpoint archive the loader ships, as
the robot runs it; the laptop's protocol keeps the standard library's dataclasses."""

from __future__ import annotations

import io
import subprocess
import sys
import zipfile
from pathlib import Path

from fetchsync.protocol import loader

PROBE = (
    "import sys; sys.path.insert(0, sys.argv[1]); import fetchsync.protocol.server, "
    "fetchsync.protocol.delta; from fetchsync.protocol import messages as M; "
    "op = M.Op(M.WRITE, 'a', expect=M.ABSENT, hash='00', size=1, source=M.SRC_DATA); "
    "assert op.but(size=2).size == 2 and op == M.Op.from_wire(op.to_wire()); "
    "print(' '.join(m for m in ('dataclasses', 'inspect', 'ast', 'dis') if m in sys.modules))"
)


def test_the_endpoint_imports_no_dataclasses(tmp_path: Path) -> None:
    data, _ = loader.endpoint_archive()
    zipfile.ZipFile(io.BytesIO(data)).extractall(tmp_path)
    out = subprocess.run(
        [sys.executable, "-I", "-c", PROBE, str(tmp_path)], capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == [], out.stdout


def test_the_laptop_keeps_the_standard_librarys_dataclasses() -> None:
    import dataclasses

    from fetchsync.protocol import messages as M

    assert dataclasses.is_dataclass(M.Op)
