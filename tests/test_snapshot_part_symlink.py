"""A snapshot's archive is written through a ``.part`` nobody can plant.

The archive was written to ``NAME.part`` opened by name, then renamed into place.
In a shared directory (``/tmp``, a lab's NFS share, a robot's home with group
write) another local user could put a symlink of that name to a file of the
user's: the snapshot truncated and overwrote that file.
"""

from __future__ import annotations

import os
import stat
import tarfile
import zipfile
from pathlib import Path

import pytest

from fetchsync.chores.snapshot import OK, CommandResult, write_archive


def _results(tmp_path: Path) -> list[CommandResult]:
    out = tmp_path / "work" / "uname.out"
    out.parent.mkdir()
    out.write_text("Linux robot 5.4\n")
    return [CommandResult(name="uname", kind="system", command="uname -a", status=OK, stdout=out)]


@pytest.mark.parametrize("archive_format", ["tar", "zip"])
def test_a_planted_part_symlink_is_not_followed(tmp_path: Path, archive_format: str) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    victim = tmp_path / "victim" / "notes.txt"
    victim.parent.mkdir()
    victim.write_text("the user's own work\n")
    name = "snapshot-robot.zip" if archive_format == "zip" else "snapshot-robot.tar.gz"
    path = shared / name
    os.symlink(victim, shared / (name + ".part"))  # another user's trap

    size = write_archive(
        path, results=_results(tmp_path), manifest={}, archive_format=archive_format
    )

    assert victim.read_text() == "the user's own work\n"
    assert size == path.stat().st_size > 0
    assert not path.is_symlink()
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    if archive_format == "zip":
        with zipfile.ZipFile(path) as z:
            assert "snapshot-robot/uname.txt" in z.namelist()
    else:
        with tarfile.open(path) as t:
            assert "snapshot-robot/uname.txt" in t.getnames()
    # nothing of ours is left beside it: only the archive and the untouched trap
    assert sorted(p.name for p in shared.iterdir()) == sorted([name, name + ".part"])


def test_a_failed_write_leaves_no_part(tmp_path: Path) -> None:
    results = _results(tmp_path)
    assert results[0].stdout is not None
    results[0].stdout.unlink()  # vanished before it was read: the write fails
    shared = tmp_path / "shared"
    shared.mkdir()
    with pytest.raises(Exception, match="cannot write the snapshot archive"):
        write_archive(shared / "s.tar.gz", results=results, manifest={})
    assert list(shared.iterdir()) == []
