"""The watcher on the real filesystem (inotify through watchdog).

Each test runs :func:`batches` in a thread and looks at the union of what the
batches after an action name, so that a save split over two batches still
passes; nothing here asserts a latency. The latency from a write to its
batch is measured and printed by ``test_latency_is_measured`` (``-s``).

Kernel limits are provoked for real where the machine allows it:

- queue overflow: as root, ``fs.inotify.max_queued_events`` is lowered to
  16 for the instant the watcher's inotify instance is created (the kernel
  reads it then), and restored at once; then 100 files are written while
  watchdog's reader is held (by its own lock), so the kernel's queue
  overflows for sure. Without root, the overflow event is injected where
  watchdog hands it over (``InotifyFD.handle_event``), which also always runs;
- watch limit: in a child user namespace (``unshare --user``) whose own
  ``user.max_inotify_watches`` is lowered, which no other process sees;
  else, as root, ``fs.inotify.max_user_watches`` is lowered to what this
  user already holds plus 4 while the watches are added, then restored.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import statistics
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

import pytest

from fetchsync.agent.coalescer import CLOSED, Batch, Change, Coalescer, Item, Rescan
from fetchsync.agent.watcher import IgnoreFilter, Watcher, batches
from fetchsync.protocol.ignore import IgnoreRules

pytestmark = [
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="inotify is Linux's"),
    # the watcher silences this watchdog warning at import, which pytest's
    # collection undoes
    pytest.mark.filterwarnings("ignore:Callback with id:RuntimeWarning"),
]

REPO = str(Path(__file__).resolve().parent.parent)
WAIT = 30.0  # how long an expected batch may take before the test fails (the machine may be busy)
SETTLE = 0.15  # no batch for this long: the action's batches are all in


class Feed:
    """:func:`batches` running in a thread, collecting what it yields."""

    def __init__(self, root: Path, **kw: object) -> None:
        self.stop = threading.Event()
        self.batches: list[Batch] = []
        self.cond = threading.Condition()
        self.error: BaseException | None = None
        self._gen = batches(str(root), stop_event=self.stop, **kw)  # type: ignore[arg-type]
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        first = self.wait_for(lambda b: b.rescan is not None, since=0)
        assert first.rescan is not None and first.rescan.startswith("started watching")

    def _run(self) -> None:
        try:
            for batch in self._gen:
                with self.cond:
                    self.batches.append(batch)
                    self.cond.notify_all()
        except BaseException as exc:  # reported by the test, not lost in the thread
            self.error = exc
            with self.cond:
                self.cond.notify_all()

    def mark(self) -> int:
        with self.cond:
            return len(self.batches)

    def wait_for(
        self, pred: Callable[[Batch], bool], *, since: int, timeout: float = WAIT
    ) -> Batch:
        deadline = time.monotonic() + timeout
        k = since
        with self.cond:
            while True:
                while k < len(self.batches):
                    if pred(self.batches[k]):
                        return self.batches[k]
                    k += 1
                left = deadline - time.monotonic()
                if left <= 0 or self.error is not None:
                    raise AssertionError(
                        f"no such batch; got {self.batches[since:]}, error {self.error!r}"
                    )
                self.cond.wait(left)

    def wait_path(self, path: str, *, since: int) -> Batch:
        return self.wait_for(lambda b: path in b.paths or path in b.dirs, since=since)

    def settle(self, since: int) -> list[Batch]:
        """The batches after ``since`` once none came for SETTLE seconds."""
        with self.cond:
            n = -1
            while n != len(self.batches):
                n = len(self.batches)
                self.cond.wait(SETTLE)
            return self.batches[since:]

    def close(self) -> float:
        t0 = time.monotonic()
        self.stop.set()
        self.thread.join(5)
        assert not self.thread.is_alive()
        return time.monotonic() - t0


def union(bs: list[Batch]) -> tuple[set[str], set[str], list[str]]:
    paths: set[str] = set()
    dirs: set[str] = set()
    rescans = []
    for b in bs:
        paths |= b.paths
        dirs |= b.dirs
        if b.rescan:
            rescans.append(b.rescan)
    return paths, dirs, rescans


@pytest.fixture
def src(tmp_path: Path) -> Path:
    root = tmp_path / "src"
    (root / "pkg" / "src").mkdir(parents=True)
    (root / "pkg" / "node.cpp").write_text("int main() {}\n")
    (root / "pkg" / "src" / "lib.cpp").write_text("// lib\n")
    (root / "pkg" / ".git" / "objects" / "ab").mkdir(parents=True)
    return root


@pytest.fixture
def feed(src: Path) -> Iterator[Feed]:
    f = Feed(src)
    try:
        yield f
    finally:
        f.close()


def only(feed: Feed, since: int) -> set[str]:
    """Everything the batches after ``since`` name, once settled; no rescan allowed."""
    paths, dirs, rescans = union(feed.settle(since))
    assert not rescans
    return paths | {d + "/" for d in dirs}


# -- editors' saves -------------------------------------------------------------------


def test_write_in_place(src: Path, feed: Feed) -> None:
    m = feed.mark()
    (src / "pkg" / "node.cpp").write_text("int main() { return 1; }\n")
    feed.wait_path("pkg/node.cpp", since=m)
    assert only(feed, m) == {"pkg/node.cpp"}


def test_a_save_in_place_is_reported_closed(src: Path) -> None:
    """The close after a write (IN_CLOSE_WRITE) reaches the coalescer as ``closed``: the
    event that ends a save's batch without waiting for the quiet window."""
    got: list[Item] = []
    cond = threading.Condition()

    def sink(item: Item, _at: float) -> None:
        with cond:
            got.append(item)
            cond.notify_all()

    w = Watcher(str(src), sink=sink)
    w.start()
    try:
        (src / "pkg" / "node.cpp").write_text("int main() { return 5; }\n")
        with cond:
            assert cond.wait_for(lambda: Change("pkg/node.cpp", CLOSED) in got, timeout=WAIT), got
    finally:
        w.stop()


