"""Attacks on the fleet's shared reads (1fa4e2d: SharedPacks.read hands a content read for
one robot to the next while an lstat matches): a file rewritten to the same size with its
modification time put back (``cp -p``, ``touch -r``, tar or rsync -t restoring times), and
a file replaced by another one renamed over it, stamped alike. Only the change time,
which no user can set, tells them apart: each must be read again."""

from __future__ import annotations

import os
import time

from fetchsync.sync import engine as sync
from fetchsync.sync.engine import SharedPacks


def test_a_file_rewritten_with_its_mtime_put_back_is_read_again(tmp_path, monkeypatch):
    monkeypatch.setattr(sync, "RACY_NS", 0)  # files written by this test count as settled
    f = tmp_path / "a.cpp"
    f.write_bytes(b"int a = 1;\n")
    packs = SharedPacks()
    first, entry = packs.read(str(f))
    time.sleep(0.02)  # past the file system's timestamp tick
    f.write_bytes(b"int a = 2;\n")  # same size
    os.utime(f, ns=(entry.mtime_ns, entry.mtime_ns))  # the old mtime put back
    st = os.lstat(f)
    assert (st.st_size, st.st_mtime_ns, st.st_ino) == (entry.size, entry.mtime_ns, entry.ino)
    data, _ = packs.read(str(f))
    assert data == b"int a = 2;\n" and packs.reads_shared == 0


def test_a_file_renamed_over_with_the_same_stamps_is_read_again(tmp_path, monkeypatch):
    monkeypatch.setattr(sync, "RACY_NS", 0)
    f = tmp_path / "b.cpp"
    f.write_bytes(b"int b = 1;\n")
    packs = SharedPacks()
    first, entry = packs.read(str(f))
    time.sleep(0.02)
    other = tmp_path / "b.cpp.new"
    other.write_bytes(b"int b = 2;\n")
    os.chmod(other, entry.mode)
    os.utime(other, ns=(entry.mtime_ns, entry.mtime_ns))
    os.replace(other, f)  # an editor's or a tool's save: a new inode, stamped alike
    data, _ = packs.read(str(f))
    assert data == b"int b = 2;\n" and packs.reads_shared == 0
