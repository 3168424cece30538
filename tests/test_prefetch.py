"""fetchsync.prefetch: the next files of a push, opened and asked of the disk ahead.

Unit tests of the window (how many files, how many bytes, what is closed) on
real files, and of read_stable taking a descriptor opened ahead: the file may
have changed, been replaced or become a FIFO since, and the read must notice.
The push's use of it is tested in test_local_faults.py.
"""

from __future__ import annotations

import errno
import os
import threading
from pathlib import Path

import pytest

from fetchsync import prefetch as prefetch_mod
from fetchsync import sync
from fetchsync.prefetch import Prefetch

pytestmark = pytest.mark.skipif(not hasattr(os, "posix_fadvise"), reason="no posix_fadvise here")


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@pytest.fixture
def files(tmp_path: Path) -> list[tuple[str, int]]:
    out = []
    for i in range(10):
        data = (b"file %d\n" % i) * (i + 1)
        (tmp_path / f"f{i}").write_bytes(data)
        out.append((f"f{i}", len(data)))
    return out


@pytest.fixture
def advised(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The descriptors posix_fadvise(WILLNEED) was asked for, in order."""
    seen: list[int] = []
    real = os.posix_fadvise

    def spy(fd: int, offset: int, length: int, advice: int) -> None:
        assert advice == os.POSIX_FADV_WILLNEED
        seen.append(fd)
        real(fd, offset, length, advice)

    monkeypatch.setattr(prefetch_mod, "_fadvise", spy)
    return seen


def test_the_next_files_are_open_and_asked_for(tmp_path, files, advised):
    before = open_fds()
    p = Prefetch(str(tmp_path), files, depth=3)
    assert len(p) == 3 and len(advised) == 3 and open_fds() == before + 3
    for i in range(10):
        fd = p.take(f"f{i}")
        assert fd is not None
        assert os.read(fd, 1000) == (tmp_path / f"f{i}").read_bytes()
        os.close(fd)
        assert len(p) == min(3, 9 - i)  # refilled behind the one taken
    assert len(advised) == 10 and open_fds() == before


def test_the_window_is_bounded_in_bytes_but_takes_one_large_file(tmp_path, advised):
    sizes = [600, 600, 600, 5000, 10]
    for i, n in enumerate(sizes):
        (tmp_path / f"f{i}").write_bytes(b"x" * n)
    p = Prefetch(str(tmp_path), [(f"f{i}", n) for i, n in enumerate(sizes)], depth=10, budget=1500)
    assert len(p) == 2                       # 1,200 bytes; a third would pass 1,500
    for i in range(3):
        os.close(p.take(f"f{i}") or -1)
    assert len(p) == 1                       # the 5,000-byte file alone: nothing else is open
    os.close(p.take("f3") or -1)
    assert len(p) == 1                       # then the last one
    p.close()


def test_skipped_files_and_close_leave_nothing_open(tmp_path, files):
    before = open_fds()
    p = Prefetch(str(tmp_path), files, depth=4)
    fd = p.take("f2")  # f0 and f1 were not read through it: closed
    assert fd is not None and len(p) == 4 and open_fds() == before + 5
    os.close(fd)
    assert p.take("f1") is None               # behind the window: read as usual
    assert p.take("not-planned") is None
    p.close()
    p.close()
    assert open_fds() == before and len(p) == 0
    assert p.take("f9") is None                # closed: nothing more is opened


def test_what_cannot_be_opened_is_passed_over(tmp_path, files):
    os.unlink(tmp_path / "f1")
    os.unlink(tmp_path / "f2")
    os.symlink("f0", tmp_path / "f2")         # never followed
    os.unlink(tmp_path / "f3")
    os.mkfifo(tmp_path / "f3")                # opened without waiting for a writer
    p = Prefetch(str(tmp_path), files, depth=3)
    assert p.take("f1") is None and p.take("f2") is None
    fd = p.take("f3")
    assert fd is not None
    os.close(fd)
    p.close()


def test_read_stable_reads_a_file_opened_ahead(tmp_path, files):
    p = Prefetch(str(tmp_path), files)
    data, entry = sync.read_stable(str(tmp_path / "f4"), fd=p.take("f4"))
    assert data == (tmp_path / "f4").read_bytes() and entry.size == len(data)
    p.close()


def test_read_stable_reads_the_new_file_when_the_one_opened_ahead_was_replaced(tmp_path, files):
    p = Prefetch(str(tmp_path), files)
    (tmp_path / "save").write_bytes(b"saved since\n")
    os.rename(tmp_path / "save", tmp_path / "f4")  # an editor's atomic save
    data, _entry = sync.read_stable(str(tmp_path / "f4"), fd=p.take("f4"))
    assert data == b"saved since\n"
    p.close()


def test_read_stable_reports_a_file_opened_ahead_that_vanished(tmp_path, files):
    p = Prefetch(str(tmp_path), files)
    os.unlink(tmp_path / "f4")
    with pytest.raises(FileNotFoundError):
        sync.read_stable(str(tmp_path / "f4"), fd=p.take("f4"))
    p.close()


def test_read_stable_refuses_a_fifo_at_once(tmp_path, files):
    """A file replaced by a FIFO since the scan: an error, not a wait for a writer."""
    os.unlink(tmp_path / "f4")
    os.mkfifo(tmp_path / "f4")
    got: list[BaseException] = []

    def read(fd: int | None) -> None:
        try:
            sync.read_stable(str(tmp_path / "f4"), fd=fd)
        except OSError as exc:
            got.append(exc)

    p = Prefetch(str(tmp_path), files)
    for fd in (p.take("f4"), None):  # opened ahead, and opened by the read itself
        t = threading.Thread(target=read, args=(fd,), daemon=True)
        t.start()
        t.join(10)
        assert not t.is_alive(), "read_stable waited on a FIFO"
    p.close()
    assert [getattr(e, "errno", None) for e in got] == [errno.EBUSY, errno.EBUSY]
    assert "no longer a regular file" in str(got[0])


def test_read_stable_closes_the_descriptor_it_was_given_when_it_fails_first(tmp_path, files,
                                                                           monkeypatch):
    def hook(full: str, what: str) -> None:
        raise OSError(errno.EIO, "the disk failed")

    monkeypatch.setattr(sync, "read_hook", hook)
    fd = os.open(tmp_path / "f0", os.O_RDONLY)
    with pytest.raises(OSError):
        sync.read_stable(str(tmp_path / "f0"), fd=fd)
    with pytest.raises(OSError) as exc:
        os.fstat(fd)
    assert exc.value.errno == errno.EBADF
