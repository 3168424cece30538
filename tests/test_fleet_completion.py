"""Completing ``--robot`` with groups of robots.toml (``@lab``) and lists (``a,@lab``):
the names offered, and what an interactive bash puts on the command line at a Tab."""

from __future__ import annotations

import os
import pty
import select
import shlex
import shutil
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from fetchsync.chores.shell import robot_names
from fetchsync.cli import cli


def _home(tmp_path: Path) -> Path:
    home = tmp_path / "home"
    (home / ".config/fetchsync").mkdir(parents=True)
    (home / ".config/fetchsync/robots.toml").write_text(
        'lab = ["fetch1", "fetch2"]\nlab2 = ["fetch3"]\nclass = ["freight0"]\n'
        '[robots.fetch1]\nremote_workspace = "~/ws"\n'
    )
    return home


def test_groups_and_lists_are_completed(tmp_path):
    home = _home(tmp_path)
    none = str(tmp_path / "none")
    assert robot_names("@", home=home, global_known_hosts=none) == ["@lab", "@lab2", "@class"]
    assert robot_names("@la", home=home, global_known_hosts=none) == ["@lab", "@lab2"]
    assert robot_names("x,@c", home=home, global_known_hosts=none) == ["x,@class"]
    assert robot_names("x,fetch", home=home, global_known_hosts=none)[:2] == [
        "x,fetch0",
        "x,fetch1",
    ]
    (home / ".config/fetchsync/robots.toml").write_text("lab = [\n")  # broken: nothing, quietly
    assert robot_names("@", home=home, global_known_hosts=none) == []


def test_click_offers_groups_for_the_robot_option(tmp_path):
    result = CliRunner().invoke(
        cli,
        [],
        prog_name="fetchsync",
        env={
            "_FETCHSYNC_COMPLETE": "bash_complete",
            "COMP_WORDS": "fetchsync watch --robot fetch1,@la",
            "COMP_CWORD": "3",
            "HOME": str(_home(tmp_path)),
            "XDG_CONFIG_HOME": "",
        },
    )
    assert result.exit_code == 0
    assert result.output.splitlines() == ["plain,fetch1,@lab", "plain,fetch1,@lab2"]


def _interactive_bash(home: Path, tmp_path: Path, typed: list[str]) -> list[str]:
    """The command lines an interactive bash holds after each of ``typed`` and a Tab."""
    bash = shutil.which("bash")
    if bash is None:
        pytest.skip("bash not installed")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    wrapper = bin_dir / "fetchsync"  # this checkout's, whatever is installed
    wrapper.write_text(f'#!/bin/sh\nexec {shlex.quote(sys.executable)} -m fetchsync "$@"\n')
    wrapper.chmod(0o755)
    repo = str(Path(__file__).resolve().parents[1])
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("FETCH", "_FETCHSYNC", "XDG_CONFIG")) and k not in ("BASH_ENV", "ENV")
    }
    env.update(HOME=str(home), PATH=f"{bin_dir}:{env.get('PATH', '')}", PYTHONPATH=repo)
    env["PS1"] = "$ "
    init = tmp_path / "init.bash"
    result = CliRunner().invoke(cli, ["shell-init", "bash"], prog_name="fetchsync")
    init.write_text(result.output)
    pid, fd = pty.fork()
    if pid == 0:  # the child: an interactive bash on the terminal
        os.execve(bash, [bash, "--norc", "--noprofile", "-i"], env)

    def read_until(mark: bytes, timeout: float = 20.0) -> bytes:
        out, end = b"", time.monotonic() + timeout
        while mark not in out and time.monotonic() < end:
            if select.select([fd], [], [], 0.1)[0]:
                try:
                    out += os.read(fd, 4096)
                except OSError:
                    break
        return out

    lines = []
    try:
        os.write(fd, f". {shlex.quote(str(init))}; echo READY\n".encode())
        read_until(b"READY\r\n")
        for text in typed:
            os.write(fd, text.encode() + b"\t")
            time.sleep(3)  # the completion runs fetchsync, then readline redraws
            os.write(fd, b"\x01echo LINE: \n")  # to the start of the line; print it
            out = read_until(b"\r\n$ ").decode(errors="replace")
            lines.append(out.split("LINE: ")[-1].split("\r\n")[0].strip())
    finally:
        os.write(fd, b"exit\n")
        os.waitpid(pid, 0)
        os.close(fd)
    return lines


def test_an_interactive_bash_completes_a_group_after_a_comma(tmp_path):
    home = _home(tmp_path)
    typed = [
        "fetchsync push --robot @cl",
        "fetchsync run --robot fetch1,@cl",
        "fetchsync push --robot=@cl",
    ]
    assert _interactive_bash(home, tmp_path, typed) == [
        "fetchsync push --robot @class",
        "fetchsync run --robot fetch1,@class",
        "fetchsync push --robot=@class",
    ]
