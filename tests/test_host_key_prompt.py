"""First contact on a terminal: the unknown host key is shown and asked about, as OpenSSH
asks (issue 25 item 11); without a terminal the one-line refusal stays (test_push_ssh)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from helpers import ssh_env, tree_of
from terminal import Terminal

pytestmark = pytest.mark.ssh

QUESTION = b"(yes/no/[fingerprint])? "


@pytest.mark.parametrize("answer", ["yes", "fingerprint"])
def test_an_accepted_unknown_key_is_recorded_and_the_push_goes_on(
    answer, ssh_home, remote_dir, tmp_path
):
    ssh_home.known_hosts.write_text("")
    env = ssh_env(ssh_home.home, remote_dir, tmp_path, PYTHONPATH=os.environ.get("PYTHONPATH", ""))
    term = Terminal(["push"], env)
    try:
        out = term.read_until(QUESTION)
        fingerprint = ssh_home.sshd.host_key_fingerprint
        assert b"The authenticity of host 'robot" in out and fingerprint.encode() in out
        term.send((("yes" if answer == "yes" else fingerprint) + "\n").encode())
        assert term.wait(60) == 0, term.output.decode()
    finally:
        term.close()
    assert ssh_home.sshd.host_key_pub.split()[1] in ssh_home.known_hosts.read_text()
    assert tree_of(Path(env["FETCHSYNC_WORKSPACE"]) / "src") == tree_of(remote_dir / "src")


def test_a_refused_unknown_key_is_one_line_and_not_recorded(ssh_home, remote_dir, tmp_path):
    ssh_home.known_hosts.write_text("")
    env = ssh_env(ssh_home.home, remote_dir, tmp_path, PYTHONPATH=os.environ.get("PYTHONPATH", ""))
    term = Terminal(["push"], env)
    try:
        term.read_until(QUESTION)
        term.send(b"maybe\n")
        term.read_until(b"Please type 'yes', 'no' or the fingerprint: ")
        term.send(b"no\n")
        assert term.wait(60) == 3
        text = term.output.decode()
        assert "host key verification failed" in text and "Traceback" not in text
    finally:
        term.close()
    assert ssh_home.known_hosts.read_text() == ""
    assert not (remote_dir / "src").exists()
