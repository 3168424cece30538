"""Protocol messages: operations on a tree, their results, and tree listings.

Each is small and immutable (a frozen dataclass, or a NamedTuple where a push
makes one per file), with ``to_wire()`` (a JSON-able value) and ``from_wire()``
(validates; ``Op.validate()`` raises ProtocolError).

An *expectation* is what the receiver should hold at a path before an
operation applies, written as a string:

    "-"            nothing
    "d"            a directory
    "l:TARGET"     a symlink to TARGET
    "f:HEXHASH"    a regular file with that content hash

A mismatch is a conflict: the receiver's version is preserved, never lost.
"""

from typing import Any, Dict, List, NamedTuple, Optional, Tuple

from fetchsync.protocol import paths
from fetchsync.protocol.compat import dataclass, field, fields
from fetchsync.protocol.errors import ProtocolError

MKDIR = "mkdir"
WRITE = "write"
SYMLINK = "symlink"
CHMOD = "chmod"
DELETE = "delete"
UPLOAD = "upload"
OP_KINDS = (MKDIR, WRITE, SYMLINK, CHMOD, DELETE, UPLOAD)

# sources of a write
SRC_DATA = "data"  # the blob holds the whole content
SRC_DELTA = "delta"  # the blob holds a delta against the current file (hash ``base``)
SRC_COPY = "copy"  # content the receiver holds at another path (hash ``base``)
SRC_UPLOAD = "upload"  # content sent before in UPLOAD ops with id ``upload``
# the blob is a raw deflate stream of the whole content, made with the current file (hash
# ``base``, at most ZDICT_BASE_MAX bytes) as its preset dictionary; only to an endpoint
# whose hello offers "zdict" (an older one refuses an unknown source)
SRC_ZDICT = "zdict"
# the blob holds the whole content of a binary STL with its records split (stl.split: ~10-26%
# fewer bytes of real meshes on the wire); only to an endpoint whose hello offers "stl"
SRC_STL = "stl"
SOURCES = (SRC_DATA, SRC_DELTA, SRC_COPY, SRC_UPLOAD, SRC_ZDICT, SRC_STL)
ZDICT_BASE_MAX = 32 * 1024  # zlib's window: a longer dictionary would not be seen whole
ZDICT_SIZE_MAX = 1024 * 1024  # the content such a write may inflate to

ABSENT = "-"
IS_DIR = "d"

# result codes
OK = "ok"
CONFLICT = "conflict"  # precondition failed and the conflict policy refused
BASE_MISMATCH = "base_mismatch"  # delta/copy base is not what we expected: resend whole
IO_ERROR = "io"
PATH_ERROR = "path"
NO_SPACE = "no_space"


def expect_file(hexhash: str) -> str:
    return "f:" + hexhash


def expect_link(target: str) -> str:
    return "l:" + target


def _check_expect(value: "Optional[str]") -> None:
    if value is None:
        return
    if not isinstance(value, str) or not (value in (ABSENT, IS_DIR) or value[:2] in ("f:", "l:")):
        raise ProtocolError("bad expectation %r" % (value,))


def _check_int(name: str, value: "Any", lo: int = 0, hi: int = 1 << 62) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
        raise ProtocolError("%s out of range: %r" % (name, value))


