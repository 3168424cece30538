"""The early route (fetchsync.link.early) is remembered only where the route is the config
text's alone: the text was scanned for Match/Include by a regex of its own (lines ending
in LF, led by spaces or tabs) while paramiko reads the file in text mode (a CR ends a
line too) and strips any whitespace off a line (a form feed, a no-break space) before
its keyword; and CanonicalizeHostname makes the route a DNS answer. Each such config got
a memory: a later call then ran the remembered, now stale, ProxyCommand (or connected to
the old address) before the config was parsed. Against the real sshd."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import pytest
from test_ssh import extra_config
from test_ssh_early import _cache, _memories, _own_cache, _starts, opened, settled  # noqa: F401

from fetchsync.link import early
from fetchsync.link.ssh import SSHTransport

pytestmark = pytest.mark.ssh

PROXY = (
    "    ProxyCommand sh -c 'echo started >> {log}; exec ssh -F {{sshd_config}} "
    "-o BatchMode=yes -W {{host}}:{{port}} robot 2>/dev/null'\n"
)


def _via_proxy(log: Path) -> str:
    """A Host block reaching the sshd through a logged ProxyCommand, whatever the
    HostName resolved to (a canonicalized name keeps it)."""
    return (
        "Host viaproxy\n    HostName {host}\n    Port {port}\n    HostKeyAlias [{host}]:{port}\n"
        "{common}" + PROXY.format(log=log)
    )


def test_a_match_exec_read_across_cr_line_ends_runs_no_stale_proxy_command(
    ssh_home: Any,
    settled: None,  # noqa: F811
    opened: list[Any],  # noqa: F811
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``Match exec`` in a config with CR line ends (paramiko reads them as lines): the
    route changes with the command's answer, never with the config's identity."""
    monkeypatch.setattr(sys, "stdin", open(os.devnull))  # noqa: SIM115 - invoke reads it
    log, flag, other = tmp_path / "proxy.log", tmp_path / "on-vpn", tmp_path / "other.log"
    block = (
        "# fetchsync's early route\n"
        f'Match host viaproxy exec "test -e {flag}"\n'
        f"    ProxyCommand sh -c 'echo $$ >> {other}; exec sleep 30'\n" + _via_proxy(log)
    )
    extra_config(ssh_home, block)
    ssh_home.config.write_bytes(ssh_home.config.read_bytes().replace(b"\n", b"\r"))
    opened.append(SSHTransport.connect("viaproxy", connect_timeout=10.0))
    assert _starts(log) == 1
    flag.touch()  # the Match now holds: the config's route is the other command
    link = early.start("viaproxy")
    if link is not None:
        opened.append(link)
    assert link is None, f"the stale route {link.route} was opened"
    assert _starts(log) == 1


@pytest.mark.parametrize(
    "block",
    [
        "\fMatch host viaproxy user nobody\n    Port {port}\n",
        "\u00a0Match host viaproxy user nobody\n    Port {port}\n",
        "\vInclude /dev/null\n",
        "CanonicalizeHostname yes\nCanonicalDomains invalid\n",
    ],
    ids=["form-feed-match", "nbsp-match", "vtab-include", "canonicalize"],
)
def test_no_route_is_remembered_where_paramiko_reads_more_than_the_text(
    ssh_home: Any,
    settled: None,  # noqa: F811
    opened: list[Any],  # noqa: F811
    tmp_path: Path,
    block: str,
) -> None:
    log = tmp_path / "proxy.log"
    extra_config(ssh_home, block + _via_proxy(log))
    opened.append(SSHTransport.connect("viaproxy", connect_timeout=10.0))
    assert _starts(log) == 1  # the config was read and used as written
    assert _memories(_cache()) == []
    assert early.start("viaproxy") is None


def test_a_same_size_edit_with_its_mtime_put_back_opens_no_remembered_route(
    ssh_home: Any,
    settled: None,  # noqa: F811
    opened: list[Any],  # noqa: F811
    tmp_path: Path,
) -> None:
    """The config's ctime moves with any write, and no one but root can set it back."""
    log = tmp_path / "proxy.log"
    extra_config(ssh_home, _via_proxy(log))
    opened.append(SSHTransport.connect("viaproxy", connect_timeout=10.0))
    assert len(_memories(_cache())) == 1
    before = ssh_home.config.stat()
    text = ssh_home.config.read_bytes()
    with open(ssh_home.config, "r+b") as fh:  # same inode, same size, another route
        fh.write(text.replace(b"Host viaproxy", b"Host viaproxz", 1))
    os.utime(ssh_home.config, ns=(before.st_atime_ns, before.st_mtime_ns))
    after = ssh_home.config.stat()
    assert (after.st_ino, after.st_size, after.st_mtime_ns) == (
        before.st_ino,
        before.st_size,
        before.st_mtime_ns,
    )
    assert early.start("viaproxy") is None
    assert _starts(log) == 1
