"""``bench/scale.py`` at a small size runs to the end: push, no-op push, watch start-up and one edit.

The reduced, CI form of the 100,000-file scale benchmark (issue 5): 3,000
files over the real sshd. It asserts that every step completes, that the
robot's tree equals the local one after each, and that the table with the
targets prints; never a timing or a memory figure (a shared CI machine makes
them meaningless). The full run is by hand: see bench/README.md.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from sshd import find_sshd

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.ssh
def test_scale_small_completes_and_verifies(tmp_path: Path) -> None:
    if find_sshd() is None:
        if os.environ.get("CI"):
            pytest.fail("sshd is installed by .ci/run; it is missing")
        pytest.skip("needs sshd (openssh-server)")
    out_json = tmp_path / "scale.json"
    proc = subprocess.run(
        [
            sys.executable,
            str(REPO / "bench" / "scale.py"),
            "--files",
            "3000",
            "--size-mb",
            "20",
            "--json",
            str(out_json),
            "--workdir",
            str(tmp_path / "work"),
        ],
        cwd=REPO,
        check=False,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == 0, f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-5000:]}"
    assert "| step | time | fetchsync peak RSS | robot endpoint peak RSS | target | verdict |" in (
        proc.stdout
    )
    assert "verification: PASS" in proc.stdout
    raw = json.loads(out_json.read_text())
    assert raw["failures"] == []
    assert raw["verification"] == {
        "initial push": [],
        "no-op push": [],
        "watch, after one edit": [],
    }
    assert (
        raw["initial"]["returncode"] == 0 and raw["initial"]["files"] == raw["workspace"]["files"]
    )
    assert raw["noop"]["returncode"] == 0 and raw["noop"]["files"] == 0
    watch = raw["watch"]
    assert watch["status_state"] == "live"
    assert watch["edit_seconds"] is not None
    # the measurements were taken (figures exist), whatever they are
    assert raw["initial"]["client_peak_kib"] > 0 and raw["initial"]["endpoint_peak_kib"] > 0
    assert watch["agent_peak_live_kib"] > 0 and watch["inotify_watches"] > 0