def test_new_file(src: Path, feed: Feed) -> None:
    m = feed.mark()
    (src / "pkg" / "new.py").write_text("print('hi')\n")
    feed.wait_path("pkg/new.py", since=m)
    assert only(feed, m) == {"pkg/new.py"}


def test_vscode_write_temporary_then_rename(src: Path, feed: Feed) -> None:
    m = feed.mark()
    tmp = src / "pkg" / ".node.cpp.tmp"
    tmp.write_text("int main() { return 2; }\n")
    os.replace(tmp, src / "pkg" / "node.cpp")
    feed.wait_path("pkg/node.cpp", since=m)
    assert only(feed, m) == {"pkg/node.cpp"}


def test_jetbrains_safe_write(src: Path, feed: Feed) -> None:
    m = feed.mark()
    pkg = src / "pkg"
    (pkg / "node.cpp___jb_tmp___").write_text("int main() { return 3; }\n")
    os.rename(pkg / "node.cpp", pkg / "node.cpp___jb_old___")
    os.rename(pkg / "node.cpp___jb_tmp___", pkg / "node.cpp")
    os.unlink(pkg / "node.cpp___jb_old___")
    feed.wait_path("pkg/node.cpp", since=m)
    assert only(feed, m) == {"pkg/node.cpp"}


def test_vim_save(src: Path, feed: Feed) -> None:
    m = feed.mark()
    pkg = src / "pkg"
    probe = pkg / "4913"  # vim checks that it may create files here
    probe.write_text("")
    probe.unlink()
    os.rename(pkg / "node.cpp", pkg / "node.cpp~")
    (pkg / "node.cpp").write_text("int main() { return 4; }\n")
    os.chmod(pkg / "node.cpp", 0o644)
    os.unlink(pkg / "node.cpp~")
    feed.wait_path("pkg/node.cpp", since=m)
    assert only(feed, m) == {"pkg/node.cpp"}


def test_emacs_lock_file_and_autosave(src: Path, feed: Feed) -> None:
    m = feed.mark()
    pkg = src / "pkg"
    os.symlink("user@host.1234:1700000000", pkg / ".#node.cpp")  # dangling on purpose
    (pkg / "#node.cpp#").write_text("autosave")
    (pkg / "node.cpp").write_text("int main() { return 5; }\n")
    os.unlink(pkg / "#node.cpp#")
    os.unlink(pkg / ".#node.cpp")
    feed.wait_path("pkg/node.cpp", since=m)
    assert only(feed, m) == {"pkg/node.cpp"}


# -- files and directories -------------------------------------------------------------------


