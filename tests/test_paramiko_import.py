"""paramiko imported without importlib.metadata (fetchsync/config.py's import_paramiko):
its ``__version__`` comes from its own dist-info's name, as importlib.metadata would
say it, and nothing of the stand-in is left behind (issue 24: ~30 ms of CPU of every
push that connects without a connection master)."""

from __future__ import annotations

import subprocess
import sys


def _run(code: str) -> str:
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    return out.stdout.strip()


def test_paramiko_imports_without_importlib_metadata_and_with_its_version() -> None:
    code = (
        "import sys; from fetchsync.config import import_paramiko; p = import_paramiko(); "
        "print('importlib.metadata' in sys.modules, p.__version__, p.Transport._CLIENT_ID); "
        "from importlib import metadata; print(metadata.version('paramiko'), "
        "metadata.__file__ is not None)"
    )
    first, second = _run(code).splitlines()
    loaded, version, client_id = first.split()
    real, real_module = second.split()
    assert loaded == "False"  # paramiko's import did not load it
    assert version == real and client_id == f"paramiko_{real}"
    assert real_module == "True"  # a later import gets the real importlib.metadata


def test_a_process_that_has_importlib_metadata_keeps_it() -> None:
    code = (
        "import sys; from importlib import metadata; m = sys.modules['importlib.metadata']; "
        "from fetchsync.config import import_paramiko; p = import_paramiko(); "
        "print(sys.modules['importlib.metadata'] is m, p.__version__ == metadata.version('paramiko'))"
    )
    assert _run(code) == "True True"


def test_importlib_metadata_stays_itself_while_paramiko_imports() -> None:
    """Another import of importlib.metadata while paramiko's import runs (another thread of
    a fleet push, or paramiko's own modules) gets the real one: a stand-in put in
    sys.modules made a fleet's robot fail with "'importlib.metadata' is not a package"."""
    code = (
        "import sys\n"
        "seen = []\n"
        "class Probe:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'paramiko.transport' and not seen:\n"
        "            seen.append(1)\n"
        "            import importlib.metadata._text\n"
        "            from importlib import metadata\n"
        "            seen.append(metadata.version('paramiko'))\n"
        "        return None\n"
        "sys.meta_path.insert(0, Probe())\n"
        "from fetchsync.config import import_paramiko\n"
        "p = import_paramiko()\n"
        "print(seen[1] == p.__version__, 'paramiko' in sys.modules)\n"
    )
    assert _run(code) == "True True"


def test_paramiko_from_threads_at_once() -> None:
    code = (
        "import threading, sys\n"
        "from fetchsync.config import import_paramiko\n"
        "got = []\n"
        "def one():\n"
        "    got.append(import_paramiko().Transport._CLIENT_ID)\n"
        "def other():\n"
        "    from importlib import metadata\n"
        "    got.append('paramiko_' + metadata.version('paramiko'))\n"
        "ts = [threading.Thread(target=one if i % 2 else other) for i in range(8)]\n"
        "[t.start() for t in ts]; [t.join() for t in ts]\n"
        "print(len(got), len(set(got)))\n"
    )
    assert _run(code) == "8 1"
