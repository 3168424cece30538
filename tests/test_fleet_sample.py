"""A fleet push samples each file's compressibility once for all its robots (issue 27: a
zlib pass over up to 32 KiB of each file of 64 KiB or more, per robot before), and every
robot gets the same decision, hence the same bytes, as a single push would."""

from __future__ import annotations

import collections
import os
import threading
from pathlib import Path

import pytest
from helpers import tree_of
from test_fleet import fleet_env  # noqa: F401 - the fixture

from fetchsync.cli import cli
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
    for key, value in fleet_env.items():
        monkeypatch.setenv(key, value)
    for key in [k for k in os.environ if k not in fleet_env]:
        monkeypatch.delenv(key)
    with pytest.raises(SystemExit) as exit_:
        cli.main(["push", "--robot", "fetch1,fetch2,fetch3", "-j", "3"], standalone_mode=False)
    assert exit_.value.code == 0
    for name in ("fetch1", "fetch2", "fetch3"):
        assert tree_of(tmp_path / f"robot-{name}/src") == tree_of(src), name
    assert len(sampled) == 8  # each big file sampled ...
    assert max(sampled.values()) == 1, sampled.most_common(2)  # ... once for the three robots