def test_delete_and_rename_a_file(src: Path, feed: Feed) -> None:
    m = feed.mark()
    os.rename(src / "pkg" / "node.cpp", src / "pkg" / "main.cpp")
    (src / "pkg" / "src" / "lib.cpp").unlink()
    feed.wait_path("pkg/src/lib.cpp", since=m)
    assert only(feed, m) == {"pkg/node.cpp", "pkg/main.cpp", "pkg/src/lib.cpp"}


def test_chmod(src: Path, feed: Feed) -> None:
    m = feed.mark()
    os.chmod(src / "pkg" / "node.cpp", 0o755)
    feed.wait_path("pkg/node.cpp", since=m)
    assert only(feed, m) == {"pkg/node.cpp"}


def test_chmod_of_a_directory_rescans_below_it(src: Path, feed: Feed) -> None:
    m = feed.mark()
    os.chmod(src / "pkg" / "src", 0o700)
    feed.wait_path("pkg/src", since=m)
    assert only(feed, m) == {"pkg/src/"}


def test_directory_created_with_content(src: Path, feed: Feed) -> None:
    m = feed.mark()
    (src / "new" / "a" / "b").mkdir(parents=True)
    (src / "new" / "a" / "b" / "f.txt").write_text("x")
    (src / "new" / "g.txt").write_text("y")
    feed.wait_path("new", since=m)
    # "new/" alone on a quick machine; on a loaded one the watch on new/ may be in place
    # before its content is made, which then comes as its own paths: both say it all
    named = only(feed, m)
    assert "new/" in named
    assert all(p == "new/" or p.startswith("new/") for p in named), named


def test_directory_moved_within_the_tree(src: Path, feed: Feed) -> None:
    m = feed.mark()
    os.rename(src / "pkg", src / "pkg2")
    feed.wait_path("pkg2", since=m)
    got = only(feed, m)
    # both directories, to rescan below; watchdog's per-entry "moved" events for what the
    # directory holds may come in a later batch on a busy machine (a CI run saw
    # pkg/node.cpp, pkg2/src/, ...): paths below them, more work, never a wrong sync
    assert {"pkg/", "pkg2/"} <= got
    assert all(p.startswith(("pkg/", "pkg2/")) for p in got), got


def test_directory_deleted(src: Path, feed: Feed) -> None:
    m = feed.mark()
    shutil.rmtree(src / "pkg" / "src")
    feed.wait_path("pkg/src", since=m)
    assert only(feed, m) == {"pkg/src/"}


def test_directory_moved_out_of_and_into_the_tree(src: Path, feed: Feed, tmp_path: Path) -> None:
    m = feed.mark()
    os.rename(src / "pkg" / "src", tmp_path / "away")  # unpaired: watchdog waits 0.5 s
    feed.wait_path("pkg/src", since=m)
    assert only(feed, m) == {"pkg/src/"}
    m = feed.mark()
    os.rename(tmp_path / "away", src / "back")
    (src / "back" / "late.cpp").write_text("// after the move\n")
    feed.wait_path("back", since=m)
    got = only(feed, m)  # late.cpp may come in a batch after the move's (a busy machine)
    assert "back/" in got and all(p.startswith("back/") for p in got), got


def test_a_file_replaced_by_a_directory(src: Path, feed: Feed) -> None:
    m = feed.mark()
    (src / "pkg" / "node.cpp").unlink()
    (src / "pkg" / "node.cpp").mkdir()
    (src / "pkg" / "node.cpp" / "inner").write_text("x")
    feed.wait_for(lambda b: "pkg/node.cpp" in b.dirs, since=m)
    assert "pkg/node.cpp/" in only(feed, m)


# -- symlinks ----------------------------------------------------------------------------


def test_symlink_created(src: Path, feed: Feed) -> None:
    m = feed.mark()
    os.symlink("node.cpp", src / "pkg" / "link.cpp")
    feed.wait_path("pkg/link.cpp", since=m)
    assert only(feed, m) == {"pkg/link.cpp"}


def test_symlinks_are_not_followed_out_of_the_root(src: Path, tmp_path: Path) -> None:
    outside = tmp_path / "outside"
    outside.mkdir()
    os.symlink(outside, src / "pkg" / "before")  # there when the watch starts
    f = Feed(src)
    try:
        m = f.mark()
        os.symlink(outside, src / "pkg" / "after")  # made while watching
        f.wait_path("pkg/after", since=m)
        assert only(f, m) == {"pkg/after"}  # a link, not a directory to rescan
        m = f.mark()
        (outside / "secret.txt").write_text("not ours")
        (src / "pkg" / "node.cpp").write_text("// marker\n")
        f.wait_path("pkg/node.cpp", since=m)
        assert only(f, m) == {"pkg/node.cpp"}
    finally:
        f.close()


