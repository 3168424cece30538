"""Shared fixtures: the real-sshd robot and a laptop-side HOME that points at it.

- ``sshd`` (session): a running OpenSSH server on 127.0.0.1, see ``sshd.SSHD``.
- ``ssh_home`` (function): a fresh HOME whose ``~/.ssh`` reaches the robot as
  ``robot``; ``HOME`` is set to it and ``SSH_AUTH_SOCK`` unset.
- ``clean_process_env`` (function): none of the developer's fetchsync or ROS settings in
  ``os.environ``; ``helpers.clean_env``, ``local_env`` and ``ssh_env`` build a CLI
  subprocess's environment the same way.
- ``remote_dir`` (function): an empty absolute directory to use as the remote
  workspace on the robot (the robot is this machine).
- ``fault_proxy`` (function): a started ``faultproxy.FaultProxy`` in front of
  the robot; ``proxied_home`` is ``ssh_home`` with ``robot`` going through it.
  Use either ``ssh_home`` or ``proxied_home`` in a test: both set ``HOME``.

Tests that use them are marked ``@pytest.mark.ssh`` by convention.
"""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path
from typing import Iterator

import pytest

# Helper modules beside this file (sshd, faultproxy) import as top-level
# modules whatever pytest's import mode.
_TESTS_DIR = str(Path(__file__).resolve().parent)
if _TESTS_DIR not in sys.path:
    sys.path.insert(0, _TESTS_DIR)

from faultproxy import FaultProxy
from helpers import clean_env
from sshd import SSHD, SSHDStartError, SSHHome, find_sshd, make_ssh_home, running_sshd


@pytest.fixture(scope="session")
def sshd(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SSHD]:
    """The robot: a real sshd on 127.0.0.1 for the whole session."""
    if find_sshd() is None and not os.environ.get("CI"):
        # On CI a missing sshd is an install bug and must fail, not skip.
        pytest.skip("sshd not installed (apt-get install openssh-server)")
    try:
        with running_sshd(tmp_path_factory.mktemp("sshd")) as server:
            yield server
    except SSHDStartError as exc:
        pytest.fail(str(exc), pytrace=False)


def _use_home(home: SSHHome, monkeypatch: pytest.MonkeyPatch) -> SSHHome:
    monkeypatch.setenv("HOME", str(home.home))
    # A developer's agent would offer their own keys to the robot.
    monkeypatch.delenv("SSH_AUTH_SOCK", raising=False)
    return home


@pytest.fixture
def ssh_home(sshd: SSHD, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> SSHHome:
    """A fresh HOME for the laptop side, reaching the robot as ``robot``."""
    return _use_home(make_ssh_home(tmp_path / "home", sshd=sshd), monkeypatch)


@pytest.fixture
def robot_transport(ssh_home: SSHHome) -> Iterator[object]:
    """An SSH connection to the tests' robot (fetchsync.link.ssh.SSHTransport), closed after."""
    from fetchsync.link.ssh import SSHTransport

    transport = SSHTransport.connect("robot", connect_timeout=10.0)
    try:
        yield transport
    finally:
        transport.close()


@pytest.fixture
def fault_proxy(sshd: SSHD) -> Iterator[FaultProxy]:
    """A link to the robot that a test can blackhole, cut or throttle."""
    with FaultProxy(sshd.host, sshd.port) as proxy:
        yield proxy


@pytest.fixture
def proxied_home(
    sshd: SSHD, fault_proxy: FaultProxy, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> SSHHome:
    """Like ``ssh_home``, but ``robot`` is reached through ``fault_proxy``."""
    home = make_ssh_home(tmp_path / "home-proxied", sshd=sshd, port=fault_proxy.port)
    return _use_home(home, monkeypatch)


@pytest.fixture(scope="session")
def _laptop_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("laptop-cache")


@pytest.fixture(autouse=True)
def _sigint_not_ignored() -> Iterator[None]:
    """A suite started as a background job of a non-interactive shell (`bash .ci/run &`,
    nohup) starts with SIGINT ignored; the fetchsync processes the tests start inherit
    that and Python keeps it ignored, so every Ctrl-C test (a push, the resident's push,
    run, the fleet) would fail on how the suite was launched. Children start with the
    default disposition when this process handles SIGINT itself."""
    saved = signal.getsignal(signal.SIGINT)
    if saved == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, saved)


@pytest.fixture(autouse=True)
def _no_lingering_masters(
    tmp_path_factory: pytest.TempPathFactory, _laptop_cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Tests open fresh SSH connections unless they ask for a connection master, and keep
    the laptop's cache (the robots' interpreters, the connections noted) in one directory
    of the session: not in the user's ~/.cache, where each test's own local robot left a
    note that stayed (1,300 of them after a few runs)."""
    monkeypatch.setenv("FETCHSYNC_PERSIST", "0")
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path_factory.mktemp("run")))
    monkeypatch.setenv("XDG_CACHE_HOME", str(_laptop_cache))


@pytest.fixture
def clean_process_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """This process's environment as ``helpers.clean_env()`` leaves a CLI run's (none of the
    developer's fetchsync, fetch_tools or ROS settings), for tests that run the CLI in-process."""
    kept = clean_env()
    for var in [k for k in os.environ if k not in kept]:
        monkeypatch.delenv(var)


@pytest.fixture
def remote_dir(tmp_path: Path) -> Path:
    """An empty directory on the robot to use as the remote workspace."""
    path = (tmp_path / "robot-ws").resolve()
    path.mkdir()
    return path


def pytest_configure(config: pytest.Config) -> None:
    """Parallel workers (``-n 4``) are handed the tests one at a time (``--maxschedchunk 1``)
    unless told otherwise: pytest-xdist's default hands each worker a quarter of its share
    of the collection at once, in order, so one worker got every slow test and the suite
    waited for it alone."""
    if getattr(config.option, "maxschedchunk", 0) is None:
        config.option.maxschedchunk = 1


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The tests marked ``slow`` first (in their order, then the rest in theirs): handed out
    one at a time, the parallel workers take the long ones early and end together, instead
    of one worker starting a 50-second test when the others are done."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
