"""The endpoint's command line comes from a local note; the archive is built only on NEED."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from fetchsync.protocol import loader
from fetchsync.protocol.errors import ProtocolError


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(loader, "_cache", None)
    return tmp_path / "fetchsync"


def test_the_note_gives_the_archive_digest_without_building_it(cache, monkeypatch):
    data, digest = loader.endpoint_archive()
    assert hashlib.sha256(data).hexdigest() == digest
    monkeypatch.setattr(loader, "_cache", None)
    assert loader.endpoint_digest() == (digest, len(data))  # builds once, writes the note
    assert len(list(cache.glob("endpoint-*.note"))) == 1

    def no_build():
        raise AssertionError("the archive was built although the note has its digest")

    monkeypatch.setattr(loader, "_cache", None)
    monkeypatch.setattr(loader, "endpoint_archive", no_build)
    cmd, _archive = loader.loader_spec("python3")
    assert f" {digest} {len(data)}" in cmd


def test_a_changed_source_gets_a_new_note(cache, monkeypatch):
    loader.endpoint_digest()
    monkeypatch.setattr(loader, "_cache", None)
    monkeypatch.setattr(loader, "_sources_stamp", lambda here: "0" * 32)
    loader.endpoint_digest()
    assert len(list(cache.glob("endpoint-*.note"))) == 2


def test_a_wrong_note_is_refused_on_need_and_removed(cache, monkeypatch):
    _data, digest = loader.endpoint_archive()
    monkeypatch.setattr(loader, "_cache", None)
    loader.endpoint_digest()
    [note] = cache.glob("endpoint-*.note")
    note.write_text("f" * 64 + " 1234\n")
    monkeypatch.setattr(loader, "_cache", None)
    cmd, archive = loader.loader_spec("python3")
    assert "f" * 64 in cmd
    with pytest.raises(ProtocolError, match="run the command again"):
        archive()
    assert not note.exists()
    monkeypatch.setattr(loader, "_cache", None)
    assert loader.endpoint_digest()[0] == digest


def test_the_loader_puts_site_directories_and_a_venvs_on_the_path(tmp_path):
    """The endpoint runs with -S (no site hooks): the loader adds the site directories
    itself, including a venv's, which Python finds only through site."""
    import subprocess
    import sys
    import sysconfig

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    site_dir = Path(sysconfig.get_path("purelib", vars={"base": str(venv)}))
    (site_dir / "only_in_the_venv.py").write_text("")
    head = loader.LOADER.split("h, n = sys.argv[1]")[0]
    probe = head + "\nimport only_in_the_venv, xxhash\nprint(sys.flags.no_site)"
    got = subprocess.run([str(venv / "bin" / "python"), "-S", "-c", probe], capture_output=True, text=True)
    assert got.returncode == 0 and got.stdout == "1\n", got.stderr
    # the installation's own site-packages, where xxhash was installed, stays reachable
    base = subprocess.run([sys.executable, "-S", "-c", head + "\nimport xxhash"], capture_output=True, text=True)
    assert base.returncode == 0, base.stderr


def test_the_endpoint_imports_nothing_it_needs_only_later():
    """Every connection pays the endpoint's imports before its hello: the modules needed
    only for rare paths (deep removals, a mallopt after the hello, a delivery, a crash)
    are imported there, not when the endpoint starts."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    code = ("import sys; sys.path.insert(0, %r); import fetchsync.protocol.server; "
            "print(' '.join(sorted(m for m in sys.modules if m in %r)))"
            % (str(root), ["shutil", "ctypes", "hashlib", "_hashlib", "shlex", "socket", "uuid",
                           "traceback", "zipfile", "subprocess"]))
    out = subprocess.run([sys.executable, "-S", "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
