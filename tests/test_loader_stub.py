"""The endpoint's command line is a short stub; the loader runs from the robot's cache.

Every endpoint start sends its command line over the link (a push through the master
pays its next spare's): the whole loader made it 4.3 KB. The stub runs a cached loader
only from the user's private cache directory, only if it is the user's regular file,
writable by no one else, and has the SHA-256 the command line names; anything else and
the loader is sent again (and cached again by the loader, after its own checks of the
directory). Another user on the robot cannot get code of theirs run.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

from fetchsync.protocol import loader, wire

ROOT = str(Path(loader.__file__).parents[2])


def start(home: Path) -> tuple[list[bytes], subprocess.CompletedProcess]:
    """Run the real command line as the robot's shell would, answering NEED_LOADER and
    NEED as the client does; what it asked for, in order, and the finished process."""
    cmd, archive = loader.loader_spec(sys.executable)
    env = {"HOME": str(home), "PATH": "/usr/bin:/bin", "PYTHONPATH": ROOT}
    proc = subprocess.Popen(
        ["sh", "-c", f"exec {cmd}"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
    )
    assert proc.stdout is not None and proc.stdin is not None
    asked: list[bytes] = []
    said = b""
    while wire.MAGIC not in said:
        chunk = proc.stdout.read1(1 << 16)
        if not chunk:
            break
        said += chunk
        for need, data in ((loader.NEED_LOADER, loader.LOADER_BYTES), (loader.NEED, b"")):
            if need in said:
                said = said.replace(need, b"", 1)
                asked.append(need)
                proc.stdin.write(data + archive())  # the endpoint follows the loader unasked
                proc.stdin.flush()
    out, err = proc.communicate(b"", timeout=60)
    return asked, subprocess.CompletedProcess(proc.args, proc.returncode, said + out, err)


def cached_loader(home: Path) -> Path:
    (path,) = (home / ".cache" / "fetchsync").glob("loader-*.py")
    return path


def test_the_command_line_is_a_short_stub_not_the_loader():
    cmd, _archive = loader.loader_spec("python3")
    assert len(cmd) < 1700, len(cmd)  # the whole loader: 4,318 characters at e0eb7a5
    assert "zipfile" not in cmd and "py_compile" not in cmd


def test_the_loader_is_sent_once_then_run_from_the_cache(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    asked, got = start(home)
    assert got.returncode == 0 and wire.MAGIC in got.stdout, got.stderr
    assert asked == [loader.NEED_LOADER]  # one round trip: the endpoint came with the loader
    path = cached_loader(home)
    assert path.read_bytes() == loader.LOADER_BYTES
    assert path.stat().st_mode & 0o777 == 0o600
    asked, got = start(home)
    assert got.returncode == 0 and wire.MAGIC in got.stdout, got.stderr
    assert asked == []


def _planted(home: Path) -> Path:
    """A first start, then the cached loader replaced by code that leaves a mark."""
    assert start(home)[1].returncode == 0
    path = cached_loader(home)
    mark = home / "PWNED"
    path.write_text(f"open({str(mark)!r}, 'w').close()\n")
    return mark


def test_a_cached_loader_whose_hash_differs_is_not_run(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    mark = _planted(home)
    asked, got = start(home)
    assert got.returncode == 0 and wire.MAGIC in got.stdout, got.stderr
    assert not mark.exists()
    assert asked[0] == loader.NEED_LOADER
    assert cached_loader(home).read_bytes() == loader.LOADER_BYTES  # cached again


def test_a_right_loader_is_still_refused_from_an_unsafe_place(tmp_path):
    """Right content, wrong keeper: a symlink, a file others may write, a directory
    others may enter: the stub asks for the loader instead of running it."""
    home = tmp_path / "home"
    home.mkdir()
    assert start(home)[1].returncode == 0
    path = cached_loader(home)
    elsewhere = tmp_path / "elsewhere.py"
    elsewhere.write_bytes(loader.LOADER_BYTES)
    path.unlink()
    path.symlink_to(elsewhere)
    assert start(home)[0][:1] == [loader.NEED_LOADER]
    assert not path.is_symlink()
    path.chmod(0o620)
    assert start(home)[0][:1] == [loader.NEED_LOADER]
    assert path.stat().st_mode & 0o777 == 0o600
    path.parent.chmod(0o755)
    assert start(home)[0][:1] == [loader.NEED_LOADER]
    assert path.parent.stat().st_mode & 0o777 == 0o700  # the loader closed it again


def test_another_users_cached_loader_is_not_run(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    assert start(home)[1].returncode == 0
    path = cached_loader(home)
    os.chown(path, 4242, 4242)
    asked, got = start(home)
    assert got.returncode == 0 and asked[:1] == [loader.NEED_LOADER], got.stderr
    assert path.stat().st_uid == os.getuid()


def test_a_loader_damaged_in_transit_is_refused(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    cmd, _archive = loader.loader_spec(sys.executable)
    proc = subprocess.run(
        ["sh", "-c", f"exec {cmd}"],
        input=loader.LOADER_BYTES[:-1] + b"#",
        capture_output=True,
        env={"HOME": str(home), "PATH": "/usr/bin:/bin", "PYTHONPATH": ROOT},
        timeout=60,
    )
    assert proc.returncode != 0 and b"damaged in transit" in proc.stderr
    assert hashlib.sha256(loader.LOADER_BYTES).hexdigest()[:32] in cmd
    assert not list((home / ".cache" / "fetchsync").glob("loader-*"))


def test_a_robot_with_the_endpoint_but_not_this_loader_takes_the_endpoint_sent_with_it(tmp_path):
    """The client sends the endpoint right after the loader, unasked: the loader reads it
    (and checks it) even when its cache holds it already, so none of it is left on stdin
    to be taken for the client's hello."""
    home = tmp_path / "home"
    home.mkdir()
    assert start(home)[1].returncode == 0
    cached_loader(home).unlink()
    asked, got = start(home)
    assert asked == [loader.NEED_LOADER]
    assert got.returncode == 0 and wire.MAGIC in got.stdout, got.stderr


def test_an_endpoint_damaged_after_the_loader_is_refused(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    cmd, archive = loader.loader_spec(sys.executable)
    data = bytearray(archive())
    data[len(data) // 2] ^= 0xFF
    proc = subprocess.run(
        ["sh", "-c", f"exec {cmd}"],
        input=loader.LOADER_BYTES + bytes(data),
        capture_output=True,
        env={"HOME": str(home), "PATH": "/usr/bin:/bin", "PYTHONPATH": ROOT},
        timeout=60,
    )
    assert proc.returncode != 0 and b"endpoint was damaged in transit" in proc.stderr
    assert wire.MAGIC not in proc.stdout
    assert not list((home / ".cache" / "fetchsync").glob("endpoint-*"))
