"""Channel data sealed in one copy (fetchsync/link/channels.py's Packetizer), against the
real sshd: what the robot reads is what was sent, whole and in order, across a rekey and
beside paramiko's own messages; sshd drops the connection at the first packet whose
AES-GCM tag, nonce or length is wrong ("Corrupted MAC on input")."""

from __future__ import annotations

import hashlib
import os
import threading

import pytest

from fetchsync.link.ssh import SSHTransport

pytestmark = pytest.mark.ssh


def sha256_on_robot(transport: SSHTransport, pieces: list[bytes]) -> str:
    """The robot's sha256sum of ``pieces`` sent one after the other."""
    chan = transport.exec("sha256sum")
    for piece in pieces:
        chan.send_all(memoryview(piece))
    chan.shutdown_write()
    out = b""
    while chunk := chan.recv(4096):
        out += chunk
    assert chan.exit_status(timeout=30) == 0
    chan.close()
    return out.split()[0].decode()


def packetizer(transport: SSHTransport):  # type: ignore[no-untyped-def]
    return transport._transport.packetizer


def test_channel_data_arrives_whole_through_the_one_copy_path(robot_transport):
    assert robot_transport._transport.local_cipher.endswith("-gcm@openssh.com")
    # odd sizes: every padding length, packets split at the window and the 32 KiB limit
    pieces = [os.urandom(n) for n in (1, 15, 16, 17, 4095, 32 * 1024 + 3, 3 * 2**20 + 7)]
    want = hashlib.sha256(b"".join(pieces)).hexdigest()
    assert sha256_on_robot(robot_transport, pieces) == want
    assert packetizer(robot_transport).fast_packets > 100
    # and the connection is alive for the next command (sshd kept it: no bad tag)
    assert sha256_on_robot(robot_transport, [b"again"]) == hashlib.sha256(b"again").hexdigest()


def test_a_rekey_in_the_middle_of_channel_data(robot_transport):
    pk = packetizer(robot_transport)
    pk.REKEY_BYTES = 2**20  # a rekey every MiB sent (paramiko's: 512 MiB)
    data = os.urandom(5 * 2**20)
    assert sha256_on_robot(robot_transport, [data]) == hashlib.sha256(data).hexdigest()
    # the outbound cipher was set afresh on the way (which zeroes the bytes counted)
    assert pk._Packetizer__sent_bytes < 2**20 + 64 * 1024
    assert robot_transport.is_alive(timeout=10)


def sent_from_threads(transport: SSHTransport, blobs: list[bytes]) -> None:
    """Each blob on a channel of its own, all at once: each arrives whole."""
    got: dict[int, str] = {}

    def one(i: int) -> None:
        got[i] = sha256_on_robot(transport, [blobs[i]])

    threads = [threading.Thread(target=one, args=(i,)) for i in range(len(blobs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert got == {i: hashlib.sha256(b).hexdigest() for i, b in enumerate(blobs)}


def test_channel_data_from_threads_at_once(robot_transport):
    """Several channels' senders at once: each packet's nonce is the next on the wire."""
    sent_from_threads(robot_transport, [os.urandom(2**20 + i) for i in range(4)])
