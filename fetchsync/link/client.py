"""The typed client of the robot-side endpoint (:class:`fetchsync.protocol.server.Server`).

:class:`Endpoint` has one method per request the endpoint serves (its ``do_*``
handlers): ``open``, ``list`` (:meth:`Endpoint.listing`), ``sync``, ``read``, ``sigs``,
``adopt``, ``kept`` and ``ping``; ``bye`` is the connection's own
(:meth:`Connection.close`). A request is a
:class:`typing.TypedDict` (what goes on the wire, checked by mypy); an answer is a
frozen dataclass, checked as it arrives: a robot whose answer is malformed (a field
missing or of the wrong type, a blob reference out of range, a count that does not
match the request) is a :class:`~fetchsync.errors.ProtocolError`, one line at the CLI,
never a ``KeyError`` deep in the engine.

Requests pipeline: each ``send_*`` method returns a :class:`Pending` answer at once,
and the plain method waits for it. The robot side stays dict-based (Python 3.6,
standard library): this module is the laptop's only speaker of the protocol.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Generic, Literal, TypedDict, TypeVar

from fetchsync.errors import ProtocolError
from fetchsync.link.connection import Connection
from fetchsync.protocol import messages as M
from fetchsync.protocol import paths, wire
from fetchsync.protocol.ignore import IgnoreRules

T = TypeVar("T")

# ------------------------------------------------------------------------------ requests


class OpenRequest(TypedDict, total=False):
    op: Literal["open"]
    workspace: str
    rules: Any  # IgnoreRules.to_wire()
    create: bool
    readonly: bool


class ListRequest(TypedDict, total=False):
    op: Literal["list"]
    mode: Literal["full", "drift"]
    epoch: str
    gen: int


class SyncRequest(TypedDict, total=False):
    op: Literal["sync"]
    ops: list[dict[str, Any]]  # M.Op.to_wire()
    policy: str
    epoch: str
    gen: int
    require_fresh: bool
    zpart: list[int]  # [compressed length, inflated length] of the blob's zlib part


class ReadItem(TypedDict, total=False):
    p: str
    off: int
    len: int


class ReadRequest(TypedDict):
    op: Literal["read"]
    items: list[ReadItem]


class SigsRequest(TypedDict):
    op: Literal["sigs"]
    items: list[ReadItem]


class AdoptRequest(TypedDict):
    op: Literal["adopt"]
    entries: list[list[Any]]  # M.Listed.to_wire()


class KeptRequest(TypedDict, total=False):
    op: Literal["kept"]
    where: str
    at: str
    p: str
    off: int
    len: int


class PingRequest(TypedDict):
    op: Literal["ping"]


#: The requests this client makes, as the endpoint names them (``Server.do_<name>``).
REQUESTS = ("open", "list", "sync", "read", "sigs", "adopt", "kept", "ping", "bye")

# ------------------------------------------------------------------------------ answers


def _malformed(op: str, what: str) -> ProtocolError:
    return ProtocolError(f"the robot's answer to {op!r} is malformed: {what}")


def _str(op: str, header: dict[str, Any], key: str) -> str:
    value = header.get(key)
    if type(value) is not str:  # noqa: E721 - a str subclass is no wire value
        raise _malformed(op, f"{key!r} is not a string")
    return value


def _int(op: str, header: dict[str, Any], key: str) -> int:
    value = header.get(key)
    if type(value) is not int:  # noqa: E721 - bool is no wire int
        raise _malformed(op, f"{key!r} is not an integer")
    return value


def _list(op: str, header: dict[str, Any], key: str, *, default: bool = False) -> list[Any]:
    value = header.get(key, [] if default else None)
    if not isinstance(value, list):
        raise _malformed(op, f"{key!r} is not a list")
    return value


def _items(op: str, frame: wire.Frame, asked: int) -> list[tuple[dict[str, Any], bytes]]:
    """A per-item answer (read, sigs): each item with its slice of the blob, or ``c`` not OK."""
    items = _list(op, frame.header, "items")
    if len(items) != asked:
        raise _malformed(op, f"{len(items)} answers to {asked} items")
    out: list[tuple[dict[str, Any], bytes]] = []
    for ans in items:
        if not isinstance(ans, dict) or not isinstance(ans.get("c"), str):
            raise _malformed(op, "an item is not an answer")
        data = b""
        if ans["c"] == M.OK:
            ref = ans.get("bl")
            if not (
                isinstance(ref, list)
                and len(ref) == 2
                and all(type(x) is int and x >= 0 for x in ref)  # noqa: E721
                and ref[0] + ref[1] <= len(frame.blob)
            ):
                raise _malformed(op, "a blob reference is out of range")
            data = frame.blob[ref[0] : ref[0] + ref[1]]
        out.append((ans, data))
    return out


def _failed(ans: dict[str, Any]) -> Failed | None:
    if ans["c"] == M.OK:
        return None
    return Failed(ans["c"], str(ans.get("msg", "")) or "cannot read")


@dataclass(frozen=True, slots=True)
class Failed:
    """An item the robot could not serve (a file gone, unreadable): data, not an error."""

    code: str
    message: str


@dataclass(frozen=True, slots=True)
class Opened:
    """The workspace the endpoint opened: its absolute path and the index's generation."""

    workspace: str
    epoch: str
    gen: int
    readonly: bool = False

    @classmethod
    def from_frame(cls, frame: wire.Frame) -> Opened:
        h = frame.header
        return cls(
            _str("open", h, "workspace"),
            _str("open", h, "epoch"),
            _int("open", h, "gen"),
            h.get("readonly") is True,
        )