@dataclass(frozen=True)
class Op:
    kind: str
    path: str
    expect: "Optional[str]" = None  # None: no check (only for UPLOAD)
    mode: int = 0
    target: str = ""  # SYMLINK
    hash: str = ""  # WRITE: content hash of the result (hex)
    size: int = 0  # WRITE: size of the result; UPLOAD: offset
    source: str = ""  # WRITE: one of SOURCES
    base: str = ""  # WRITE from delta: hash of the base; from copy: its hash
    from_path: str = ""  # WRITE from copy
    blob: "Tuple[int, int]" = (0, 0)  # (offset, length) in the request's blob
    upload: str = ""  # WRITE from upload / UPLOAD: the upload id
    z: int = 0  # 1: the blob is zlib-compressed

    def validate(self) -> "Op":
        if self.kind not in OP_KINDS:
            raise ProtocolError("unknown operation %r" % (self.kind,))
        if self.kind == UPLOAD:
            if not self.upload.isalnum() or len(self.upload) > 64:
                raise ProtocolError("bad upload id %r" % (self.upload,))
            _check_int("upload offset", self.size)
        else:
            paths.validate(self.path)
            _check_expect(self.expect)
            if self.expect is None:
                raise ProtocolError("%s of %r has no expectation" % (self.kind, self.path))
        _check_int("mode", self.mode, 0, 0o7777)
        _check_int("z", self.z, 0, 1)
        off, length = self.blob
        _check_int("blob offset", off)
        _check_int("blob length", length)
        if self.kind == SYMLINK and (not self.target or "\x00" in self.target):
            raise ProtocolError("bad symlink target for %r" % self.path)
        if self.kind == WRITE:
            if self.source not in SOURCES:
                raise ProtocolError("unknown write source %r" % (self.source,))
            _check_int("size", self.size)
            if not self.hash or len(self.hash) > 128:
                raise ProtocolError("write of %r has no content hash" % self.path)
            if self.source == SRC_COPY:
                paths.validate(self.from_path)
                if not self.base:
                    raise ProtocolError("copy to %r has no source hash" % self.path)
            if self.source in (SRC_DELTA, SRC_ZDICT) and not self.base:
                raise ProtocolError("delta to %r has no base hash" % self.path)
            if self.source == SRC_ZDICT and self.size > ZDICT_SIZE_MAX:
                raise ProtocolError("dictionary write of %r is too large" % self.path)
            if self.source == SRC_UPLOAD and not self.upload.isalnum():
                raise ProtocolError("bad upload id %r" % (self.upload,))
        return self

    def but(self, **changes: "Any") -> "Op":
        """A copy with ``changes``: ``dataclasses.replace`` without the frozen __init__'s
        setattr per field (the laptop makes two or three per file it sends). Like it,
        no validation: ``validate()`` is the receiver's."""
        unknown = changes.keys() - _FIELDS
        if unknown:
            raise TypeError("Op has no field %s" % ", ".join(sorted(unknown)))
        new = object.__new__(Op)
        d = new.__dict__
        d.update(self.__dict__)
        d.update(changes)
        return new

    def to_wire(self) -> "Dict[str, Any]":
        out = {"k": self.kind, "p": self.path}  # type: Dict[str, Any]
        if self.expect is not None:
            out["e"] = self.expect
        if self.mode:
            out["m"] = self.mode
        if self.target:
            out["t"] = self.target
        if self.hash:
            out["h"] = self.hash
        if self.size:
            out["s"] = self.size
        if self.source:
            out["src"] = self.source
        if self.base:
            out["b"] = self.base
        if self.from_path:
            out["fp"] = self.from_path
        if self.blob != (0, 0):
            out["bl"] = list(self.blob)
        if self.upload:
            out["u"] = self.upload
        if self.z:
            out["z"] = self.z
        return out

    @classmethod
    def from_wire(cls, obj: "Any") -> "Op":
        if not isinstance(obj, dict):
            raise ProtocolError("operation is not an object")
        get = obj.get
        blob = get("bl", (0, 0))
        if not isinstance(blob, (list, tuple)) or len(blob) != 2:
            raise ProtocolError("bad blob reference")
        if "k" not in obj:
            raise ProtocolError("operation lacks 'k'")
        path, target, hash_, source = get("p", ""), get("t", ""), get("h", ""), get("src", "")
        base, from_path, upload = get("b", ""), get("fp", ""), get("u", "")
        if not (
            type(path)
            is type(target)
            is type(hash_)
            is type(source)
            is type(base)  # noqa: E721
            is type(from_path)
            is type(upload)
            is str
        ):  # a str subclass is no wire value
            for name, value in (
                ("path", path),
                ("target", target),
                ("hash", hash_),
                ("source", source),
                ("base", base),
                ("from_path", from_path),
                ("upload", upload),
            ):
                if type(value) is not str:  # noqa: E721
                    raise ProtocolError("operation field %s is not a string" % name)
        # the frozen dataclass's __init__ sets each field through object.__setattr__:
        # a request of thousands of operations is decoded faster by filling the
        # instance's dict directly, key by key in field order (which keeps it the
        # compact dict instances share keys in), then validated as before
        op = object.__new__(cls)
        d = op.__dict__
        (
            d["kind"],
            d["path"],
            d["expect"],
            d["mode"],
            d["target"],
            d["hash"],
            d["size"],
            d["source"],
            d["base"],
            d["from_path"],
            d["blob"],
            d["upload"],
            d["z"],
        ) = (
            obj["k"],
            path,
            get("e"),
            get("m", 0),
            target,
            hash_,
            get("s", 0),
            source,
            base,
            from_path,
            (blob[0], blob[1]),
            upload,
            get("z", 0),
        )
        return op.validate()


