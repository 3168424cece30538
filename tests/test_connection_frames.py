"""A request's frame goes out whole, whoever else sends on the connection meanwhile.

A push's round that raises (a batch refused by the robot, an error in the caller's
thread) ends with _Batcher.close(), which lets the sender thread finish the frame it is
sending rather than cut it (59d72bf). The watch agent keeps its connection after such
an error (a FetchsyncError that is not the link's) and its next push sends at once: two
threads then send on one connection. Frames cut into each other's pieces would make the
robot read a request's bytes as another's data. Connection.send sends a frame whole."""

from __future__ import annotations

import threading
from typing import Any

from fetchsync.link.connection import SEND_PIECE, Connection
from fetchsync.protocol import wire


class _Channel:
    """Records what is sent; after the first piece of the slow thread's frame, that
    thread waits (a slow link) until another thread sends, or a second has passed."""

    def __init__(self) -> None:
        self.out = bytearray()
        self.lock = threading.Lock()
        self.other_sent = threading.Event()
        self.slow_thread: int | None = None
        self.closed = threading.Event()

    def send_all(self, data: Any) -> None:
        me = threading.get_ident()
        with self.lock:
            self.out += bytes(data)
        if me == self.slow_thread:
            self.slow_thread = None
            self.other_sent.wait(1.0)
        else:
            self.other_sent.set()

    def recv(self, n: int) -> bytes:
        self.closed.wait()
        return b""

    def close(self) -> None:
        self.closed.set()


class _Transport:
    name = "robot"

    class capabilities:  # noqa: N801 - stands for the Transport attribute
        keepalive = False


def test_two_threads_sending_on_one_connection_never_cut_into_each_others_frames():
    channel = _Channel()
    conn = Connection(
        _Transport(),  # type: ignore[arg-type]
        channel,  # type: ignore[arg-type]
        wire.Reader(channel.recv),
        {},
        "blake2b",
        False,
    )
    big = bytes(range(256)) * (3 * SEND_PIECE // 256)  # three pieces: the batch on the link

    def abandoned_sender() -> None:
        channel.slow_thread = threading.get_ident()
        conn.send({"op": "sync", "n": 1}, blob_parts=[big])

    sender = threading.Thread(target=abandoned_sender)
    sender.start()
    while channel.slow_thread is not None:
        threading.Event().wait(0.01)  # its first piece is being sent
    nxt = threading.Thread(target=lambda: conn.send({"op": "list"}))  # the next push
    nxt.start()
    sender.join(10)
    nxt.join(10)
    frames = []
    reader = wire.Reader(_Replay(bytes(channel.out)).recv)
    while True:
        frame = reader.read_frame()
        if frame is None:
            break
        frames.append(frame)
    assert sorted(f.header["op"] for f in frames) == ["list", "sync"]
    assert [bytes(f.blob) for f in frames if f.header["op"] == "sync"] == [big]
    channel.close()


class _Replay:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def recv(self, n: int) -> bytes:
        out, self.data = self.data[:n], self.data[n:]
        return out