@dataclass(frozen=True, slots=True)
class Listing:
    """What the robot holds: the whole tree (``full``), or what changed there since the
    generation asked about (``entries`` changed, ``gone`` removed)."""

    epoch: str
    gen: int
    full: bool = True
    entries: list[M.Listed] = field(default_factory=list)
    gone: list[str] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)

    @property
    def drifted(self) -> bool:
        """Whether the robot's tree may differ from the generation asked about."""
        return self.full or bool(self.entries) or bool(self.gone)

    def tree(self, last_synced: Callable[[], dict[str, M.Listed]]) -> dict[str, M.Listed]:
        """What the robot holds: this listing if full, else ``last_synced()`` (what the
        robot held at the generation asked about) with the changes applied."""
        if self.full:
            return {e.path: e for e in self.entries}
        remote = last_synced()
        for item in self.entries:
            remote[item.path] = item
        for path in self.gone:
            remote.pop(path, None)
        return remote

    @classmethod
    def from_frame(cls, frame: wire.Frame) -> Listing:
        h = frame.header
        gone = [paths.validate(p) for p in _list("list", h, "gone", default=True)]
        skipped = []
        for pair in _list("list", h, "skipped", default=True):
            if not (
                isinstance(pair, list) and len(pair) == 2 and all(type(x) is str for x in pair)
            ):  # noqa: E721
                raise _malformed("list", "a skipped path is not [path, reason]")
            skipped.append((pair[0], pair[1]))
        return cls(
            _str("list", h, "epoch"),
            _int("list", h, "gen"),
            h.get("full") is True,
            [M.Listed.from_wire(x) for x in _list("list", h, "entries", default=True)],
            gone,
            skipped,
        )


@dataclass(frozen=True, slots=True)
class Applied:
    """The answer to a sync request: one result per operation sent, in order; or
    ``stale`` (someone else wrote to the robot since ``gen``: nothing was applied)."""

    stale: bool
    epoch: str
    gen: int
    results: list[M.Result] = field(default_factory=list)

    @classmethod
    def from_frame(cls, frame: wire.Frame, ops: list[M.Op]) -> Applied:
        h = frame.header
        epoch, gen = _str("sync", h, "epoch"), _int("sync", h, "gen")
        if h.get("stale") is True:
            return cls(True, epoch, gen)
        results = _list("sync", h, "results")
        if len(results) != len(ops):
            raise _malformed("sync", f"{len(results)} results for {len(ops)} operations")
        return cls(False, epoch, gen, [M.Result.from_wire(r, op) for r, op in zip(results, ops)])


@dataclass(frozen=True, slots=True)
class Content:
    """A file's content as the robot read it (all of it, or the piece asked for), and
    the file as it stood then."""

    listed: M.Listed
    data: bytes


@dataclass(frozen=True, slots=True)
class Signed:
    """The delta signature of a robot's file, and the content hash it was made of."""

    hash: str
    signature: bytes


