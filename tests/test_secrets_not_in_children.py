"""Secrets given to a call (FETCHSYNC_SUDO_PASSWORD, the account passwords) are in the
environment of none of the processes it starts: the ssh config's ProxyCommand (started
by the call itself, or early from the remembered route: link/early.py) and the ``local``
robot's endpoint were given the call's whole environment. (The connection master and
the resident: tests/test_secrets_not_inherited.py.) Over the real sshd."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from helpers import fetchsync, local_env, report, ssh_env
from test_secrets_not_inherited import SECRETS
from test_ssh import extra_config

pytestmark = pytest.mark.ssh


def leaked(dump: Path) -> list[str]:
    assert dump.exists(), "the process never ran"
    seen = dump.read_bytes()
    return [name for name, value in SECRETS.items() if value.encode() in seen]


def test_a_proxy_command_gets_no_password(ssh_home, remote_dir, tmp_path):
    dump = tmp_path / "proxy-environ"
    extra_config(
        ssh_home,
        "Host viaproxy\n    HostName {host}\n    Port {port}\n{common}"
        f"    ProxyCommand sh -c 'cat /proc/$$/environ >> {dump}; "
        "exec ssh -F {sshd_config} -o BatchMode=yes -W %h:%p robot'\n",
    )
    time.sleep(2.2)  # a config this old is one whose route is remembered (link/early.py)
    env = ssh_env(ssh_home.home, remote_dir, tmp_path, FETCHSYNC_ROBOT="viaproxy", **SECRETS)
    env["FETCHSYNC_PERSIST"] = "0"  # direct: the call starts the proxy itself
    assert report(fetchsync("push", "--json", env=env))["connection"] == "ssh"
    assert leaked(dump) == []
    dump.unlink()
    # the next call opens the remembered route before it parses the config
    (Path(env["FETCHSYNC_WORKSPACE"]) / "src/new.txt").write_text("again\n")
    env["FETCHSYNC_TRACE"] = str(tmp_path / "trace")
    assert report(fetchsync("push", "--json", env=env))["files"] == 1
    assert "early: route opened" in (tmp_path / "trace").read_text()
    assert leaked(dump) == []


def test_the_local_robots_endpoint_gets_no_password(tmp_path):
    dump = tmp_path / "endpoint-environ"
    env = local_env(
        tmp_path, FETCHSYNC_REMOTE_PYTHON=f"cat /proc/$$/environ > {dump}; python3", **SECRETS
    )
    assert report(fetchsync("push", "--json", env=env))["ok"]
    assert leaked(dump) == []
