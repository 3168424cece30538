"""Channel data in runs (fetchsync/link/channels.py: up to RUN packets sealed and written
in one go, as far as the channel's window allows), against the real sshd: what the
robot reads is what was sent, whole and in order, with the window filling up, across a
rekey, from several threads, and through paramiko's own packets when the fast path is
off; sshd drops the connection at the first packet whose AES-GCM tag, nonce or length
is wrong."""

from __future__ import annotations

import hashlib
import os

import pytest
from test_channel_packets import packetizer, sent_from_threads, sha256_on_robot

from fetchsync.link.ssh import SSHTransport

pytestmark = pytest.mark.ssh


def sha256_after(transport: SSHTransport, seconds: float, data: bytes) -> str:
    """The robot's sha256sum of ``data``, read only after ``seconds``: the window fills."""
    chan = transport.exec(f"sleep {seconds}; sha256sum")
    chan.send_all(memoryview(data))
    chan.shutdown_write()
    out = b""
    while chunk := chan.recv(4096):
        out += chunk
    assert chan.exit_status(timeout=30) == 0
    chan.close()
    return out.split()[0].decode()


def test_channel_data_goes_in_runs_and_arrives_whole(robot_transport):
    pk = packetizer(robot_transport)
    packets, runs = pk.fast_packets, pk.runs
    data = os.urandom(3 * 2**20 + 5)
    assert sha256_on_robot(robot_transport, [data]) == hashlib.sha256(data).hexdigest()
    assert pk.runs - runs >= 3  # the pieces of 256 KiB went as runs
    assert pk.fast_packets - packets >= len(data) // (32 * 1024)  # each packet counted
    assert robot_transport.is_alive(timeout=10)


def test_runs_stop_at_the_window_and_go_on_when_it_opens(robot_transport):
    """sshd reads nothing for a second: the 2 MiB window fills in the middle of a run."""
    data = os.urandom(6 * 2**20 + 11)
    assert sha256_after(robot_transport, 1, data) == hashlib.sha256(data).hexdigest()
    assert robot_transport.is_alive(timeout=10)


def test_a_rekey_in_the_middle_of_runs(robot_transport):
    pk = packetizer(robot_transport)
    pk.REKEY_BYTES = 100 * 1024  # a rekey every ~3 packets: within a run
    data = os.urandom(3 * 2**20)
    assert sha256_on_robot(robot_transport, [data]) == hashlib.sha256(data).hexdigest()
    assert robot_transport.is_alive(timeout=10)


def test_runs_from_threads_at_once(robot_transport):
    sent_from_threads(robot_transport, [os.urandom(2**20 + 7 * i) for i in range(4)])


def test_a_run_goes_through_paramikos_packets_when_the_fast_path_is_off(robot_transport):
    pk = packetizer(robot_transport)
    pk._Packetizer__dump_packets = True  # paramiko's packet dump: its own way, packet by packet
    try:
        packets = pk.fast_packets
        data = os.urandom(2**20 + 3)
        assert sha256_on_robot(robot_transport, [data]) == hashlib.sha256(data).hexdigest()
        assert pk.fast_packets == packets
    finally:
        pk._Packetizer__dump_packets = False
    assert robot_transport.is_alive(timeout=10)