@dataclass(frozen=True, slots=True)
class Adopted:
    """How many identical entries the robot's index took in, and its new generation."""

    adopted: int
    epoch: str
    gen: int


@dataclass(frozen=True, slots=True)
class KeptList:
    """The files kept in ``.fetchsync/<where>``: raw ``[time, path, size]`` entries
    (checked by their reader, :mod:`fetchsync.cli.conflicts`), and whether some were
    left out."""

    entries: list[Any]
    more: bool


@dataclass(frozen=True, slots=True)
class KeptPiece:
    """A piece of a kept file, and the whole file's size."""

    size: int
    data: bytes


class Pending(Generic[T]):
    """An answer on its way: :meth:`wait` returns it typed (or raises)."""

    __slots__ = ("_conn", "_parse", "req_id", "_taken")

    def __init__(self, conn: Connection, req_id: int, parse: Callable[[wire.Frame], T]) -> None:
        self._conn = conn
        self._parse = parse
        self.req_id = req_id
        self._taken = False  # wait() has had its answer (the connection let go of it)

    def answered(self) -> bool:
        """Whether the answer came: :meth:`wait` would return (or raise) at once, or did."""
        return self._taken or self._conn.answered(self.req_id)

    def wait(self) -> T:
        frame = self._conn.wait(self.req_id)
        self._taken = True
        return self._parse(frame)


# ------------------------------------------------------------------------------ the client


