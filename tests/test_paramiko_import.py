"""paramiko is imported without invoke, and `Match exec` in an ssh config still works.

Each case runs in a new interpreter: the test process may have imported invoke.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path


def run(code: str) -> str:
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, check=False, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip()


def test_connecting_code_does_not_import_invoke_and_invoke_still_imports():
    out = run("""
        import sys
        import fetchsync.ssh
        import paramiko.config
        print("invoke" in sys.modules, paramiko.config.invoke is None)
        import invoke  # held back from paramiko only, not from anyone else
        print(bool(invoke.run))
    """)
    assert out.splitlines() == ["False True", "True"]


def test_match_exec_in_the_ssh_config_runs_its_command(tmp_path: Path):
    config = tmp_path / "config"
    config.write_text("Match host robot exec \"true\"\n    HostName 10.1.2.3\n"
                      "Match host robot exec \"false\"\n    User nobody-here\n"
                      "Host robot\n    User fetch\n")
    out = run(f"""
        import fetchsync.ssh as ssh
        found = ssh.load_ssh_config({str(config)!r}).lookup("robot")
        print(found["hostname"], found["user"])
    """)
    assert out == "10.1.2.3 fetch"


def test_a_config_without_match_exec_leaves_invoke_alone(tmp_path: Path):
    config = tmp_path / "config"
    config.write_text("Host robot\n    HostName 10.1.2.4\n    # exec is only a word in a comment\n")
    out = run(f"""
        import sys
        import fetchsync.ssh as ssh
        print(ssh.load_ssh_config({str(config)!r}).lookup("robot")["hostname"], "invoke" in sys.modules)
    """)
    assert out == "10.1.2.4 False"


def test_paramiko_gets_its_version_without_importlib_metadata():
    """paramiko's own version is read from its dist-info (importlib.metadata costs
    ~15-20 ms to import); the real module stays importable and agrees."""
    out = run("""
        import sys
        import fetchsync.ssh
        import paramiko
        from paramiko.transport import Transport
        print("importlib.metadata" in sys.modules)
        import importlib.metadata
        print(paramiko.__version__ == importlib.metadata.version("paramiko") != "")
        print(Transport._CLIENT_ID == "paramiko_" + paramiko.__version__)
        print(bool(importlib.metadata.version("click")))
    """)
    assert out.splitlines() == ["False", "True", "True", "True"]
