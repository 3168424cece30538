"""The robot's stat cache never keeps a hash taken while its file could still change
unseen: on a file system whose timestamps tick coarsely (ext2/ext3's 128-byte inodes:
one second; FAT: two; ext4 on kernels before 6.13: a jiffy), a same-size rewrite in
the same tick as the hash leaves size, times and inode as they were. The Store judged
"racy" only when it looked a hash up (now - mtime < RACY_NS), so a hash read between
two such writes was trusted from two seconds on, and kept in the index: every later
Store listed the old content (drift missed the robot-side edit; a push then replaced
it with no conflict copy). Now a hash taken while the file is racy is not cached; nor the hash of its own write
while racy (a same-size rewrite right after a push's rename: the second test).

Real file system: a 1-second-stamp ext2 image, loop-mounted in a private mount
namespace (root, unshare, mkfs.ext2); skipped where that cannot be done."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = r"""
import os, sys, time
from fetchsync.protocol import store as S
from fetchsync.protocol.hashing import BLAKE2B_128, digest
ws = sys.argv[1]
os.makedirs(ws + "/src")
path = ws + "/src/calib.yaml"
for attempt in range(5):
    while time.time() % 1 > 0.2:  # both writes in one second: the same stamps
        time.sleep(0.01)
    with open(path, "w") as fh:
        fh.write("x: 1.000\n")
    s = S.Store(ws, algorithm=BLAKE2B_128)
    s.lock()
    s.listing()  # hashes the file: its first content
    s.save_index()
    s.unlock()
    s.close()
    before = os.stat(path)
    with open(path, "r+") as fh:  # rewritten in place, same size
        fh.write("x: 2.000\n")
    after = os.stat(path)
    same = lambda st: (st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino)
    if same(before) == same(after):
        break
else:
    print("NO-SAME-TICK")
    sys.exit(0)
time.sleep(S.RACY_NS / 1e9 + 0.2)
s = S.Store(ws, algorithm=BLAKE2B_128)  # a later endpoint: the index as saved
s.lock()
listed = {x.path: x.hash for x in s.listing()[0]}
s.unlock()
with open(path, "rb") as fh:
    fresh = digest(BLAKE2B_128, fh.read()).hex()
print("SAME" if listed["calib.yaml"] == fresh else "STALE")
"""

WRITE_SCRIPT = r"""
import os, sys, time
from fetchsync.protocol import messages as M
from fetchsync.protocol import store as S
from fetchsync.protocol.hashing import BLAKE2B_128, digest
ws = sys.argv[1]
os.makedirs(ws + "/src")
path = ws + "/src/calib.yaml"
ours = b"x: 1.000\n"
for attempt in range(5):
    if os.path.exists(path):
        os.unlink(path)
    while time.time() % 1 > 0.2:  # our write and theirs in one second: the same stamps
        time.sleep(0.01)
    s = S.Store(ws, algorithm=BLAKE2B_128)
    s.lock()
    h = digest(BLAKE2B_128, ours).hex()
    op = M.Op(M.WRITE, "calib.yaml", expect=M.ABSENT, mode=0o644, hash=h, size=len(ours),
              source=M.SRC_DATA, blob=(0, len(ours)))
    (res,) = s.apply([op], ours)
    assert res.ok, res
    s.save_index()
    s.unlock()
    s.close()
    before = os.stat(path)
    with open(path, "r+") as fh:  # another program rewrites it in place, same size
        fh.write("x: 2.000\n")
    after = os.stat(path)
    same = lambda st: (st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino)
    if same(before) == same(after):
        break
else:
    print("NO-SAME-TICK")
    sys.exit(0)
time.sleep(S.RACY_NS / 1e9 + 0.2)
s = S.Store(ws, algorithm=BLAKE2B_128)  # a later endpoint: the index as saved
s.lock()
listed = {x.path: x.hash for x in s.listing()[0]}
s.unlock()
with open(path, "rb") as fh:
    fresh = digest(BLAKE2B_128, fh.read()).hex()
print("SAME" if listed["calib.yaml"] == fresh else "STALE")
"""


def _tools() -> bool:
    return os.getuid() == 0 and all(shutil.which(t) for t in ("unshare", "mount", "mkfs.ext2"))


def _listed_after_a_same_tick_rewrite(tmp_path: Path, script: str) -> list[str]:
    """Run ``script`` on a fresh 1-second-stamp ext2 in a private mount namespace; its
    words (SAME, STALE or NO-SAME-TICK), or a skip where that cannot be done."""
    image, mnt = tmp_path / "ext2.img", tmp_path / "mnt"
    mnt.mkdir()
    with open(image, "wb") as fh:
        fh.truncate(16 << 20)
    # 128-byte inodes: whole-second timestamps
    subprocess.run(
        ["mkfs.ext2", "-q", "-F", "-I", "128", str(image)], check=True, capture_output=True
    )
    (tmp_path / "check.py").write_text(script)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.run(
        [
            "unshare",
            "-m",
            "sh",
            "-c",
            'mount -o loop "$1" "$2" || exit 77; "$3" "$4" "$2/ws"; s=$?; umount "$2"; exit $s',
            "sh",
            str(image),
            str(mnt),
            sys.executable,
            str(tmp_path / "check.py"),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    if proc.returncode == 77:
        pytest.skip(f"cannot loop-mount here: {proc.stderr.strip()}")
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout.split()
    if out == ["NO-SAME-TICK"]:
        pytest.skip("the two writes never landed in one timestamp tick")
    return out


@pytest.mark.skipif(not _tools(), reason="needs root, unshare, mount and mkfs.ext2")
def test_a_same_tick_rewrite_after_a_listing_is_listed_as_it_is(tmp_path: Path) -> None:
    assert _listed_after_a_same_tick_rewrite(tmp_path, SCRIPT) == ["SAME"]


@pytest.mark.skipif(not _tools(), reason="needs root, unshare, mount and mkfs.ext2")
def test_a_same_tick_rewrite_after_our_write_is_listed_as_it_is(tmp_path: Path) -> None:
    """The hash of the Store's own write (Store._written_at) was cached at once: another
    program's same-size rewrite in the tick after a push's rename was listed as the
    push's content from 2 s on. Now cached only once not racy."""
    assert _listed_after_a_same_tick_rewrite(tmp_path, WRITE_SCRIPT) == ["SAME"]
