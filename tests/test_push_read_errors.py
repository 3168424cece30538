"""A laptop file that cannot be read when a push reads it, over the real sshd.

Between the scan (a stat) and the read that hashes or sends a file, the file may
be replaced by a FIFO or a directory. The push then reports that one file in a
line (the push fails: exit 5 in the CLI), the robot keeps its version, the other
files still go, and nothing waits: a plain open() of a FIFO waits for a writer
forever (it hung the push and the watch agent). The batcher's own failures (the
link lost while a big file goes up in pieces) stay what they are, not the
file's read error.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Callable, Iterator

import pytest
from helpers import make_workspace

from fetchsync.errors import LinkLostError
from fetchsync.link.connection import Connection
from fetchsync.link.ssh import SSHTransport
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State

pytestmark = pytest.mark.ssh


@pytest.fixture
def robot(ssh_home, remote_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator:
    """A workspace pushed over the real sshd: its Syncer, local src and the robot's src."""
    monkeypatch.setattr(sync, "BIG", 512 * 1024)  # big files go in pieces ...
    monkeypatch.setattr(sync, "PIECE", 128 * 1024)  # ... of this size
    make_workspace(tmp_path / "ws")
    src = tmp_path / "ws/src"
    (src / "my_pkg/data.txt").write_bytes(b"".join(b"line %d\n" % i for i in range(12000)))
    (src / "my_pkg/big.bin").write_bytes(os.urandom(1024 * 1024))
    conn = Connection.open(SSHTransport.connect("robot", connect_timeout=10.0))
    state = State(tmp_path / "state.sqlite")
    s = sync.Syncer(
        conn, state, local_root=str(src), remote_workspace=str(remote_dir), rules=sync.build_rules()
    )
    assert s.push().errors == []
    yield s, src, remote_dir / "src"
    conn.close()
    state.close()


def to_fifo(path: Path) -> None:
    path.unlink()
    os.mkfifo(path)


def to_dir(path: Path) -> None:
    path.unlink()
    path.mkdir()


def at_open(monkeypatch: pytest.MonkeyPatch, name: str, action: Callable[[Path], None], nth: int):
    """Run ``action`` on the file ``name`` at the ``nth`` time a push is about to open it
    (1: to hash it, the scan having found it changed; 2: to send it)."""
    seen = [0]

    def hook(full: str, event: str) -> None:
        if os.path.basename(full) == name and event == "open":
            seen[0] += 1
            if seen[0] == nth:
                action(Path(full))

    monkeypatch.setattr(sync, "read_hook", hook)


def push_within(s: sync.Syncer, fifo: Path | None, seconds: float = 30) -> sync.Report:
    """``s.push()``, failing the test if it waited more than ``seconds`` on ``fifo`` (a
    writer then opens it, which lets a push stuck opening it go on)."""
    done = threading.Event()
    waited: list[float] = []

    def unstick() -> None:
        if done.wait(seconds) or fifo is None:
            return
        while not done.is_set():
            try:
                os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
                waited.append(seconds)
            except OSError:  # no reader (ENXIO), or not a FIFO any more
                pass
            done.wait(0.2)

    t = threading.Thread(target=unstick, daemon=True)
    t.start()
    try:
        report = s.push()
    finally:
        done.set()
        t.join()
    assert not waited, f"the push waited on {fifo} for more than {seconds} s"
    return report


@pytest.mark.parametrize("name", ["data.txt", "big.bin"])
@pytest.mark.parametrize(("swap", "nth"), [(to_fifo, 1), (to_fifo, 2), (to_dir, 1), (to_dir, 2)])
def test_a_file_swapped_before_its_read_is_reported_and_the_robot_keeps_its_version(
    robot, monkeypatch, name, swap, nth
):
    s, src, robot_src = robot
    f = src / "my_pkg" / name
    old = (robot_src / "my_pkg" / name).read_bytes()
    f.write_bytes(f.read_bytes()[:-10] + b"0123456789")  # the scan sees it changed
    (src / "my_pkg/CMakeLists.txt").write_text("project(my_pkg)  # edited\n")
    at_open(monkeypatch, name, swap, nth)
    r = push_within(s, f if swap is to_fifo else None)
    assert [e["path"] for e in r.errors] == [f"my_pkg/{name}"], r.errors
    assert "regular file" in r.errors[0]["error"] or "directory" in r.errors[0]["error"]
    assert len(r.errors[0]["error"].splitlines()) == 1
    assert (robot_src / "my_pkg" / name).read_bytes() == old  # the robot's version kept
    assert (robot_src / "my_pkg/CMakeLists.txt").read_text() == "project(my_pkg)  # edited\n"
    # a regular file there again: it goes
    monkeypatch.setattr(sync, "read_hook", None)
    (f.rmdir() if f.is_dir() else f.unlink())
    f.write_bytes(b"back\n")
    r = s.push()
    assert r.errors == [] and (robot_src / "my_pkg" / name).read_bytes() == b"back\n"


def test_the_link_lost_during_a_big_files_upload_is_the_links_error(robot, monkeypatch):
    s, src, robot_src = robot
    f = src / "my_pkg/big.bin"
    old = (robot_src / "my_pkg/big.bin").read_bytes()
    f.write_bytes(os.urandom(1024 * 1024))
    pieces = [0]

    def hook(full: str, event: str) -> None:
        if os.path.basename(full) == "big.bin" and event == "read":
            pieces[0] += 1
            if pieces[0] == 3:  # two pieces are on their way: the link goes
                s.conn.transport.close()

    monkeypatch.setattr(sync, "read_hook", hook)
    with pytest.raises(LinkLostError):
        s.push()
    assert (robot_src / "my_pkg/big.bin").read_bytes() == old


def test_a_sender_threads_failure_is_not_the_files_read_error(robot, monkeypatch):
    """An OSError of the batcher's sender thread (a progress callback's on a closed
    terminal, say) ends the push as itself, raised at the batcher's next batch: not
    reported as the big file being read as that batch filled, while the push went on
    reading the rest of the tree for batches that would never go."""
    s, src, robot_src = robot
    (src / "my_pkg/big.bin").write_bytes(os.urandom(3 * 1024 * 1024))  # 24 pieces, 3 batches
    for i in range(20):
        (src / f"my_pkg/z{i:02}.txt").write_text(f"{i}\n" * 1000)
    failed = threading.Event()
    opened_after: list[str] = []
    real_send = sync._Batcher._send

    def send(self: sync._Batcher, b: object) -> None:
        if not failed.is_set():
            self._failure = BrokenPipeError(32, "Broken pipe")  # as _send_loop records it
            failed.set()
            return
        real_send(self, b)

    pieces = [0]

    def hook(full: str, event: str) -> None:
        name = os.path.basename(full)
        if name == "big.bin" and event == "read":
            pieces[0] += 1
            if pieces[0] == 10:  # the first batch (8 pieces) went to the sender meanwhile
                assert failed.wait(30)
        elif failed.is_set() and event == "open":
            opened_after.append(name)

    monkeypatch.setattr(sync._Batcher, "_send", send)
    monkeypatch.setattr(sync, "read_hook", hook)
    with pytest.raises(BrokenPipeError):
        s.push()
    assert opened_after == []