def test_a_root_given_through_a_symlink_is_watched_at_its_target(src: Path, tmp_path: Path) -> None:
    link = tmp_path / "ws_src"
    os.symlink(src, link)
    f = Feed(link)
    try:
        m = f.mark()
        (src / "pkg" / "node.cpp").write_text("// via the link\n")
        f.wait_path("pkg/node.cpp", since=m)
    finally:
        f.close()


# -- ignore rules ------------------------------------------------------------------------------


def test_ignored_paths_are_not_reported(src: Path, feed: Feed) -> None:
    m = feed.mark()
    (src / "pkg" / ".git" / "objects" / "ab" / "cdef").write_text("blob")
    (src / "pkg" / ".git" / "index").write_text("index")
    (src / "pkg" / "__pycache__").mkdir()
    (src / "pkg" / "__pycache__" / "x.cpython-311.pyc").write_bytes(b"\0")
    (src / "pkg" / ".node.cpp.swp").write_bytes(b"\0")
    (src / "pkg" / "node.cpp").write_text("// marker\n")
    feed.wait_path("pkg/node.cpp", since=m)
    assert only(feed, m) == {"pkg/node.cpp"}


def test_extra_patterns_are_honoured(src: Path) -> None:
    f = Feed(src, rules=IgnoreRules.build(extra=["*.bag"]))
    try:
        m = f.mark()
        (src / "pkg" / "run.bag").write_bytes(b"rosbag")
        (src / "pkg" / "node.cpp").write_text("// marker\n")
        f.wait_path("pkg/node.cpp", since=m)
        assert only(f, m) == {"pkg/node.cpp"}
    finally:
        f.close()


def test_a_fetchsyncignore_change_updates_the_rules(src: Path) -> None:
    (src / "pkg" / ".fetchsyncignore").write_text("*.log\n")
    f = Feed(src)
    try:
        m = f.mark()
        (src / "pkg" / "a.log").write_text("ignored")
        (src / "pkg" / "node.cpp").write_text("// marker\n")
        f.wait_path("pkg/node.cpp", since=m)
        assert only(f, m) == {"pkg/node.cpp"}

        m = f.mark()
        (src / "pkg" / ".fetchsyncignore").write_text("# nothing ignored now\n")
        f.wait_for(lambda b: (b.rescan or "").startswith("ignore rules changed"), since=m)
        f.settle(m)

        m = f.mark()
        (src / "pkg" / "a.log").write_text("now synced")
        f.wait_path("pkg/a.log", since=m)
        assert only(f, m) == {"pkg/a.log"}
    finally:
        f.close()


def test_a_directory_no_longer_excluded_is_watched_again(src: Path) -> None:
    (src / ".fetchsyncignore").write_text("data/\n")
    (src / "data" / "deep").mkdir(parents=True)
    f = Feed(src)
    try:
        m = f.mark()
        (src / ".fetchsyncignore").write_text("")
        f.wait_for(lambda b: (b.rescan or "").startswith("ignore rules changed"), since=m)
        f.settle(m)
        m = f.mark()
        (src / "data" / "deep" / "x.csv").write_text("1,2\n")
        f.wait_path("data/deep/x.csv", since=m)
    finally:
        f.close()


def _watches_held() -> int:
    """This process's inotify watches, as the kernel counts them."""
    n = 0
    for fd in os.listdir("/proc/self/fdinfo"):
        try:
            with open(f"/proc/self/fdinfo/{fd}") as fh:
                n += sum(line.startswith("inotify wd:") for line in fh)
        except OSError:
            pass
    return n


def test_excluded_directories_cost_no_watch(src: Path) -> None:
    for i in range(20):
        (src / "pkg" / ".git" / "objects" / f"{i:02x}").mkdir(exist_ok=True)
    (src / "pkg" / "__pycache__").mkdir()
    before = _watches_held()
    sink: list[tuple[Item, float]] = []
    w = Watcher(str(src), sink=lambda item, at: sink.append((item, at)))
    w.start()
    try:
        assert _watches_held() - before == 3  # src, pkg, pkg/src
    finally:
        w.stop()
    assert _watches_held() == before


