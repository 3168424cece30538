"""The resident's kept scan (fetchsync.agent.keptscan): between two pushes it answers
exactly what a fresh scan of the tree finds, after any mix of changes a user makes
(edits, new and deleted files and directories, renames, chmods, symlinks, special
files, unreadable directories, ignore files), and lists only where something
happened (no full scan for a change below the top)."""

from __future__ import annotations

import os
import random
import shutil
from pathlib import Path

import pytest

from fetchsync.agent.keptscan import KeptScan
from fetchsync.protocol.ignore import build_rules
from fetchsync.protocol.store import is_temp
from fetchsync.sync.engine import scan_tree


def fresh(root: Path) -> tuple[dict[str, object], list[tuple[str, str]]]:
    result = scan_tree(str(root), build_rules(()))
    return dict(result.entries), sorted(result.skipped)


def kept_now(kept: KeptScan) -> tuple[dict[str, object], list[tuple[str, str]]]:
    result = kept.scan()
    return dict(result.entries), sorted(result.skipped)


def make_tree(root: Path, rng: random.Random) -> None:
    for p in range(4):
        for d in ("src", "include/pkg", "launch"):
            where = root / f"pkg{p}" / d
            where.mkdir(parents=True, exist_ok=True)
            for f in range(rng.randint(1, 4)):
                (where / f"f{f}.cpp").write_text(f"// {p} {d} {f}\n")
    (root / "CMakeLists.txt").write_text("top\n")


def dirs_of(root: Path) -> list[Path]:
    return sorted(
        Path(dp) for dp, _dn, _fn in os.walk(root) if Path(dp) != root and os.access(dp, os.X_OK)
    )


def files_of(root: Path) -> list[Path]:
    return sorted(
        Path(dp) / f for dp, _dn, fn in os.walk(root) for f in fn if os.access(dp, os.X_OK)
    )


def change(root: Path, rng: random.Random, n: int) -> str:
    """One random change below the top of the tree; what it was."""
    dirs = dirs_of(root)
    files = [f for f in files_of(root) if f.parent != root and not f.is_symlink()]
    here = rng.choice(dirs)
    kind = rng.choice(
        [
            "edit",
            "edit",
            "new",
            "delete",
            "chmod",
            "touch",
            "mkdir",
            "rmtree",
            "rename",
            "move",
            "symlink",
            "relink",
            "fifo",
            "unreadable",
            "ignore",
            "dirmove",
            "replace",
            "tmp",
        ]
    )
    regular = [f for f in files if f.is_file() and not f.is_symlink()]
    if kind == "edit" and regular:
        f = rng.choice(regular)
        with open(f, "a") as fh:
            fh.write(f"edit {n}\n")
    elif kind == "new":
        (here / f"new{n}.h").write_text(f"new {n}\n")
    elif kind == "delete" and regular:
        rng.choice(regular).unlink()
    elif kind == "chmod" and regular:
        rng.choice(regular).chmod(rng.choice([0o644, 0o755, 0o600]))
    elif kind == "touch" and regular:
        os.utime(rng.choice(regular), ns=(n * 10**9, n * 10**9 + 7))
    elif kind == "mkdir":
        (here / f"dir{n}" / "deep").mkdir(parents=True)
        (here / f"dir{n}" / "deep" / "x.cpp").write_text("x\n")
    elif kind == "rmtree" and here.parent != root:
        shutil.rmtree(here)
    elif kind == "rename" and regular:
        f = rng.choice(regular)
        f.rename(f.with_name(f"renamed{n}.cpp"))
    elif kind == "move" and regular:
        rng.choice(regular).rename(here / f"moved{n}.cpp")
    elif kind == "symlink":
        (here / f"link{n}").symlink_to(f"target{n}")
    elif kind == "relink":
        links = [f for f in files_of(root) if f.is_symlink() and f.parent != root]
        if links:
            link = rng.choice(links)
            tmp = link.with_name(link.name + ".tmp")
            tmp.symlink_to(f"other{n}")
            tmp.rename(link)
    elif kind == "fifo":
        os.mkfifo(here / f"fifo{n}")
    elif kind == "unreadable":
        locked = [d for d in dirs_of(root) if d.stat().st_mode & 0o700 == 0]
        if locked:
            locked[0].chmod(0o755)
        elif here.parent != root:
            here.chmod(0o000)
    elif kind == "ignore" and here.parent != root:
        (here / ".fetchsyncignore").write_text(rng.choice(["*.h\n", "new*\n", ""]))
    elif kind == "dirmove" and here.parent != root:
        here.rename(here.parent / f"moved{n}")
    elif kind == "replace" and regular:
        f = rng.choice(regular)
        f.unlink()
        f.mkdir()
        (f / "inner.cpp").write_text("inner\n")
    elif kind == "tmp":
        (here / f".fetchsync-tmp-{n}").write_text("temporary\n")
    return f"{kind} in {here.relative_to(root)}"


