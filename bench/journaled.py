"""A journaled ext4 of the run's own for the robot's side of a bench run (root only).

    with journaled_fs(workdir / "robot-disk.img", owner=(uid, gid)) as mount:
        side = RobotSide.make(user, workdir, parent=mount)

Why: this VM's root file system is ext4 without a journal, and in that mode ext4's
inode allocator skips, on every file it creates, each free inode of the block group
that was freed in the last 60 s (360 s while its inode table block is dirty:
fs/ext4/ialloc.c, ``recently_deleted``; a journaled ext4 never consults it). The bench
and the other sessions on this machine delete trees all the time, so the robot's
creates cost 4-20x their usual kernel CPU for minutes after, depending on what ran
before (bench/createcost.py: 500 creates 17 ms quiet, 65-120 ms for ~25 s after 4,000
files deleted next to them, 170-280 ms while other sessions' benches ran); the watch
burst's figure swung 289-556 ms with the same code. A robot's Ubuntu disk is a
journaled ext4: an image file of the run's, ``mkfs.ext4`` with its defaults and
loop-mounted, is what a robot has, and nobody else deletes near it (on it, 500 creates
cost 7-29 ms right after 4,000 deletions). The image is sparse (its size is a
ceiling), in the run's work directory, and gone with it.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path


def available() -> bool:
    """Whether a journaled image can be made and mounted here: root, mkfs.ext4, a loop device."""
    return (
        os.geteuid() == 0
        and any(Path(d, "mkfs.ext4").exists() for d in ("/sbin", "/usr/sbin"))
        and Path("/dev/loop-control").exists()
    )


@contextlib.contextmanager
def journaled_fs(
    image: Path,
    *,
    size: str = "8G",
    owner: tuple[int, int] | None = None,
    under: Path | None = None,
) -> Iterator[Path]:
    """A fresh ext4 (with its journal: mkfs.ext4's defaults) in the sparse file ``image``,
    mounted on a new directory under ``under`` (default beside the image; the robot's
    account must be able to reach it: its home), owned by ``owner`` (uid, gid); unmounted
    and removed at exit."""
    image.parent.mkdir(parents=True, exist_ok=True)
    with open(image, "wb") as fh:
        fh.truncate(_bytes(size))
    subprocess.run(["mkfs.ext4", "-q", "-F", str(image)], check=True, capture_output=True)
    mount = Path(tempfile.mkdtemp(prefix="disk-", dir=under or image.parent))
    subprocess.run(["mount", "-o", "loop", str(image), str(mount)], check=True, capture_output=True)
    try:
        mount.chmod(0o755)
        if owner is not None:
            os.chown(mount, *owner)
        yield mount
    finally:
        # lazily: a process of the run still in it (a killed tool's endpoint) must not keep
        # the image mounted for ever; the loop device goes once the last one has left
        subprocess.run(["umount", "-l", str(mount)], check=False, capture_output=True)
        with contextlib.suppress(OSError):
            mount.rmdir()
        with contextlib.suppress(OSError):
            image.unlink()


def _bytes(size: str) -> int:
    units = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}
    return int(size[:-1]) * units[size[-1].upper()] if size[-1].isalpha() else int(size)
