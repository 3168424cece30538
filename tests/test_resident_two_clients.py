"""Several plain pushes at once with a resident: one is the resident's, the others go the
normal way beside it (busy). Every push ends well, and the robot and the state end as
one push would leave them: nothing is pushed twice into a conflict, nothing lost."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from helpers import fetchsync, report, tree_of
from test_resident import env, resident_up  # noqa: F401 - the fixture

pytestmark = pytest.mark.ssh


def test_pushes_at_once_beside_a_resident_all_end_well(env, remote_dir):  # noqa: F811
    resident_up(env)
    src = Path(env["FETCHSYNC_WORKSPACE"]) / "src"
    for round_ in range(3):
        for i in range(40):
            (src / f"my_pkg/f{i}.txt").write_text(f"round {round_} file {i}\n" * 200)
        procs = [
            subprocess.Popen(
                [sys.executable, "-m", "fetchsync", "push", "--json"],
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
            )
            for _ in range(4)
        ]
        outs = [p.communicate(timeout=120) for p in procs]
        for p, (_out, err) in zip(procs, outs):
            assert p.returncode == 0, err
            assert "Traceback" not in err.decode()
        reports = [report(subprocess.CompletedProcess([], 0, out, err)) for out, err in outs]
        assert all(r["conflicts"] == [] for r in reports), reports
        assert tree_of(src) == tree_of(remote_dir / "src")
    # the state is true: the next push has nothing to do
    r = report(fetchsync("push", "--json", env=env))
    assert r["files"] == 0 and r["deleted"] == 0
    assert not list((remote_dir / ".fetchsync").glob("conflicts/*"))
