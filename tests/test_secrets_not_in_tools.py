"""Secrets given to a call are in the environment of none of the tools it runs on the
laptop: the linters ``lint`` runs as processes (cpplint, catkin_lint, ament's) and git (``workspace-status``) were given the call's
whole environment, FETCHSYNC_SUDO_PASSWORD and the account passwords included.
Each Python child here dumps its environment (a sitecustomize on PYTHONPATH)."""

from __future__ import annotations

import os
import sys

from helpers import clean_env, fetchsync
from test_secrets_not_inherited import SECRETS

DUMP = """
import os, sys
if os.environ.get("FSDUMP"):
    with open(os.path.join(os.environ["FSDUMP"], "%d" % os.getpid()), "wb") as fh:
        fh.write(open("/proc/self/cmdline", "rb").read() + b"\\n" + open("/proc/self/environ", "rb").read())
"""


def test_the_linters_get_no_password(tmp_path):
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(DUMP)
    dumps = tmp_path / "dumps"
    dumps.mkdir()
    pkg = tmp_path / "ws/src/pkg"
    pkg.mkdir(parents=True)
    (pkg / "package.xml").write_text("<package><name>pkg</name></package>\n")
    (pkg / "node.cpp").write_text("int main() { return 0; }\n")
    env = clean_env(**SECRETS, FSDUMP=str(dumps))
    env["PYTHONPATH"] = os.pathsep.join([str(site), *sys.path])
    proc = fetchsync("lint", "--tool", "cpplint", str(pkg), env=env, check=False)
    assert proc.returncode in (0, 1), proc.stderr.decode()
    tools = [p.read_bytes() for p in dumps.iterdir()]
    tools = [t for t in tools if b"\0fetchsync\0" not in t.split(b"\n", 1)[0]]  # not the CLI
    assert tools, "no linter ran"
    for seen in tools:
        for name, value in SECRETS.items():
            assert value.encode() not in seen, f"{name} given to the linter"


def test_git_gets_no_password(tmp_path):
    """``workspace-status`` runs git in the repositories of the workspace: git is a fake on PATH that writes its environment, then runs the real one."""
    import shutil

    from helpers import local_env

    real = shutil.which("git")
    if real is None:
        import pytest

        pytest.skip("no git")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    dump = tmp_path / "git-environ"
    (bin_dir / "git").write_text(f'#!/bin/sh\ncat /proc/$$/environ >> {dump}\nexec {real} "$@"\n')
    (bin_dir / "git").chmod(0o755)
    env = local_env(tmp_path, **SECRETS)
    env["PATH"] = f"{bin_dir}{os.pathsep}{env['PATH']}"
    import subprocess

    subprocess.run([real, "init", "-q", str(tmp_path / "ws/src/my_pkg")], check=True)
    proc = fetchsync("workspace-status", env=env, check=False)
    assert dump.exists(), proc.stderr.decode()
    for name, value in SECRETS.items():
        assert value.encode() not in dump.read_bytes(), f"{name} given to git"


def test_a_local_build_gets_no_password(tmp_path, monkeypatch):
    """``pull --build`` builds here (chores.build.LocalRunner: bash runs each step); a
    sudo password reaches a step on its stdin, never in its environment."""
    from fetchsync.chores.build import LocalRunner, Step

    for name, value in SECRETS.items():
        monkeypatch.setenv(name, value)
    dump = tmp_path / "step-environ"
    step = Step(what="env", script=f"cat /proc/$$/environ > {dump}", program="cat")
    assert LocalRunner(stdout=2).run(step) == 0
    for name, value in SECRETS.items():
        assert value.encode() not in dump.read_bytes(), f"{name} given to a build step"
