"""The endpoint's command line comes from a local note; the archive is built only on NEED."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

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
    got = subprocess.run(
        [str(venv / "bin" / "python"), "-S", "-c", probe], capture_output=True, text=True
    )
    assert got.returncode == 0 and got.stdout == "1\n", got.stderr
    # the installation's own site-packages, where xxhash was installed, stays reachable
    base = subprocess.run(
        [sys.executable, "-S", "-c", head + "\nimport xxhash"], capture_output=True, text=True
    )
    assert base.returncode == 0, base.stderr


def test_the_endpoint_imports_nothing_it_needs_only_later():
    """Every connection pays the endpoint's imports before its hello: the modules needed
    only for rare paths (deep removals, a mallopt after the hello, a delivery, a crash)
    are imported there, not when the endpoint starts."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    code = (
        "import sys; sys.path.insert(0, %r); import fetchsync.protocol.server; "
        "print(' '.join(sorted(m for m in sys.modules if m in %r)))"
        % (
            str(root),
            [
                "shutil",
                "ctypes",
                "hashlib",
                "_hashlib",
                "shlex",
                "socket",
                "uuid",
                "traceback",
                "zipfile",
                "subprocess",
            ],
        )
    )
    out = subprocess.run(
        [sys.executable, "-S", "-c", code], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == ""


def _run_loader(home: Path, *, umask: int = 0o022) -> tuple[Any, bytes]:
    """The real loader command, as the robot's shell runs it: the archive sent on NEED,
    then end of input (the endpoint says hello and ends)."""
    import subprocess
    import sys

    from fetchsync.protocol import wire

    cmd, archive = loader.loader_command(sys.executable)
    env = {
        "HOME": str(home),
        "PATH": "/usr/bin:/bin",
        "PYTHONPATH": str(Path(loader.__file__).parents[2]),
    }
    proc = subprocess.Popen(
        ["sh", "-c", f"umask {umask:03o}; exec {cmd}"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
    )
    first = proc.stdout.read(len(loader.NEED))
    if first == loader.NEED:
        proc.stdin.write(archive)
        proc.stdin.flush()
    out, err = proc.communicate(b"", timeout=60)
    assert proc.returncode is not None
    return subprocess.CompletedProcess(proc.args, proc.returncode, first + out, err), wire.MAGIC


def test_the_endpoint_cache_is_private_whatever_the_umask(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    (got, magic) = _run_loader(home, umask=0o000)
    assert got.returncode == 0 and got.stdout.startswith(loader.NEED) and magic in got.stdout, (
        got.stderr
    )
    d = home / ".cache" / "fetchsync"
    assert d.stat().st_mode & 0o777 == 0o700
    found = list(d.rglob("*"))
    assert any(p.name.endswith(".pyz") for p in found) and any(p.is_dir() for p in found)
    for p in found:
        assert p.stat().st_mode & 0o077 == 0, f"{p} is open to others"
    (again, _magic) = _run_loader(home, umask=0o000)
    assert again.returncode == 0 and not again.stdout.startswith(loader.NEED)  # the cache is used


def test_a_cache_changed_by_another_user_is_not_run(tmp_path):
    """The zip is checked by its hash (a same-size substitute is refused), and an
    extracted tree holding another user's file, or open to others, is extracted again."""
    import os

    home = tmp_path / "home"
    home.mkdir()
    assert _run_loader(home)[0].returncode == 0
    d = home / ".cache" / "fetchsync"
    [zip_path] = d.glob("endpoint-*.pyz")
    [tree] = [p for p in d.iterdir() if p.is_dir()]
    server = next(tree.rglob("server.py"))
    # another user planted code in the tree, and a same-size zip
    data = zip_path.read_bytes()
    zip_path.write_bytes(data[:-20] + b"\0" * 20)
    for pyc in tree.rglob("server.*.pyc"):
        pyc.unlink()
    server.write_text("import sys\nsys.stderr.write('INJECTED')\nsys.exit(9)\n")
    os.chown(server, 4242, 4242)
    got = _run_loader(home)[0]
    assert got.returncode == 0 and b"INJECTED" not in got.stderr, got.stderr
    assert got.stdout.startswith(loader.NEED)  # the damaged zip was sent again
    assert zip_path.read_bytes() == data
    assert next(tree.rglob("server.py")).stat().st_uid == os.getuid()


def test_another_users_cache_directory_is_refused_with_one_line(tmp_path):
    import os

    home = tmp_path / "home"
    (home / ".cache" / "fetchsync").mkdir(parents=True)
    os.chown(home / ".cache" / "fetchsync", 4242, 4242)
    got = _run_loader(home)[0]
    assert got.returncode != 0 and b"another user" in got.stderr and b"Traceback" not in got.stderr
    os.chown(home / ".cache" / "fetchsync", os.getuid(), os.getgid())
    (home / ".cache" / "fetchsync").rmdir()
    (home / ".cache" / "fetchsync").symlink_to(tmp_path)
    got = _run_loader(home)[0]
    assert got.returncode != 0 and b"symlink" in got.stderr and b"Traceback" not in got.stderr