class Endpoint:
    """The robot-side endpoint of one :class:`Connection`, one method per request."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn

    @property
    def algorithm(self) -> str:
        """The content hash both ends agreed on."""
        return self.conn.algorithm

    @property
    def zdict(self) -> bool:
        """Whether the endpoint takes writes of source ``zdict`` (its hello says so)."""
        return bool(self.conn.hello.get("zdict"))

    @property
    def stl(self) -> bool:
        """Whether the endpoint takes writes of source ``stl`` (its hello says so)."""
        return bool(self.conn.hello.get("stl"))

    def _send(self, request: Any, parse: Callable[[wire.Frame], T], **kw: Any) -> Pending[T]:
        return Pending(self.conn, self.conn.send(dict(request), **kw), parse)

    # -- open
    def send_open(
        self,
        workspace: str,
        *,
        rules: IgnoreRules | None = None,
        create: bool = True,
        readonly: bool = False,
    ) -> Pending[Opened]:
        """Open ``workspace`` (``~/ws`` or absolute) on the robot; ``readonly``: create,
        lock and write nothing there (a dry run, a pull, a status read), and refuse
        every change. A workspace that does not exist (and ``create`` is False) is a
        :class:`~fetchsync.errors.RemoteError`."""
        request = OpenRequest(op="open", workspace=workspace, create=create, readonly=readonly)
        if rules is not None:
            request["rules"] = rules.to_wire()
        return self._send(request, Opened.from_frame)

    def open(
        self,
        workspace: str,
        *,
        rules: IgnoreRules | None = None,
        create: bool = True,
        readonly: bool = False,
    ) -> Opened:
        return self.send_open(workspace, rules=rules, create=create, readonly=readonly).wait()

    # -- list
    def send_listing(self, *, since: tuple[str, int] | None = None) -> Pending[Listing]:
        """The robot's tree; with ``since`` (epoch, generation), only what changed there
        since, if its index can say (else the whole tree: ``Listing.full``)."""
        request = (
            ListRequest(op="list", mode="full")
            if since is None
            else ListRequest(op="list", mode="drift", epoch=since[0], gen=since[1])
        )
        return self._send(request, Listing.from_frame)

    def listing(self, *, since: tuple[str, int] | None = None) -> Listing:
        return self.send_listing(since=since).wait()

    # -- sync
    def send_sync(
        self,
        ops: list[M.Op],
        *,
        policy: str,
        epoch: str,
        gen: int,
        zpart: tuple[int, int] | None = None,
        blob_parts: list[bytes] | None = None,
        sent: Callable[[int, int], None] | None = None,
    ) -> Pending[Applied]:
        """Apply ``ops`` (their blob references into ``blob_parts`` joined; the first
        ``zpart[0]`` bytes a zlib stream of ``zpart[1]`` bytes) if the robot is still at
        (``epoch``, ``gen``), each only if its path holds what it expects; ``policy``
        says what a mismatch does (``preserve``: keep the robot's version aside,
        ``refuse``). ``sent`` as :meth:`Connection.send`."""
        request = SyncRequest(
            op="sync",
            ops=[op.to_wire() for op in ops],
            policy=policy,
            epoch=epoch,
            gen=gen,
            require_fresh=True,
        )
        if zpart is not None:
            request["zpart"] = list(zpart)
        return self._send(
            request,
            lambda frame: Applied.from_frame(frame, ops),
            blob_parts=blob_parts,
            sent=sent,
        )

    def sync(
        self,
        ops: list[M.Op],
        *,
        policy: str,
        epoch: str,
        gen: int,
        zpart: tuple[int, int] | None = None,
        blob_parts: list[bytes] | None = None,
    ) -> Applied:
        return self.send_sync(
            ops, policy=policy, epoch=epoch, gen=gen, zpart=zpart, blob_parts=blob_parts
        ).wait()

    # -- read
    def send_read(
        self, items: list[tuple[str, int, int]] | list[str]
    ) -> Pending[list[Content | Failed]]:
        """The content of robot files: paths (whole files), or (path, offset, length)."""
        wanted: list[ReadItem] = [
            ReadItem(p=i) if isinstance(i, str) else ReadItem(p=i[0], off=i[1], len=i[2])
            for i in items
        ]
        n = len(wanted)

        def parse(frame: wire.Frame) -> list[Content | Failed]:
            out: list[Content | Failed] = []
            for ans, data in _items("read", frame, n):
                out.append(_failed(ans) or Content(M.Listed.from_wire(ans.get("l")), data))
            return out

        return self._send(ReadRequest(op="read", items=wanted), parse)

    def read(self, items: list[tuple[str, int, int]] | list[str]) -> list[Content | Failed]:
        return self.send_read(items).wait()

    # -- sigs
    def sigs(self, paths: list[str]) -> list[Signed | Failed]:
        """Delta signatures of the robot's copies of ``paths``."""

        def parse(frame: wire.Frame) -> list[Signed | Failed]:
            out: list[Signed | Failed] = []
            for ans, data in _items("sigs", frame, len(paths)):
                out.append(_failed(ans) or Signed(_str("sigs", ans, "h"), data))
            return out

        request = SigsRequest(op="sigs", items=[ReadItem(p=p) for p in paths])
        return self._send(request, parse).wait()

    # -- adopt
    def adopt(self, entries: list[M.Listed]) -> Adopted:
        """Tell the robot's index that it holds ``entries`` (found identical to the laptop's
        by hash), so its drift checks stop reporting them."""

        def parse(frame: wire.Frame) -> Adopted:
            h = frame.header
            return Adopted(
                _int("adopt", h, "adopted"), _str("adopt", h, "epoch"), _int("adopt", h, "gen")
            )

        request = AdoptRequest(op="adopt", entries=[e.to_wire() for e in entries])
        return self._send(request, parse).wait()

    # -- kept
    def kept(self, where: str) -> KeptList:
        """The files kept in the workspace's ``.fetchsync/<where>`` (``conflicts``, ``trash``)."""

        def parse(frame: wire.Frame) -> KeptList:
            return KeptList(
                _list("kept", frame.header, "entries"), frame.header.get("more") is True
            )

        return self._send(KeptRequest(op="kept", where=where), parse).wait()

    def kept_piece(self, where: str, at: str, path: str, *, offset: int, length: int) -> KeptPiece:
        """``length`` bytes at ``offset`` of the file kept at ``<where>/<at>/<path>``."""

        def parse(frame: wire.Frame) -> KeptPiece:
            size = _int("kept", frame.header, "size")
            if size < 0 or offset + len(frame.blob) > size:
                raise _malformed("kept", "more bytes than the file's size")
            return KeptPiece(size, frame.blob)

        request = KeptRequest(op="kept", where=where, at=at, p=path, off=offset, len=length)
        return self._send(request, parse).wait()

    # -- ping
    def ping(self) -> None:
        """One round trip: proof that the endpoint answers."""
        self._send(PingRequest(op="ping"), lambda frame: None).wait()