def test_filter_reads_nested_ignore_files_lazily_and_forgets_moved_directories(
    tmp_path: Path,
) -> None:
    (tmp_path / "a" / "b").mkdir(parents=True)
    (tmp_path / "a" / ".fetchsyncignore").write_text("*.o\n")
    flt = IgnoreFilter(str(tmp_path))
    assert not flt("a/b/x.o", False)
    assert flt("x.o", False)  # the file applies below a/ only
    (tmp_path / "a" / ".fetchsyncignore").write_text("*.a\n")
    assert flt.note(Change("a/.fetchsyncignore", "modified"))
    assert flt("a/b/x.o", False) and not flt("a/b/x.a", False)
    assert not flt.note(Change("a/.fetchsyncignore", "modified"))  # same text: no change
    shutil.rmtree(tmp_path / "a")
    (tmp_path / "a").mkdir()
    assert not flt.note(Change("a", "created", is_dir=True))
    assert flt("a/x.a", False)  # the new a/ has no ignore file


# -- bursts, latency, stopping -----------------------------------------------------------------


def _git(repo: Path, *args: str) -> None:
    subprocess.run(
        ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args],
        check=True,
        capture_output=True,
    )


def _two_branches(repo: Path) -> set[str]:
    """A repository whose branch "one" has 2,000 files in 20 directories and "two" the
    directories only (checked out: "two"); the files' paths below ``src``."""
    names = [f"d{k % 20:02d}/f{k:04d}.cpp" for k in range(2000)]
    for k, name in enumerate(names):
        (repo / name).parent.mkdir(parents=True, exist_ok=True)
        (repo / name).write_text(f"// {k}\n")
    for d in range(20):
        (repo / f"d{d:02d}" / "keep").write_text("")  # so that the directories stay
    _git(repo, "init", "-q", "-b", "one")
    _git(repo, "add", ".")
    _git(repo, "commit", "-qm", "one")
    _git(repo, "checkout", "-qb", "two")
    _git(repo, "rm", "-q", "--", *names)
    _git(repo, "commit", "-qm", "two")
    return {f"{repo.name}/{name}" for name in names}


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_every_path_of_a_git_checkout_of_2000_files_arrives_without_a_rescan(src: Path) -> None:
    """2,000 files created, then deleted, by ``git checkout`` (another process, as in life),
    through :func:`batches` on the real filesystem: every path arrives, as a path, and
    nothing is a rescan. How many batches depends on the machine's pace (see the next
    test for the coalescing): printed, not asserted."""
    expected = _two_branches(src / "repo")
    for branch in ("one", "two"):
        f = Feed(src)
        try:
            m = f.mark()
            _git(src / "repo", "checkout", "-q", branch)
            seen: set[str] = set()

            def all_in(b: Batch, seen: set[str] = seen) -> bool:
                seen.update(b.paths)
                return expected <= seen

            f.wait_for(all_in, since=m, timeout=60)
            got = f.settle(m)
        finally:
            f.close()
        paths, dirs_seen, rescans = union(got)
        assert paths == expected and not dirs_seen and not rescans
        print(
            f"\ncheckout {branch}: {len(got)} batches of {[len(b.paths) for b in got]} paths "
            f"({sum(b.items for b in got)} events)"
        )


