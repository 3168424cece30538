"""Session channels on one SSH connection: how many are open at once, and their EOF.

Two ways paramiko (5.1) and OpenSSH's sshd lose commands that run side by side on one
connection (a debug snapshot's 8 collectors, a connection master's calls):

- **Sessions past the server's limit.** sshd refuses a session channel past its
  ``MaxSessions`` (10 by default), and a session stays counted there until both ends'
  CLOSE messages have crossed, so channels just closed still take room. paramiko
  raises ``ChannelException`` ("administratively prohibited", "open failed"), or, when
  two opens are refused at once, ``SSHException("Unable to open channel.")`` for the
  second (it keeps one refusal per connection). :class:`SessionSlots` opens at most
  ``limit`` session channels at once on a connection, counting those not yet
  confirmed closed by the robot; a refusal lowers the limit to what the robot took
  (for RELEARN seconds, or until an open past it succeeds), waits for one of ours to
  close (or backs off when none is open) and tries again a few times. A refusal is
  not a lost link: only a dead transport is.
- **An EOF after our CLOSE.** paramiko builds a channel's EOF under the channel's lock
  and sends it once that is released (paramiko#1115, #1705, open). When the robot's
  CLOSE arrives in between (a command that exits at once), paramiko's reader thread
  answers with our CLOSE first; the EOF follows for a channel sshd has freed, and sshd
  drops the whole connection ("ieof packet referred to nonexistent channel"), with
  every other command on it. :func:`send_eof` sends the EOF only while no CLOSE of
  ours can be on its way, in the order the robot must see them. Seen: 2 of 16 debug
  snapshots lost their link this way on this 2-CPU VM under load (sshd's log said so).
  Data has the same race (the sudo password written to a command that ended at once,
  a master forwarding a call's bytes to an endpoint that just exited):
  :func:`send_data`. A channel request is dropped for the same reason: the PTY's
  window-change (a terminal resized as a build step ends; sshd disconnects for any
  request to a freed channel, a window adjust it only logs): :func:`send_window_change`.

Channel data goes out in fewer copies (:class:`Packetizer`): paramiko copies each 32 KiB
packet's bytes six times on its way to the cipher (into a Message, out of it, into the
packet, its padding, a slice, the ciphertext joined to the length); a DATA message built
here is joined once and sealed by the same AES-GCM with the same nonce sequence, random
padding and rekey counts. Issue 27: the fleet push's sender threads (one per robot) spent
~120 us of laptop CPU per packet, ~134 packets per robot in the bench's initial push.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from typing import Any

import paramiko
from paramiko.common import cMSG_CHANNEL_DATA, cMSG_CHANNEL_EOF, cMSG_CHANNEL_REQUEST
from paramiko.message import Message
from paramiko.packet import Packetizer as _PacketizerBase
from paramiko.ssh_exception import ChannelException, SSHException

__all__ = [
    "MAX_SESSIONS",
    "Packetizer",
    "REFUSALS",
    "SessionSlots",
    "send_data",
    "send_eof",
    "send_exec",
    "send_window_change",
]

MAX_SESSIONS = 10  # sshd's default MaxSessions
REFUSALS = 6  # refused opens in a row before the refusal is the answer
BACKOFF = 0.05  # seconds after the first refusal while none of ours is open; doubles
_POLL = 0.02  # how often a wait looks for one of ours confirmed closed
WAIT = 10.0  # seconds an open waits for a slot when the caller gives no timeout
RELEARN = 30.0  # seconds after the last refusal that a lowered limit is forgotten


def refused(exc: BaseException, transport: paramiko.Transport) -> bool:
    """Whether ``exc`` from ``open_session`` is the robot refusing the channel (the
    connection lives on), not a lost link."""
    if not transport.is_active():
        return False
    return isinstance(exc, ChannelException) or (
        isinstance(exc, SSHException) and "Unable to open channel" in str(exc)
    )


class SessionSlots:
    """The session channels open on one paramiko connection, bounded (see the module)."""

    def __init__(self, transport: paramiko.Transport, *, limit: int = MAX_SESSIONS) -> None:
        self._transport = transport
        self.ceiling = self.limit = limit
        self._refused_at = 0.0  # when the robot last refused a session
        self._held: list[paramiko.Channel] = []
        self._opening = 0
        self._cond = threading.Condition()

    def open(self, *, timeout: float | None) -> paramiko.Channel:
        """A new session channel; raises what ``open_session`` raises, a refusal only
        after REFUSALS of them in a row."""
        refusals = 0
        while True:
            with self._cond:
                # our channels end as their commands do; one held for hours (a watch
                # agent's endpoint) must not hold the others forever: past the wait,
                # the robot's answer decides
                now = time.monotonic()
                if self.limit < self.ceiling and now - self._refused_at > RELEARN:
                    # what the robot refused then (sessions of ours it had not yet
                    # freed, commands still running): maybe not any more
                    self.limit = self.ceiling
                give_up = now + (timeout if timeout is not None else WAIT)
                while self._count() >= self.limit and time.monotonic() < give_up:
                    self._cond.wait(_POLL)
                self._opening += 1
            try:
                chan = self._transport.open_session(timeout=timeout)
            except (SSHException, EOFError, OSError) as exc:
                with self._cond:
                    self._opening -= 1
                    ours = self._count()
                    if not refused(exc, self._transport) or refusals + 1 >= REFUSALS:
                        raise
                    refusals += 1
                    self._refused_at = time.monotonic()
                    if ours:
                        # the robot holds at most this many of ours: the next open waits
                        # for one of them to close
                        self.limit = max(1, min(self.limit, ours))
                if not ours:
                    time.sleep(BACKOFF * 2 ** (refusals - 1))
                continue
            with self._cond:
                self._opening -= 1
                self._held.append(chan)
                # opened past the limit (the wait ran out): the robot takes that many
                self.limit = min(self.ceiling, max(self.limit, len(self._held)))
            return chan

    def _count(self) -> int:
        """Channels open or opening, and closed but not yet confirmed by the robot (under
        the condition's lock)."""
        if not self._transport.is_active():
            self._held.clear()
        else:
            live: Any = self._transport._channels  # paramiko's ChannelMap, until the robot's CLOSE
            self._held = [c for c in self._held if live.get(c.get_id()) is c]
        return len(self._held) + self._opening


def send_eof(chan: paramiko.Channel) -> None:
    """``chan.shutdown_write()`` without paramiko's race: the EOF goes out before our
    CLOSE, or not at all once a CLOSE of ours is on its way (see the module)."""
    transport: Any = chan.transport
    if not _ours(transport):
        chan.shutdown_write()  # another paramiko: its own way
        return
    with chan.lock:
        if chan.eof_sent or chan.closed or not chan.active:
            return
        chan.eof_sent = True  # a close from now on sends its CLOSE alone
        m = Message()
        m.add_byte(cMSG_CHANNEL_EOF)
        m.add_int(chan.remote_chanid)
    _send_while_open(transport, chan, m)


def send_data(chan: paramiko.Channel, data: bytes | memoryview) -> int:
    """``chan.send(data)`` without paramiko's race: the data goes out before our CLOSE,
    or not at all once a CLOSE of ours is on its way (the command has ended: sshd would
    have dropped it, and the connection with it). Returns how much of ``data`` was taken:
    with our :class:`Packetizer`, up to RUN packets' worth as far as the channel's
    window allows (sealed and written in one go: :class:`_DataRun`), else one packet's."""
    transport: Any = chan.transport
    if not _ours(transport) or not hasattr(chan, "_wait_for_send_window"):
        return int(chan.send(data))
    with chan.lock:  # as paramiko's Channel._send
        if chan.closed:
            raise OSError("Socket is closed")
        size = int(chan._wait_for_send_window(len(data)))
        if size == 0:
            return 0
        m: Any = _Data(cMSG_CHANNEL_DATA + _HEAD.pack(chan.remote_chanid, size), data[:size])
        taken = size
        if taken < len(data) and type(transport.packetizer) is Packetizer:
            run = [m]
            # more packets only while the window has room: never waits with one in hand
            while taken < len(data) and len(run) < RUN and chan.out_window_size > 0:
                size = int(chan._wait_for_send_window(len(data) - taken))
                if size == 0:
                    break
                head = cMSG_CHANNEL_DATA + _HEAD.pack(chan.remote_chanid, size)
                run.append(_Data(head, data[taken : taken + size]))
                taken += size
            if len(run) > 1:
                m = _DataRun(run)
    _send_while_open(transport, chan, m)
    return taken


RUN = 8  # channel DATA packets sealed and written in one go at most (8 x 32 KiB)
_HEAD = struct.Struct(">II")  # a DATA message's channel and its string's length
_LENGTH = struct.Struct(">I")


class _Data:
    """A channel DATA message: its header and its bytes, not joined yet (:class:`Packetizer`
    joins them once, into the packet); ``asbytes`` for any other packetizer."""

    __slots__ = ("body", "header")

    def __init__(self, header: bytes, body: bytes | memoryview) -> None:
        self.header = header
        self.body = body

    def asbytes(self) -> bytes:
        return self.header + bytes(self.body)


class _DataRun:
    """Channel DATA messages that go out one after the other, sealed and written by
    :class:`Packetizer` in one go (one window taken, one lock, one random read for
    their padding), each packet written as it is sealed: joined into one write, the
    run's 256 KiB left the CPU's cache and cost more than packets one by one.
    bench/channelab.py (16 MiB to sshd on loopback, 8 interleaved, load 27): the
    sending thread's CPU 2.69 -> 1.96 ms/MiB (84 -> 61 us per 32 KiB packet); joined:
    2.40 -> 3.05. Issue 27: a fleet push's sender threads (one per robot)."""

    __slots__ = ("parts",)

    def __init__(self, parts: list[_Data]) -> None:
        self.parts = parts


class Packetizer(_PacketizerBase):  # type: ignore[misc]  # paramiko ships no types
    """paramiko's Packetizer, sealing channel data (:class:`_Data`) under AES-GCM in one
    copy: the packet is built once and encrypted as paramiko does it (RFC 5647: the
    length as associated data, the 12-byte nonce's counter moved on per packet, random
    padding to the 16-byte block), under the same write lock, counting the same bytes
    and packets towards a rekey. Anything else (other messages, other ciphers,
    compression, packet dumps) goes paramiko's way."""

    fast_packets = 0  # sent this way (tests)
    runs = 0  # runs of more than one packet (tests)

    def send_message(self, data: Any) -> None:
        kind = type(data)
        if kind is not _Data and kind is not _DataRun:
            return super().send_message(data)  # type: ignore[no-any-return]
        parts: list[_Data] | tuple[_Data] = data.parts if kind is _DataRun else (data,)
        me: Any = self  # paramiko's private state, by its mangled names
        with me._Packetizer__write_lock:  # the nonce sequence is the wire's order
            engine = me._Packetizer__block_engine_out
            if (
                engine is None
                or not me._Packetizer__aead_out
                or me._Packetizer__compress_engine_out is not None
                or me._Packetizer__dump_packets
            ):
                for part in parts:
                    super().send_message(part)
                return None
            bsize = me._Packetizer__block_size_out
            # as paramiko's _build_packet (AEAD): padding to the block, at least 4
            sizes = [len(part.header) + len(part.body) for part in parts]
            paddings = [3 + bsize - ((n + 4) % bsize) for n in sizes]
            noise = os.urandom(sum(paddings))
            iv = me._Packetizer__iv_out
            seq = me._Packetizer__sequence_number_out
            sent = at_noise = 0
            for part, n, padding in zip(parts, sizes, paddings):
                header, body = part.header, part.body
                plain = bytearray(1 + n + padding)
                plain[0] = padding
                at = 1 + len(header)
                plain[1:at] = header
                plain[at : at + len(body)] = body
                plain[at + len(body) :] = noise[at_noise : at_noise + padding]
                at_noise += padding
                length = _LENGTH.pack(len(plain))
                out = length + engine.encrypt(iv, plain, length)
                iv = self._inc_iv_counter(iv)
                seq = (seq + 1) & 0xFFFFFFFF
                if seq == 0 and not self._initial_kex_done:
                    raise SSHException("Sequence number rolled over during initial kex!")
                me._Packetizer__iv_out = iv
                me._Packetizer__sequence_number_out = seq
                self.write_all(out)  # each as it is sealed: 32 KiB stays in the cache
                sent += len(out)
            me._Packetizer__sent_bytes += sent
            me._Packetizer__sent_packets += len(parts)
            self.fast_packets += len(parts)
            self.runs += len(parts) > 1
            if (
                me._Packetizer__sent_packets >= self.REKEY_PACKETS
                or me._Packetizer__sent_bytes >= self.REKEY_BYTES
            ) and not me._Packetizer__need_rekey:
                me._Packetizer__received_bytes_overflow = 0
                me._Packetizer__received_packets_overflow = 0
                self._trigger_rekey()
        return None


def send_exec(chan: paramiko.Channel, command: str) -> None:
    """Start ``command`` on a new session channel without waiting for the robot's reply.

    paramiko's ``exec_command`` waits for the reply (a round trip and sshd's fork of the
    session's command: 10-13 ms on the bench's wifi) before the caller goes on, though
    the command starts when the request arrives, whatever the reply. The reply is still
    asked for and read by paramiko: a refusal closes the channel, and the caller reading
    it sees its end (as a command that did not start). Only for a fresh channel: no CLOSE
    of ours can be on its way yet. Measured (bench/firststart.py --link wifi --rclcpp
    --rounds 6 against the commit before, interleaved, load 5.8-6.6): the endpoint's
    hello to the push connected (its local work meanwhile done) 3.5 ms against 16.2
    (medians)."""
    m = Message()
    m.add_byte(cMSG_CHANNEL_REQUEST)
    m.add_int(chan.remote_chanid)
    m.add_string("exec")
    m.add_boolean(True)
    m.add_string(command)
    chan._event_pending()
    chan.transport._send_user_message(m)


def send_window_change(chan: paramiko.Channel, *, width: int, height: int) -> None:
    """``chan.resize_pty(width, height)`` without paramiko's race: the request goes out
    before our CLOSE, or not at all (the command has ended; see the module)."""
    transport: Any = chan.transport
    if not _ours(transport):
        chan.resize_pty(width=width, height=height)
        return
    with chan.lock:
        if chan.closed or not chan.active:
            return
        m = Message()
        m.add_byte(cMSG_CHANNEL_REQUEST)
        m.add_int(chan.remote_chanid)
        m.add_string("window-change")
        m.add_boolean(False)
        for n in (width, height, 0, 0):
            m.add_int(n)
    _send_while_open(transport, chan, m)


def _ours(transport: Any) -> bool:
    """Whether ``transport`` has the paramiko internals :func:`_send_while_open` uses."""
    return transport is not None and all(
        hasattr(transport, a)
        for a in ("clear_to_send", "clear_to_send_lock", "clear_to_send_timeout", "_send_message")
    )


def _send_while_open(transport: Any, chan: paramiko.Channel, m: Message) -> None:
    """Send ``m`` unless ``chan`` is closed by the time it can go: as paramiko's
    _send_user_message (not during a key exchange), with the check under the same lock
    our CLOSE is sent under, after its channel was marked closed."""
    start = time.monotonic()
    while True:
        transport.clear_to_send.wait(0.1)
        if not transport.active:
            return
        with transport.clear_to_send_lock:
            if transport.clear_to_send.is_set():
                if not chan.closed:
                    transport._send_message(m)
                return
        if time.monotonic() > start + transport.clear_to_send_timeout:
            raise SSHException("Key-exchange timed out waiting for key negotiation")
