"""paramiko is imported without invoke unless an ssh config has a ``Match exec`` line.

paramiko.config imports invoke (and with it asyncio, yaml and unittest.mock) only to
run ``Match exec``; that was ~90 of paramiko's ~330 ms of import CPU here, paid by every
connection made without a connection master: a first push, the master itself."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

PLAIN = "Host robot\n    HostName 10.1.2.3\n    User fetch\n"
EXEC = 'Match host robot exec "true"\n    HostName 10.1.2.4\nHost robot\n    User fetch\n'


def _run(code: str) -> str:
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
        stdin=subprocess.DEVNULL,  # invoke reads its stdin
    )
    return out.stdout.strip()


def test_a_config_without_match_exec_resolves_without_importing_invoke(tmp_path: Path) -> None:
    config = tmp_path / "config"
    config.write_text(PLAIN)
    code = (
        "import sys; from fetchsync.link.ssh import load_ssh_config; "
        "from fetchsync.config import ssh_config_user; "
        f"found = load_ssh_config({str(config)!r}).lookup('robot'); "
        f"user = ssh_config_user('robot', ssh_config={str(config)!r}); "
        "print(found['hostname'], user, 'invoke' in sys.modules)"
    )
    assert _run(code) == "10.1.2.3 fetch False"


def test_match_exec_still_runs_through_either_reader(tmp_path: Path) -> None:
    config = tmp_path / "config"
    config.write_text(EXEC)
    for code in (
        "from fetchsync.link.ssh import load_ssh_config; "
        f"found = load_ssh_config({str(config)!r}).lookup('robot'); "
        "print(found['hostname'], found['user'])",
        "from fetchsync.config import ssh_config_user; "
        f"print(ssh_config_user('robot', ssh_config={str(config)!r}))",
    ):
        assert _run(code) in ("10.1.2.4 fetch", "fetch")