@pytest.mark.parametrize("seed", range(6))
def test_the_kept_scan_is_what_a_fresh_scan_finds(tmp_path: Path, seed: int) -> None:
    rng = random.Random(seed)
    root = tmp_path / "src"
    make_tree(root, rng)
    kept = KeptScan(str(root), build_rules(()), is_temp=is_temp)
    assert kept_now(kept) == fresh(root)
    assert kept.full_scans == 1
    done = []
    try:
        for n in range(60):
            for k in range(rng.randint(1, 3)):
                done.append(change(root, rng, n * 10 + k))
            assert kept_now(kept) == fresh(root), done[-3:]
    finally:
        for d in dirs_of(root) + [p for p in root.rglob("*") if p.is_dir()]:
            d.chmod(0o755)
    # most pushes listed only where something happened
    assert kept.full_scans < 40, kept.full_scans
    kept.close()


def test_an_edit_lists_only_its_directory(tmp_path: Path) -> None:
    root = tmp_path / "src"
    make_tree(root, random.Random(1))
    kept = KeptScan(str(root), build_rules(()), is_temp=is_temp)
    kept.scan()
    for n in range(5):
        with open(root / "pkg2" / "src" / "f0.cpp", "a") as fh:
            fh.write(f"{n}\n")
        (root / "pkg1" / "include" / "pkg" / f"new{n}.h").write_text("h\n")
        assert kept_now(kept) == fresh(root)
        assert kept.scan().entries == fresh(root)[0]  # nothing since: the same
    assert kept.full_scans == 1
    (root / "new_top.txt").write_text("top\n")  # the top's listing is the whole tree's
    assert kept_now(kept) == fresh(root)
    assert kept.full_scans == 2
    kept.close()


def test_an_overflow_or_a_replaced_root_steps_aside(tmp_path: Path) -> None:
    root = tmp_path / "src"
    make_tree(root, random.Random(2))
    kept = KeptScan(str(root), build_rules(()), is_temp=is_temp)
    kept.scan()
    limit = int(Path("/proc/sys/fs/inotify/max_queued_events").read_text())
    if limit <= 20000:  # more events than the queue holds: IN_Q_OVERFLOW
        where = root / "pkg0" / "src"
        for n in range(limit // 2 + 10):  # distinct events: inotify merges repeated ones
            (where / f"t{n}").write_bytes(b"")
            (where / f"t{n}").unlink()
        (where / "last.cpp").write_text("last\n")
        assert kept_now(kept) == fresh(root)
        assert kept.full_scans == 2
    shutil.rmtree(root)
    make_tree(root, random.Random(3))
    assert kept_now(kept) == fresh(root)
    kept.close()


class _Limited:
    """libc's inotify whose watches run out after ``left`` (ENOSPC), counting the tries."""

    def __init__(self, real: object, left: int) -> None:
        self.real = real
        self.left = left
        self.tries = 0

    def inotify_init1(self, flags: int) -> int:
        return self.real.inotify_init1(flags)  # type: ignore[attr-defined,no-any-return]

    def inotify_add_watch(self, fd: int, path: bytes, mask: int) -> int:
        import ctypes
        import errno

        self.tries += 1
        if self.left <= 0:
            ctypes.set_errno(errno.ENOSPC)
            return -1
        self.left -= 1
        return self.real.inotify_add_watch(fd, path, mask)  # type: ignore[attr-defined,no-any-return]


def test_used_up_watches_are_given_back_and_not_taken_again(tmp_path, monkeypatch):
    """The user's inotify watches used up (an IDE holds most): the kept scan gives its own
    back at once, scans in full (still exactly), and does not try again."""
    from fetchsync.agent import keptscan

    root = tmp_path / "src"
    make_tree(root, random.Random(4))
    limited = _Limited(keptscan._inotify(), left=5)
    monkeypatch.setattr(keptscan, "_libc", limited)
    kept = KeptScan(str(root), build_rules(()), is_temp=is_temp)
    assert kept_now(kept) == fresh(root)
    assert kept.gave_up and not kept.warm and kept._fd < 0  # its 5 watches given back
    tries = limited.tries
    for n in range(3):
        (root / "pkg1" / "src" / f"more{n}.cpp").write_text("more\n")
        assert kept_now(kept) == fresh(root)
    assert limited.tries == tries and kept.full_scans == 4


def test_a_root_reached_through_a_symlink_is_kept(tmp_path: Path) -> None:
    """src/ a symlink to the real tree (as the engine's scan, listed through it)."""
    real = tmp_path / "real"
    make_tree(real, random.Random(5))
    root = tmp_path / "src"
    root.symlink_to(real)
    kept = KeptScan(str(root), build_rules(()), is_temp=is_temp)
    assert kept_now(kept) == fresh(root) and kept.warm
    (real / "pkg3" / "src" / "late.cpp").write_text("late\n")
    assert kept_now(kept) == fresh(root) and kept.full_scans == 1
    root.unlink()
    other = tmp_path / "other"
    make_tree(other, random.Random(6))
    root.symlink_to(other)  # pointed elsewhere: another tree
    assert kept_now(kept) == fresh(root) and kept.full_scans == 2
    kept.close()