_FIELDS = frozenset(f.name for f in fields(Op))


# an answer's result that is only this number: the operation succeeded and left exactly
# what it asked for (see :func:`asked`), so the listing entry is not spelled out again
# (JSON for each of a 7,000-file push's results was ~5% of the robot's serving thread)
AS_ASKED = 0


def asked(op: "Op") -> "Optional[List[Any]]":
    """The listing entry an operation leaves when it does exactly what it asks, as
    :meth:`Listed.to_wire` spells it; None for kinds that do not say (chmod, delete)."""
    if op.kind == WRITE:
        return [op.path, "f", op.mode, op.size, op.hash]
    if op.kind == MKDIR:
        return [op.path, "d", op.mode, 0, ""]
    if op.kind == SYMLINK:
        return [op.path, "l", 0, 0, op.target]
    return None


class Result(NamedTuple):
    """The outcome of one operation. A NamedTuple, as Listed: a push makes one or two
    per file on the robot and decodes one per file on the laptop."""

    code: str = OK
    message: str = ""
    preserved: str = ""  # where the receiver's conflicting version was moved
    written: "Optional[List[Any]]" = None  # the listing entry of what now stands there

    @property
    def ok(self) -> bool:
        return self.code == OK

    def to_wire(self, op: "Optional[Op]" = None) -> "Any":
        """The wire form; with the ``op`` it answers, just AS_ASKED when it did exactly that."""
        if (
            op is not None
            and self.code == OK
            and not self.message
            and not self.preserved
            and self.written is not None
            and self.written == asked(op)
        ):
            return AS_ASKED
        out = {"c": self.code}  # type: Dict[str, Any]
        if self.message:
            out["msg"] = self.message
        if self.preserved:
            out["pv"] = self.preserved
        if self.written is not None:
            out["w"] = self.written
        return out

    @classmethod
    def from_wire(cls, obj: "Any", op: "Optional[Op]" = None) -> "Result":
        """The result of ``op`` from its wire form (AS_ASKED needs the ``op``)."""
        if type(obj) is int and obj == AS_ASKED:
            written = asked(op) if op is not None else None
            if written is None:
                raise ProtocolError("a result says 'as asked' of an operation that does not say")
            return cls(OK, "", "", written)
        if not isinstance(obj, dict) or not isinstance(obj.get("c"), str):
            raise ProtocolError("bad result")
        return cls(obj["c"], str(obj.get("msg", "")), str(obj.get("pv", "")), obj.get("w"))


class Listed(NamedTuple):
    """One entry of a receiver's listing: what stands at a path, with its content hash.

    A NamedTuple rather than a dataclass: trees hold tens of thousands of
    these, and building them is on the no-op push's critical path.
    """

    path: str
    kind: str
    mode: int = 0
    size: int = 0
    hash: str = ""  # files
    target: str = ""  # links

    def expectation(self) -> str:
        if self.kind == "d":
            return IS_DIR
        if self.kind == "l":
            return expect_link(self.target)
        return expect_file(self.hash)

    def to_wire(self) -> "List[Any]":
        return [self.path, self.kind, self.mode, self.size, self.hash or self.target]

    @classmethod
    def from_wire(cls, obj: "Any") -> "Listed":
        if not isinstance(obj, (list, tuple)) or len(obj) != 5:
            raise ProtocolError("bad listing entry")
        path, kind, mode, size, extra = obj
        if kind not in ("f", "d", "l") or not isinstance(extra, str):
            raise ProtocolError("bad listing entry kind %r" % (kind,))
        _check_int("mode", mode, 0, 0o7777)
        _check_int("size", size)
        paths.validate(path)
        if kind == "f":
            return cls(path, kind, mode, size, hash=extra)
        if kind == "l":
            if not extra or "\x00" in extra:
                raise ProtocolError("bad symlink target at %r" % path)
            return cls(path, kind, 0, 0, target=extra)
        return cls(path, kind, mode)


@dataclass(frozen=True)
class Stats:
    files: int = 0
    dirs: int = 0
    deleted: int = 0
    bytes_literal: int = 0
    bytes_reused: int = 0
    extra: "Dict[str, Any]" = field(default_factory=dict)
