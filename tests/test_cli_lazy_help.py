"""``fetchsync --help`` and tab completion list every verb without importing them all.

The verbs in LAZY_COMMANDS are imported when used; listing them with their first
sentences used to import each (snapshot, lint, workspace-status: ~70 ms of CPU at every
``--help`` and every tab). Their sentences are kept in LAZY_HELP instead: these tests
check that each is still its command's own, and that listing imports none of them.
"""

from __future__ import annotations

import importlib
import json
import subprocess
import sys

import click
import pytest

from fetchsync.cli import LAZY_COMMANDS, LAZY_HELP

WRAPPER = """
import atexit, json, sys
before = set(sys.modules)
atexit.register(lambda: print("MODULES " + json.dumps(sorted(set(sys.modules) - before))))
sys.argv = ["fetchsync", *json.loads(sys.argv[1])]
import runpy
runpy.run_module("fetchsync", run_name="__main__")
"""

LAZY_MODULES = {spec.split(":")[0] for spec in LAZY_COMMANDS.values()}


def run(args: list[str], **env: str) -> tuple[str, set[str]]:
    """The CLI's output for ``args`` and the modules it imported beyond site's."""
    import os

    proc = subprocess.run(
        [sys.executable, "-c", WRAPPER, json.dumps(args)],
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    out, _, modules = proc.stdout.rpartition("MODULES ")
    return out, set(json.loads(modules))


@pytest.mark.parametrize("verb", sorted(LAZY_COMMANDS))
def test_each_lazy_verbs_sentence_is_its_commands_own(verb):
    module, attr = LAZY_COMMANDS[verb].split(":")
    command: click.Command = getattr(importlib.import_module(module), attr)
    assert not command.hidden
    assert LAZY_HELP[verb] == command.get_short_help_str(limit=1000)


def test_help_lists_every_verb_and_imports_none_of_them():
    out, imported = run(["--help"])
    assert not LAZY_MODULES & imported, sorted(LAZY_MODULES & imported)
    for verb in LAZY_COMMANDS:
        if verb != "debug-snapshot":  # an alias: named on snapshot's line
            assert f"  {verb}  " in out or f"  {verb}\n" in out, verb
    words = " ".join(out.split())
    for verb, text in LAZY_HELP.items():
        if verb != "debug-snapshot":
            assert f"{verb} {text.rstrip('.')}" in words, verb
    assert "timestamped archive (fetch_tools' name: debug-snapshot)." in words


def test_tab_completion_of_the_verbs_imports_none_of_them():
    out, imported = run(
        [], _FETCHSYNC_COMPLETE="zsh_complete", COMP_WORDS="fetchsync ", COMP_CWORD="1"
    )
    assert not LAZY_MODULES & imported, sorted(LAZY_MODULES & imported)
    lines = out.splitlines()
    for verb in [*LAZY_COMMANDS, "push", "pull"]:
        assert verb in lines, verb
    i = lines.index("workspace-status")
    assert lines[i + 1] == click.utils.make_default_short_help(LAZY_HELP["workspace-status"], 45)
    out, _ = run([], _FETCHSYNC_COMPLETE="bash_complete", COMP_WORDS="fetchsync wa", COMP_CWORD="1")
    assert out.split() == ["plain,watch"]
