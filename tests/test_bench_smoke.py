"""``bench/run.py --quick`` runs to the end: both tools push, every tree verifies, a table prints.

A smoke test only: timings on a shared CI machine mean nothing, so none is
asserted. The full benchmark is run by hand (see bench/README.md).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import run_bench

@pytest.mark.ssh
def test_bench_quick_completes_and_verifies(tmp_path: Path) -> None:
    stdout, raw = run_bench("run.py", "--quick", tmp_path=tmp_path, needs=("rsync",))
    assert "| scenario | fetchsync | rsync | ratio (fetchsync/rsync) | target |" in stdout
    assert ("| scenario | fetchsync | rsync | ratio of the medians | median of the rounds' ratios "
            "| target |") in stdout
    assert "verification: PASS" in stdout
    assert raw["verified"] is True
    scenarios = {s["scenario"] for s in raw["samples"]}
    assert scenarios == {"initial", "noop", "edit", "insert", "rename"}
    assert {s["tool"] for s in raw["samples"]} == {"fetchsync", "rsync"}
    initial = raw["summary"]["fetchsync"]["initial"]
    assert len(initial["round_ratios"]) == sum(
        1 for s in raw["samples"] if s["scenario"] == "initial" and s["tool"] == "fetchsync")
    assert initial["round_ratio"] > 0
    # both went through the counting proxy
    assert all(s["bytes"] > 0 for s in raw["samples"] if s["scenario"] == "initial")


@pytest.mark.ssh
def test_bench_watch_quick_completes_and_verifies(tmp_path: Path) -> None:
    """``bench/watch.py --quick``: fetchsync watch and lsyncd each mirror every save and the burst."""
    stdout, raw = run_bench("watch.py", "--quick", tmp_path=tmp_path, needs=("rsync", "lsyncd"))
    assert "| tool | median | p90 | min | max | lost | start-up to live |" in stdout
    assert "verification: PASS" in stdout
    for tool in ("fetchsync", "lsyncd"):
        assert raw["latency"][tool] and all(x is not None for x in raw["latency"][tool])
        assert raw["burst"][tool]["missing"] == 0
    assert not any(raw["verification"].values())
