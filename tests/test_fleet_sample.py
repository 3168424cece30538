"""A fleet push samples each file's compressibility once for all its robots (issue 27: a
zlib pass over up to 32 KiB of each file of 64 KiB or more, per robot before), and every
robot gets the same decision, hence the same bytes, as a single push would."""

from __future__ import annotations

import collections
import os
import threading
from pathlib import Path

import pytest
from test_fleet import fleet_env, push_three_in_process  # noqa: F401 - the fixture

from fetchsync.protocol import wire
from fetchsync.sync import engine as sync

pytestmark = pytest.mark.ssh


def test_a_fleet_push_samples_each_file_once(fleet_env, tmp_path, monkeypatch, clean_process_env):  # noqa: F811
    src = Path(fleet_env["FETCHSYNC_WORKSPACE"]) / "src"
    big = src / "pkg_big"
    big.mkdir(parents=True)
    for i in range(4):  # text (compressible) and random (not): both decisions
        (big / f"text{i}.cpp").write_bytes(b"int f%d(int x) { return x; }\n" % i * 4000)
        (big / f"blob{i}.bin").write_bytes(os.urandom(100_000))
    monkeypatch.setattr(sync, "RACY_NS", 0)  # the files above count as settled
    sampled: collections.Counter[int] = collections.Counter()
    lock = threading.Lock()
    real = wire.compressible

    def compressible(data, **kw):
        if len(data) in (112_000, 100_000):  # this test's files, not the workspace's
            with lock:
                sampled[len(data), bytes(data[:64])] += 1
        return real(data, **kw)

    monkeypatch.setattr(wire, "compressible", compressible)
    push_three_in_process(fleet_env, monkeypatch, tmp_path, src)
    assert len(sampled) == 8  # each big file sampled ...
    assert max(sampled.values()) == 1, sampled.most_common(2)  # ... once for the three robots