def _replay(events: list[Item], *, gaps: Callable[[int], float], cap: float) -> list[Batch]:
    """The batches a :class:`Coalescer` makes of ``events`` when event k comes ``gaps(k)``
    seconds after the one before, taken as :func:`batches` takes them (each one once due)."""
    c = Coalescer(cap=cap)
    out: list[Batch] = []
    t = 1000.0
    for k, item in enumerate(events):
        t += gaps(k)
        while c.due(t) == 0.0:
            b = c.take(t)
            if b is not None:
                out.append(b)
        c.add(item, t)
    b = c.take(t, force=True)
    return out + ([b] if b is not None else [])


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
@pytest.mark.parametrize("pace", [0.00005, 0.0005, 0.002])
def test_a_git_checkout_of_2000_files_comes_as_a_handful_of_batches(src: Path, pace: float) -> None:
    """The events the real watcher reports for a ``git checkout`` of 2,000 files, replayed
    with scripted times (watchfiles' habit; no clock of this machine's in the count): one
    every ``pace`` seconds, a fast laptop's to a loaded one's, with a 20 ms stall (the
    scheduler, the disk) every 500. The burst is coalesced: cut only by the cap, so a
    checkout that lasts T seconds comes as about T / cap batches, every path in one, no
    rescan."""
    expected = _two_branches(src / "repo")
    events: list[Item] = []
    lock = threading.Lock()

    def sink(item: Item, _at: float) -> None:
        with lock:
            events.append(item)

    w = Watcher(str(src), sink=sink)
    w.start()
    try:
        _git(src / "repo", "checkout", "-q", "one")
        deadline = time.monotonic() + 60
        while True:
            with lock:
                seen = {e.path for e in events if isinstance(e, Change)}
            if expected <= seen or time.monotonic() > deadline:
                break
            time.sleep(0.05)
    finally:
        w.stop()
    with lock:
        events = [
            e for e in events if not isinstance(e, Rescan) or not e.reason.startswith("started")
        ]
    assert len(events) >= len(expected)

    def gaps(k: int) -> float:
        return 0.020 if k % 500 == 499 else pace

    span = sum(gaps(k) for k in range(len(events)))
    for cap in (0.5, 0.1):
        got = _replay(events, gaps=gaps, cap=cap)
        paths, dirs_seen, rescans = union(got)
        assert paths == expected and not dirs_seen and not rescans
        assert len(got) <= span / cap + 2, (cap, len(got), [len(b.paths) for b in got])
        # cut by the cap only, never by a stall or the pace: each batch but the last
        # holds (nearly) cap seconds of the burst
        assert all(b.last_at - b.first_at >= cap - 0.021 - pace for b in got[:-1]), [
            round(b.last_at - b.first_at, 4) for b in got
        ]


def test_latency_is_measured(src: Path, feed: Feed) -> None:
    """Median time from a write (its close) to the batch that names it. Reported, not asserted."""
    target = src / "pkg" / "node.cpp"
    latencies = []
    for k in range(100):
        m = feed.mark()
        t0 = time.monotonic()
        target.write_text(f"// save {k}\n")
        feed.wait_path("pkg/node.cpp", since=m)
        latencies.append(time.monotonic() - t0)
        if k % 10 == 9:
            feed.settle(m)  # now and then, let everything drain
        else:
            time.sleep(0.01)
    latencies.sort()
    median = statistics.median(latencies) * 1000
    p90 = latencies[89] * 1000
    print(
        f"\nwrite -> batch over 100 saves: median {median:.1f} ms, p90 {p90:.1f} ms, "
        f"max {latencies[-1] * 1000:.1f} ms"
    )


def test_stops_promptly(src: Path) -> None:
    """The watcher's thread ends when asked (close() joins it: a hang fails the test);
    no wall-time bound: under a loaded CI machine that would measure the machine."""
    f = Feed(src)
    time.sleep(0.05)
    f.close()
    assert not f.thread.is_alive()


def test_closing_the_generator_stops_the_watcher(src: Path) -> None:
    before = _watches_held()
    gen = batches(str(src))
    assert next(gen).rescan
    assert _watches_held() > before
    gen.close()
    assert _watches_held() == before


def test_a_root_that_is_not_a_directory_is_refused(tmp_path: Path) -> None:
    from fetchsync.errors import ConfigError

    with pytest.raises(ConfigError):
        Watcher(str(tmp_path / "missing"), sink=lambda item, at: None)


def test_the_root_deleted_is_a_rescan(src: Path) -> None:
    f = Feed(src, rewatch=60.0)
    try:
        m = f.mark()
        shutil.rmtree(src)
        b = f.wait_for(lambda b: b.rescan is not None, since=m)
        assert "deleted or moved away" in (b.rescan or "")
    finally:
        f.close()


def test_the_root_moved_away_then_made_again(src: Path, tmp_path: Path) -> None:
    f = Feed(src, rewatch=0.2)
    try:
        m = f.mark()
        os.rename(src, tmp_path / "src.old")
        b = f.wait_for(lambda b: b.rescan is not None, since=m)
        assert "moved away or replaced" in (b.rescan or "")
        m = f.mark()
        (src / "pkg").mkdir(parents=True)
        f.wait_for(lambda b: b.rescan == "watching every directory again", since=m)
        m = f.mark()
        (src / "pkg" / "fresh.cpp").write_text("//\n")
        (tmp_path / "src.old" / "pkg" / "node.cpp").write_text("// not watched any more\n")
        f.wait_path("pkg/fresh.cpp", since=m)
        assert only(f, m) == {"pkg/fresh.cpp"}
    finally:
        f.close()


