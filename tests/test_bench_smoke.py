"""``bench/run.py --quick`` runs to the end: both tools push, every tree verifies, a table prints.

A smoke test only: timings on a shared CI machine mean nothing, so none is
asserted. The full benchmark is run by hand (see bench/README.md).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from sshd import find_sshd

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.ssh
def test_bench_quick_completes_and_verifies(tmp_path: Path) -> None:
    if find_sshd() is None or shutil.which("rsync") is None:
        if os.environ.get("CI"):
            pytest.fail("sshd and rsync are installed by .ci/run; one is missing")
        pytest.skip("needs sshd (openssh-server) and rsync")
    out_json = tmp_path / "bench.json"
    proc = subprocess.run(
        [
            sys.executable,
            str(REPO / "bench" / "run.py"),
            "--quick",
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
    assert "| scenario | fetchsync | rsync | ratio (fetchsync/rsync) | target |" in proc.stdout
    assert "verification: PASS" in proc.stdout
    raw = json.loads(out_json.read_text())
    assert raw["verified"] is True
    scenarios = {s["scenario"] for s in raw["samples"]}
    assert scenarios == {"initial", "noop", "edit", "insert", "rename"}
    assert {s["tool"] for s in raw["samples"]} == {"fetchsync", "rsync"}
    # both went through the counting proxy
    assert all(s["bytes"] > 0 for s in raw["samples"] if s["scenario"] == "initial")


@pytest.mark.ssh
def test_bench_watch_quick_completes_and_verifies(tmp_path: Path) -> None:
    """``bench/watch.py --quick``: fetchsync watch and lsyncd each mirror every save and the burst."""
    if find_sshd() is None or shutil.which("rsync") is None or shutil.which("lsyncd") is None:
        if os.environ.get("CI"):
            pytest.fail("sshd, rsync and lsyncd are installed by .ci/run; one is missing")
        pytest.skip("needs sshd (openssh-server), rsync and lsyncd")
    out_json = tmp_path / "watch.json"
    proc = subprocess.run(
        [
            sys.executable,
            str(REPO / "bench" / "watch.py"),
            "--quick",
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
    assert "| tool | median | p90 | min | max | lost | start-up to live |" in proc.stdout
    assert "verification: PASS" in proc.stdout
    raw = json.loads(out_json.read_text())
    for tool in ("fetchsync", "lsyncd"):
        assert raw["latency"][tool] and all(x is not None for x in raw["latency"][tool])
        assert raw["burst"][tool]["missing"] == 0
    assert not any(raw["verification"].values())
