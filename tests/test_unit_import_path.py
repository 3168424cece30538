"""The watch agent's systemd unit runs in the workspace (WorkingDirectory); where no
``fetchsync`` script is found (a pyenv shim on PATH) its ExecStart is ``python -m
fetchsync``, and -m puts the working directory first on the import path: a ``json.py``
lying in the workspace was imported by the agent. The unit's command keeps it off
(``-P``, Python 3.11+). Run here as the unit would, in a workspace holding one."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from fetchsync.agent import unit


@pytest.mark.skipif(sys.version_info < (3, 11), reason="python -P is 3.11's")
def test_the_units_python_command_imports_nothing_from_the_workspace(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["-c"])
    monkeypatch.setattr(unit.shutil, "which", lambda name: None)
    argv = unit.fetchsync_argv()
    assert "-m" in argv, argv
    ws = tmp_path / "ws"
    (ws / "src").mkdir(parents=True)
    hit = tmp_path / "imported"
    for name in ("json", "typing", "enum"):
        (ws / f"{name}.py").write_text(f"open({str(hit)!r}, 'a').write('{name}\\n')\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    proc = subprocess.run(
        [*argv, "--help"], cwd=ws, env=env, capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert not hit.exists(), hit.read_text()