# -- kernel limits -------------------------------------------------------------------------------


class Sink:
    def __init__(self) -> None:
        self.items: list[Item] = []
        self.cond = threading.Condition()

    def __call__(self, item: Item, at: float) -> None:
        with self.cond:
            self.items.append(item)
            self.cond.notify_all()

    def wait_for(
        self, pred: Callable[[Item], bool], timeout: float = WAIT, *, since: int = 0
    ) -> Item:
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                for item in self.items[since:]:
                    if pred(item):
                        return item
                left = deadline - time.monotonic()
                assert left > 0, f"not found among {self.items[-20:]}"
                self.cond.wait(left)


def test_overflow_injected_at_the_watchdog_boundary_is_a_rescan(
    src: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from watchdog.observers.inotify_c import InotifyConstants, InotifyEvent

    sink = Sink()
    w = Watcher(str(src), sink=sink)
    w.start()
    try:
        with caplog.at_level(logging.WARNING, logger="fetchsync.agent.watcher"):
            assert w._fd is not None
            # what the kernel sends when it drops events: wd -1, IN_Q_OVERFLOW
            w._fd.handle_event(InotifyEvent(-1, InotifyConstants.IN_Q_OVERFLOW, 0, b""))  # type: ignore[arg-type]
            item = sink.wait_for(lambda i: isinstance(i, Rescan))
        assert "fs.inotify.max_queued_events" in item.reason  # type: ignore[union-attr]
        assert any("max_queued_events" in r.getMessage() for r in caplog.records)
        # watchdog rebuilt its watches: changes are still seen
        (src / "pkg" / "src" / "after.cpp").write_text("//\n")
        sink.wait_for(lambda i: i == Change("pkg/src/after.cpp", "created"))
    finally:
        w.stop()


SYSCTL = Path("/proc/sys/fs/inotify")


def _writable(path: Path) -> bool:
    return os.geteuid() == 0 and os.access(path, os.W_OK)


@pytest.mark.skipif(
    not _writable(SYSCTL / "max_queued_events"),
    reason="needs root to lower fs.inotify.max_queued_events",
)
def test_a_real_queue_overflow_is_a_rescan(src: Path, caplog: pytest.LogCaptureFixture) -> None:
    sink = Sink()
    w = Watcher(str(src), sink=sink)
    knob = SYSCTL / "max_queued_events"
    saved = knob.read_text()
    try:
        # The kernel sizes an instance's queue when it is created: lower the
        # knob for that instant only (other programs' new instances would get it too).
        knob.write_text("16\n")
        try:
            w.start()
        finally:
            knob.write_text(saved)
        with caplog.at_level(logging.WARNING, logger="fetchsync.agent.watcher"):
            assert w._fd is not None
            with w._fd._lock:  # the reader waits: nothing leaves the kernel's queue
                for k in range(100):
                    (src / "pkg" / f"burst{k}.txt").write_text("x")
            item = sink.wait_for(lambda i: isinstance(i, Rescan))
        assert "max_queued_events" in item.reason  # type: ignore[union-attr]
        # changes are still seen: as themselves, or covered by a later rescan
        # (this instance's queue stays 16 events long, and rebuilding the
        # watches may overflow it again; a rescan then includes the change)
        before = len(sink.items)
        (src / "pkg" / "src" / "after.cpp").write_text("//\n")
        sink.wait_for(
            lambda i: i == Change("pkg/src/after.cpp", "created") or isinstance(i, Rescan),
            since=before,
        )
    finally:
        w.stop()
        assert knob.read_text() == saved


# The watch-limit scenario runs in a child process: in a user namespace of
# its own when possible (its limit is private), else with the global knob.
_LIMIT_SCRIPT = textwrap.dedent("""
    import json, logging, os, sys, threading, time
    sys.path.insert(0, REPO)
    root, mode = sys.argv[1], sys.argv[2]
    logs = []

    class Keep(logging.Handler):
        def emit(self, record):
            logs.append(record.levelname + " " + record.getMessage())

    logging.getLogger("fetchsync").addHandler(Keep())
    logging.getLogger("fetchsync").setLevel(logging.INFO)
    from fetchsync.agent.watcher import batches

    USERNS = "/proc/sys/user/max_inotify_watches"
    GLOBAL = "/proc/sys/fs/inotify/max_user_watches"

    def watches_of_this_user():
        n, uid = 0, os.geteuid()
        for pid in filter(str.isdigit, os.listdir("/proc")):
            try:
                if os.stat("/proc/" + pid).st_uid != uid:
                    continue
                for fd in os.listdir("/proc/%s/fdinfo" % pid):
                    with open("/proc/%s/fdinfo/%s" % (pid, fd)) as fh:
                        n += sum(line.startswith("inotify wd:") for line in fh)
            except OSError:
                pass
        return n

    def write(path, value):
        with open(path, "w") as fh:
            fh.write("%d\\n" % value)

    out = {"mode": mode, "batches": []}
    stop = threading.Event()
    gen = batches(root, rewatch=0.3, stop_event=stop)
    if mode == "userns":
        write(USERNS, 4)          # the root and 3 directories
        first = next(gen)
    else:
        saved = int(open(GLOBAL).read())
        write(GLOBAL, watches_of_this_user() + 4)
        try:
            first = next(gen)     # the watches are added here
        finally:
            write(GLOBAL, saved)
    out["first"] = first.rescan

    def until(pred, timeout=5.0):
        deadline = time.monotonic() + timeout
        for b in gen:
            out["batches"].append([b.rescan, sorted(b.paths)])
            if pred(b):
                return b
            if time.monotonic() > deadline:
                raise SystemExit("timed out: " + json.dumps(out))

    if mode == "userns":
        # still limited: a change in an unwatched directory comes with the next retry's rescan
        with open(os.path.join(root, "d9", "while_limited.txt"), "w") as fh:
            fh.write("x")
        out["retry"] = until(lambda b: b.rescan is not None).rescan
        write(USERNS, 100000)
    out["recovered"] = until(lambda b: b.rescan == "watching every directory again").rescan
    with open(os.path.join(root, "d9", "after.txt"), "w") as fh:
        fh.write("x")
    until(lambda b: "d9/after.txt" in b.paths)
    stop.set()
    for _ in gen:
        pass
    out["logs"] = logs
    print(json.dumps(out))
""").replace("REPO", repr(REPO))


def _run_limit_script(root: Path, tmp_path: Path) -> dict[str, object]:
    script = tmp_path / "limit.py"
    script.write_text(_LIMIT_SCRIPT)
    unshare = shutil.which("unshare")
    attempts = []
    if unshare:
        attempts.append(
            (
                [
                    unshare,
                    "--user",
                    "--map-root-user",
                    sys.executable,
                    str(script),
                    str(root),
                    "userns",
                ],
                "userns",
            )
        )
    if _writable(SYSCTL / "max_user_watches"):
        attempts.append(([sys.executable, str(script), str(root), "global"], "global"))
    errors = []
    for argv, _mode in attempts:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=60)
        if proc.returncode == 0:
            return json.loads(proc.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]
        errors.append(proc.stderr[-2000:])
    pytest.skip(
        "cannot lower an inotify watch limit here: " + " | ".join(errors)[-500:]
        if attempts
        else "no unshare and not root"
    )


def test_watch_limit_is_a_rescan_with_a_clear_warning_until_watches_are_back(
    tmp_path: Path,
) -> None:
    root = tmp_path / "src"
    for i in range(10):
        (root / f"d{i}").mkdir(parents=True)
    for i in range(10):
        (root / "d0" / ".git" / f"o{i}").mkdir(parents=True)  # excluded: costs no watch
    out = _run_limit_script(root, tmp_path)
    first = str(out["first"])
    assert first.startswith("inotify watch limit reached")
    assert "fs.inotify.max_user_watches" in first
    assert "sudo sysctl fs.inotify.max_user_watches=" in first
    logs = [str(x) for x in out["logs"]]  # type: ignore[attr-defined]
    assert any(
        x.startswith("WARNING inotify watch limit reached (fs.inotify.max_user_watches = ")
        for x in logs
    )
    if out["mode"] == "userns":
        assert "user.max_inotify_watches = 4" in first
        assert str(out["retry"]).startswith("inotify watch limit reached")
        # one warning for the whole episode, not one per retry
        assert sum("watch limit reached" in x for x in logs) == 1
    assert out["recovered"] == "watching every directory again"
    assert any("is watched again" in x for x in logs)
