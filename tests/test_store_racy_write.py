"""The robot's stat cache never keeps the hash of its own write while the file could still
change unseen: a push's write is renamed into place and its hash was cached at once
(Store._written_at); another program rewriting the file at the same size within the same
timestamp tick (one second on ext2/ext3's 128-byte inodes, a jiffy on ext4 before Linux
6.13) left size, times and inode as they were, and from two seconds on every Store listed
the push's content: drift missed the robot-side edit, and the next push replaced it with
no conflict copy. Now a write whose file is still racy is not cached: the next listing
reads it once. Real file system, as tests/test_store_racy_cache.py (the listing's hash)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = r"""
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


@pytest.mark.skipif(not _tools(), reason="needs root, unshare, mount and mkfs.ext2")
def test_a_same_tick_rewrite_after_our_write_is_listed_as_it_is(tmp_path: Path) -> None:
    image, mnt = tmp_path / "ext2.img", tmp_path / "mnt"
    mnt.mkdir()
    with open(image, "wb") as fh:
        fh.truncate(16 << 20)
    # 128-byte inodes: whole-second timestamps
    subprocess.run(
        ["mkfs.ext2", "-q", "-F", "-I", "128", str(image)], check=True, capture_output=True
    )
    (tmp_path / "check.py").write_text(SCRIPT)
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
    assert out == ["SAME"], (proc.stdout, proc.stderr)
