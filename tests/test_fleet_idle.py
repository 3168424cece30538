"""The push's sender waits for the packer's next batch without waking up meanwhile (a
fleet's 20 senders polled every 3 ms: issue 27), and still sees how long the link sat
idle: from the last batch's answer (the connection's ``last_arrival``) to the next batch."""

from __future__ import annotations

import threading
import time
from typing import Any

from fetchsync.protocol import messages as M
from fetchsync.sync import engine as sync

TEXT = b"".join(b"line %d of a source file\n" % i for i in range(60000))


class _Pending:
    def __init__(self, answered: bool) -> None:
        self.asked = 0  # how often the sender looked
        self.is_answered = answered

    def answered(self) -> bool:
        self.asked += 1
        return self.is_answered


class _Endpoint:
    class conn:  # noqa: N801 - stands for the Connection attribute
        compress = True
        bytes_in = bytes_out = 0
        last_arrival = 0.0

    def __init__(self, *, answered: bool = True) -> None:
        self.pendings: list[_Pending] = []
        self.is_answered = answered

    def send_sync(self, ops: Any, **kw: Any) -> _Pending:
        pending = _Pending(self.is_answered)
        self.pendings.append(pending)
        return pending


def _batcher(endpoint: _Endpoint) -> sync._Batcher:
    endpoint.conn.last_arrival = 0.0
    return sync._Batcher(
        endpoint,  # type: ignore[arg-type]
        policy="preserve",
        epoch="e",
        gen=0,
        progress=None,
        total=0,
    )


def _send_one(batcher: sync._Batcher, path: str) -> None:
    op = M.Op(M.WRITE, path, expect=M.ABSENT, hash="00", size=len(TEXT), source=M.SRC_DATA)
    batcher._send(batcher._pack(0, [(op, TEXT, True)], [None]))


def _waiting(batcher: sync._Batcher) -> threading.Thread:
    waiter = threading.Thread(target=batcher._next_packed)
    waiter.start()
    while batcher._waiting is None:
        time.sleep(0.001)
    return waiter


def _end(batcher: sync._Batcher, waiter: threading.Thread) -> None:
    batcher._to_send.put(None)
    waiter.join(10)
    assert not waiter.is_alive()


def test_the_sender_does_not_wake_up_while_it_waits_and_counts_the_idle_time():
    endpoint = _Endpoint()
    batcher = _batcher(endpoint)
    _send_one(batcher, "a")
    t0 = time.monotonic()
    waiter = _waiting(batcher)
    time.sleep(0.3)
    _end(batcher, waiter)
    waited = time.monotonic() - t0
    # the 3 ms poll looked ~100 times in 0.3 s
    assert endpoint.pendings[-1].asked <= 2
    assert 0.25 <= batcher.idle <= waited


def test_the_idle_time_starts_when_the_last_answer_arrived():
    endpoint = _Endpoint()
    batcher = _batcher(endpoint)
    _send_one(batcher, "a")
    waiter = _waiting(batcher)
    arrival = time.monotonic() + 0.15  # the answer came 0.15 s into the wait
    endpoint.conn.last_arrival = arrival
    time.sleep(0.3)
    put = time.monotonic()
    _end(batcher, waiter)
    assert put - arrival - 0.01 <= batcher.idle <= time.monotonic() - arrival


def test_a_wait_with_the_last_batch_unanswered_is_not_idle():
    endpoint = _Endpoint(answered=False)
    batcher = _batcher(endpoint)
    _send_one(batcher, "a")
    waiter = _waiting(batcher)
    time.sleep(0.1)
    _end(batcher, waiter)
    assert batcher.idle == 0.0


def test_the_packer_sees_the_idle_time_of_a_wait_going_on():
    """The level rule is judged while the sender still waits (the packer decides the
    next batch's level as it starts packing it): that wait's idle time counts."""
    endpoint = _Endpoint()
    batcher = _batcher(endpoint)
    _send_one(batcher, "a")
    _send_one(batcher, "b")  # FAST_AFTER answers
    waiter = _waiting(batcher)
    # idle for well over FAST_IDLE of the time since the first batch, however long the
    # second one took to pack on a loaded machine
    time.sleep(max(0.2, 2 * (time.monotonic() - batcher._first_sent)))
    try:
        assert batcher.slow
        batcher._measure_link()  # the link sat idle all along since the first batch
        assert not batcher.slow
    finally:
        _end(batcher, waiter)
