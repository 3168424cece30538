"""A file still being written in a new directory (redteam, session 23): the directory's
batch can end before the file does (the 5 ms quiet window between two writes, or the
100 ms cap) and is rescanned with what the file holds then, so the robot may get the
file as it was half-way (as rsync or lsyncd would); what must hold is that the file's
close sends its whole content and the robot ends with it, however the writes were
spread (the engine decides on stat: a grown file is sent again)."""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

import pytest
from helpers import fetchsync, ssh_env
from test_watch import Watch, same, wait_for


@pytest.mark.ssh
def test_a_file_written_slowly_in_a_new_directory_lands_whole_once_closed(
    ssh_home, remote_dir: Path, tmp_path: Path
) -> None:
    runtime = Path(tempfile.mkdtemp(prefix="fsw", dir="/tmp"))
    runtime.chmod(0o700)
    env = ssh_env(ssh_home.home, remote_dir, tmp_path, XDG_RUNTIME_DIR=str(runtime))
    src = tmp_path / "ws/src"
    fetchsync("push", env=env)
    w = Watch(env, tmp_path / "watch.log")
    robot = remote_dir / "src/newpkg/data.txt"
    seen = set()
    try:
        wait_for(lambda: w.status().get("state") == "live", what="the agent to be live")
        (src / "newpkg").mkdir()
        parts = [b"%07d partial line\n" % i * 2000 for i in range(4)]
        fd = os.open(src / "newpkg/data.txt", os.O_WRONLY | os.O_CREAT, 0o644)
        try:
            for part in parts:
                os.write(fd, part)
                deadline = time.monotonic() + 0.6  # past the quiet window and the cap
                while time.monotonic() < deadline:
                    if robot.exists():
                        seen.add(robot.read_bytes())
                    time.sleep(0.01)
        finally:
            os.close(fd)
        wait_for(lambda: same(src, remote_dir / "src"), what="the whole file on the robot")
        time.sleep(1.0)
        assert robot.read_bytes() == b"".join(parts)  # and it stays so
        assert same(src, remote_dir / "src")
        # what landed on the way was always some whole prefix of the writes, never torn
        whole = b"".join(parts)
        assert all(whole.startswith(got) for got in seen), [len(g) for g in seen]
    finally:
        w.stop()
        shutil.rmtree(runtime, ignore_errors=True)
    print("partial versions seen on the robot:", sorted(len(g) for g in seen))
