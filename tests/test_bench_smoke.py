"""The bench runs to the end: both tools push, every tree verifies, the report has its fields.

Smoke tests only: timings on a shared CI machine mean nothing, so none is
asserted, except the lower bounds the link shaper must guarantee (a shaped
link is never faster than its rate and delay allow; being slower is the
machine's business). The full benchmarks are run by hand (bench/README.md).
"""

from __future__ import annotations

import hashlib
import os
import select
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from helpers import run_bench

BENCH = Path(__file__).resolve().parent.parent / "bench"
sys.path.insert(0, str(BENCH))

from countproxy import LINKS, Counter, link_state, parse_link, set_link_state
from robot import ROBOT_USER, default_robot_user, ensure_account


class _Echo:
    """A TCP server on 127.0.0.1 that sends back whatever it receives, one client."""

    def __init__(self) -> None:
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.port = self.srv.getsockname()[1]
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        conn, _ = self.srv.accept()
        with conn:
            while data := conn.recv(1 << 16):
                conn.sendall(data)

    def close(self) -> None:
        self.srv.close()


def _proxy(port: int, countdir: Path, link: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [
            sys.executable,
            "-S",
            str(BENCH / "countproxy.py"),
            "127.0.0.1",
            str(port),
            str(countdir),
            link,
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
    )


def _read_exactly(proc: subprocess.Popen[bytes], n: int) -> bytes:
    assert proc.stdout is not None
    out = b""
    while len(out) < n:
        chunk = os.read(proc.stdout.fileno(), n - len(out))
        assert chunk, "the proxy closed early"
        out += chunk
    return out


@pytest.mark.parametrize("name", ["weak", "loopback"])
def test_shaper_delivers_intact_and_never_faster_than_the_link(tmp_path: Path, name: str) -> None:
    """Through ``countproxy.py HOST PORT DIR LINK``: 1 MiB each way arrives byte for byte,
    no sooner than its serialisation time at the rate; a ping-pong takes at least two
    one-way delays; the counters see every byte and the proxy's end."""
    link = LINKS[name]
    echo = _Echo()
    proc = _proxy(echo.port, tmp_path / "wire", name)
    try:
        assert proc.stdin is not None
        proc.stdin.write(b"?")
        proc.stdin.flush()
        assert _read_exactly(proc, 1) == b"?"  # connected (the proxy's start is not timed)
        pings = 3
        t0 = time.monotonic()
        for i in range(pings):
            proc.stdin.write(bytes([65 + i]))
            proc.stdin.flush()
            assert _read_exactly(proc, 1) == bytes([65 + i])
        ping_pong = (time.monotonic() - t0) / pings
        data = hashlib.shake_256(b"seed").digest(1 << 20)
        t0 = time.monotonic()
        writer = threading.Thread(target=lambda: (proc.stdin.write(data), proc.stdin.close()))  # type: ignore[union-attr]
        writer.start()
        back = _read_exactly(proc, len(data))
        bulk = time.monotonic() - t0
        writer.join()
        assert back == data
        assert proc.wait(10) == 0  # stdin's EOF -> the server's EOF -> the proxy ends
    finally:
        if proc.poll() is None:
            proc.kill()
        echo.close()
    totals = Counter(tmp_path / "wire").settle(live=0, timeout=5)
    assert (totals.up, totals.down) == (1 + pings + len(data), 1 + pings + len(data))
    assert 0 < Counter(tmp_path / "wire").cpu() < 60  # the proxy's own CPU, as it stopped
    if link is not None:
        assert ping_pong >= 2 * link.delay
        assert bulk >= len(data) / link.rate + 2 * link.delay


def test_shaper_outages_hold_then_deliver_and_cuts_refuse(tmp_path: Path) -> None:
    """``link.state``: a blackhole holds bytes (none arrive) and delivers them once the link
    is back; a cut ends an open connection and refuses a new one until the link is up."""
    wire = tmp_path / "wire"
    wire.mkdir()
    echo = _Echo()
    proc = _proxy(echo.port, wire, "wifi")
    try:
        assert proc.stdin is not None and proc.stdout is not None
        proc.stdin.write(b"a")
        proc.stdin.flush()
        assert _read_exactly(proc, 1) == b"a"
        set_link_state(wire, "blackhole")
        time.sleep(0.2)
        proc.stdin.write(b"b")
        proc.stdin.flush()
        ready, _, _ = select.select([proc.stdout], [], [], 0.5)
        assert not ready  # held while the link is a blackhole
        set_link_state(wire, "up")
        assert _read_exactly(proc, 1) == b"b"
        set_link_state(wire, "cut")
        assert proc.wait(5) == 0 and proc.stdout.read() == b""  # the connection ended
        refused = _proxy(echo.port, wire, "wifi")
        assert refused.wait(5) == 1  # a new one is refused while cut
    finally:
        for p in (proc,):
            if p.poll() is None:
                p.kill()
        echo.close()
    assert link_state(wire) == "cut"
    set_link_state(wire, "up")
    assert link_state(wire) == "up"


def test_an_unknown_robot_account_is_one_line_not_a_new_account() -> None:
    """``--robot-user`` names an account that exists; only the bench's own is created."""
    with pytest.raises(SystemExit, match="no such account"):
        ensure_account("fsbench-no-such-user")


def test_link_profiles_and_custom_links() -> None:
    wifi, weak = LINKS["wifi"], LINKS["weak"]
    assert wifi is not None and weak is not None and LINKS["loopback"] is None
    assert (wifi.rate * 8, wifi.delay) == (40e6, 0.004)
    assert (weak.rate * 8, weak.delay) == (8e6, 0.025)
    custom = parse_link("100:1.5")
    assert custom is not None and (custom.rate * 8, custom.delay) == (100e6, 0.0015)
    for bad in ("fast", "0:4", "10:-1", "10"):
        with pytest.raises(ValueError):
            parse_link(bad)


# the last commit before the modules moved into packages (fetchsync/link, fetchsync/sync, ...)
FLAT_MODULES_REV = "48c1793"


def _have_commit(rev: str) -> bool:
    repo = BENCH.parent
    return (
        subprocess.run(
            ["git", "-C", str(repo), "cat-file", "-e", f"{rev}^{{commit}}"],
            capture_output=True,
            check=False,
        ).returncode
        == 0
    )


@pytest.mark.slow
@pytest.mark.ssh
def test_bench_quick_completes_and_verifies(tmp_path: Path) -> None:
    """``bench/run.py --quick`` (a smaller tree, one round) runs to the end, every tree
    verified; with ``--baseline-rev`` of a commit whose modules sit elsewhere, that commit's
    fetchsync runs from its own tree in the same rounds (an A/B of any two commits)."""
    old = FLAT_MODULES_REV if _have_commit(FLAT_MODULES_REV) else None
    ab = ["--baseline-rev", old] if old else []
    stdout, raw = run_bench(
        "run.py",
        "--quick",
        "--files",
        "200",
        "--size-mb",
        "4",
        "--reps",
        "1",
        *ab,
        tmp_path=tmp_path,
        needs=("rsync",),
    )
    assert "| scenario | fetchsync | rsync | ratio (fetchsync/rsync) | target |" in stdout
    assert (
        "| scenario | fetchsync | rsync | ratio of the medians | median of the rounds' ratios "
        "| target |"
    ) in stdout
    assert "verification: PASS" in stdout
    assert raw["verified"] is True
    scenarios = {s["scenario"] for s in raw["samples"]}
    assert scenarios == {"initial", "noop", "edit", "insert", "rename"}
    tools = {"fetchsync", "rsync"} | ({f"fetchsync@{old}"} if old else set())
    assert {s["tool"] for s in raw["samples"]} == tools
    initial = raw["summary"]["fetchsync"]["initial"]
    assert len(initial["round_ratios"]) == sum(
        1 for s in raw["samples"] if s["scenario"] == "initial" and s["tool"] == "fetchsync"
    )
    assert initial["round_ratio"] > 0
    # both went through the counting proxy
    assert all(s["bytes"] > 0 for s in raw["samples"] if s["scenario"] == "initial")
    # the rows to paste into bench/README.md's Latest results, in the report and the JSON
    assert "Rows for bench/README.md's Latest results (loopback, run.py" in stdout
    figures = [r["figure"] for r in raw["results_rows"]]
    assert figures[:2] == ["initial push, time (fresh robot trees)", "initial push, bytes"]
    assert "insert / rename, bytes beyond no-op" in figures and "no-op push, time" in figures
    assert all(r["verdict"] in ("**PASS**", "**MISS**", "") for r in raw["results_rows"])
    # the no-op push's wall time is set against the interpreter's start
    assert raw["startup"]["fetchsync"] > 0 and "No-op push of fetchsync: " in stdout
    # the robot is a robot's account (as root: the bench's own, with a stock ~/.bashrc and the
    # system python3), and every tool's tree on the robot was written as that account
    robot = default_robot_user()
    assert raw["robot"]["user"] == robot
    if os.geteuid() == 0:
        assert robot == ROBOT_USER and raw["robot"]["python3"] != "?"
        assert ".pyenv" not in raw["robot"]["python3"]
    assert raw["owners"] and all(o == [robot] for o in raw["owners"].values()), raw["owners"]
    assert f"Robot: account {robot} " in stdout
    # each fetchsync imported its own tree's modules
    repo = BENCH.parent.resolve()
    assert Path(raw["sources"]["fetchsync"]) == repo / "fetchsync"
    # every fetchsync keeps its own connection master: a no-op push opens no new connection
    # (a baseline without one would be timed with a login and an endpoint start each push)
    for tool in tools - {"rsync"}:
        noops = [s for s in raw["samples"] if s["tool"] == tool and s["scenario"] == "noop"]
        assert noops and all(s["connections"] == 0 for s in noops), (tool, noops)
    if old:
        tree = (tmp_path / "work" / f"baseline-{old}" / "fetchsync").resolve()
        # its bytecode written, as an installed copy's is (not compiled at every push)
        assert list((tree / "__pycache__").glob("*.pyc"))
        assert Path(raw["sources"][f"fetchsync@{old}"]) == tree
        assert raw["series"] == [f"fetchsync@{old}", "fetchsync"]
        assert f"A/B: fetchsync (this checkout) against fetchsync@{old}" in stdout
        assert set(raw["ab"][f"fetchsync@{old}"]) == scenarios


@pytest.mark.slow
@pytest.mark.ssh
def test_bench_watch_quick_completes_and_verifies(tmp_path: Path) -> None:
    """``bench/watch.py --quick --link wifi``: fetchsync watch and lsyncd each mirror every save
    and the burst, and recover from each outage (a blackhole, a cut, the robot's sshd
    restarting) with the save made during it on the robot and the tree identical."""
    stdout, raw = run_bench(
        "watch.py", "--quick", "--link", "wifi", tmp_path=tmp_path, needs=("rsync", "lsyncd")
    )
    assert "| tool | median | p90 | min | max | lost | start-up to live |" in stdout
    assert raw["robot"]["user"] == default_robot_user()  # logged in as the robot's account
    assert "verification: PASS" in stdout
    for tool in ("fetchsync", "lsyncd"):
        assert raw["latency"][tool] and all(x is not None for x in raw["latency"][tool])
        assert raw["burst"][tool]["missing"] == 0
        cycles = raw["recovery"][tool]
        assert [c["outage"] for c in cycles] == ["blackhole", "cut", "sshd-restart"]
        for c in cycles:
            assert c["after_up"] is not None and not c["differences"], (tool, c)
        before, after = cycles[2]["listener"]  # the robot's sshd was another process after
        assert before and after and before != after
    assert "| fetchsync | sshd-restart 2 s |" in stdout
    figures = [r["figure"] for r in raw["results_rows"]]
    assert figures[0] == "watch: save → same bytes on the robot, p50 (p90)"
    assert any(f.startswith("recovery: the robot's sshd back") for f in figures), figures
    assert any(f.startswith("recovery: link back") for f in figures), figures
    assert not any(raw["verification"].values())


@pytest.mark.slow
@pytest.mark.ssh
def test_bench_history_quick_replays_real_commits_and_verifies(tmp_path: Path) -> None:
    """``bench/history.py --quick``: rclcpp's bundle checked out, pushed by both tools, two
    commits and a release switch replayed, both robot trees identical after every step."""
    bundle = Path("/work/shared/data/rclcpp.bundle")
    if not bundle.is_file():
        pytest.skip(f"{bundle} is not here")
    stdout, raw = run_bench(
        "history.py", "--quick", "--link", "wifi", tmp_path=tmp_path, needs=("rsync", "git")
    )
    assert "verification: PASS" in stdout and raw["verified"] is True
    assert raw["robot"]["user"] == default_robot_user()  # logged in as the robot's account
    assert [(s["kind"], s["index"]) for s in raw["steps"]] == [
        ("initial", 0),
        ("noop", 0),
        ("commit", 0),
        ("commit", 1),
        ("switch", 0),
    ]
    for step in raw["steps"]:
        assert set(step["verified"]) == {"fetchsync", "rsync"}
        assert not any(step["verified"].values())
    assert raw["repository"]["commits"] == 2 and raw["repository"]["files"] > 100
    rows = raw["summary"]["fetchsync"]
    for kind in ("initial", "commit", "switch"):
        for key in ("time_ratio", "time_step_ratio", "bytes_ratio", "bytes_total_ratio"):
            assert key in rows[kind]
        for tool in ("fetchsync", "rsync"):
            assert set(rows[kind][tool]) == {"seconds", "seconds_total", "bytes", "bytes_total"}
    assert rows["commit"]["bytes_target"] == 0.8  # issue 24's target on wifi
    assert all(s["bytes"] > 0 for s in raw["samples"])  # every push went through the shaper
    assert "| one commit | 2 |" in stdout and "| a release switch | 1 |" in stdout
    rows = {r["figure"]: r for r in raw["results_rows"]}
    assert rows["real history, per commit: bytes beyond no-op"]["target"] == "≤ 0.8x"
    assert "release switches: time" in rows and "rclcpp's first push, time / bytes" in rows


def test_one_command_per_profile_runs_the_readme_runs() -> None:
    """``bench/profile.py PROFILE --dry-run``: the scripts and arguments of the final runs."""
    out = subprocess.run(
        [sys.executable, str(BENCH / "profile.py"), "wifi", "--dry-run"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.splitlines()
    assert [line.split()[1].rsplit("/", 1)[1] for line in out] == [
        "run.py",
        "watch.py",
        "history.py",
    ]
    assert "--link wifi --files 2000 --size-mb 40" in out[0]
    assert "--commits 30 --switches 4" in out[2]
