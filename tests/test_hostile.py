"""A hostile robot during ``pull``: forged listings, contents and frames.

The robot is ``tests/hostile_endpoint.py`` run as the ``local`` robot: the
real wire protocol over pipes, started by a wrapper named as the robot's
Python (the client runs ``PYTHON -c LOADER HASH LEN``; the wrapper ignores
the loader). Whatever it sends, the pull must write nothing outside the local
``src/`` (a canary directory beside it stays empty) and must not damage what
``src/`` holds.
"""

from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path

import helpers
import pytest
from helpers import fetchsync, make_workspace, tree_of, without_where

HERE = Path(__file__).resolve().parent
REPO = HERE.parent


@pytest.fixture
def robot(tmp_path: Path):
    """A workspace on the laptop and one on the ``local`` robot, both synced."""
    ws = make_workspace(tmp_path / "ws")
    canary = ws / "canary"
    canary.mkdir()
    (canary / "keep.txt").write_text("canary\n")
    env = helpers.local_env(tmp_path)
    fetchsync("push", env=env)  # the honest endpoint
    return env, ws, canary


def hostile(env: dict, tmp_path: Path, mode: str, canary: Path) -> dict:
    wrapper = tmp_path / f"hostile-python-{mode}"
    wrapper.write_text(
        "#!/bin/sh\n"
        f"PYTHONPATH={shlex.quote(str(REPO))} exec {shlex.quote(sys.executable)} "
        f"{shlex.quote(str(HERE / 'hostile_endpoint.py'))} {mode} "
        f"{shlex.quote(str(canary))}\n"
    )
    wrapper.chmod(0o755)
    return dict(env, FETCHSYNC_REMOTE_PYTHON=str(wrapper))


def snapshot(ws: Path) -> dict:
    # pull keeps its own store's bookkeeping in .fetchsync/ beside src/
    return {
        "src": tree_of(ws / "src"),
        "canary": tree_of(ws / "canary"),
        "beside": sorted(set(os.listdir(ws)) - {".fetchsync"}),
        "outside": sorted(os.listdir(ws.parent)),
    }


REFUSED = [
    "dotdot",
    "absolute",
    "nul",
    "slash",
    "empty_name",
    "oversized_frame",
    "garbage_after_hello",
    "huge_header",
]


@pytest.mark.parametrize("mode", REFUSED)
def test_pull_refuses_a_forged_listing_or_frame(robot, tmp_path, mode):
    env, ws, canary = robot
    env = hostile(env, tmp_path, mode, canary)
    before = snapshot(ws)
    proc = fetchsync("pull", "--yes", env=env, check=False)
    err = proc.stderr.decode("utf-8", "replace")
    assert proc.returncode != 0, (proc.stdout.decode(), err)
    assert snapshot(ws) == before


@pytest.mark.parametrize("mode", REFUSED)
def test_pull_refusal_is_one_line(robot, tmp_path, mode):
    env, ws, canary = robot
    proc = fetchsync("pull", "--yes", env=hostile(env, tmp_path, mode, canary), check=False)
    err = proc.stderr.decode("utf-8", "replace")
    assert proc.returncode == 7
    assert "Traceback" not in err and len(without_where(err)) == 1, err


def test_pull_never_writes_through_a_symlink_out_of_the_workspace(robot, tmp_path):
    env, ws, canary = robot
    env = hostile(env, tmp_path, "symlink_escape", canary)
    before = snapshot(ws)
    proc = fetchsync("pull", "--yes", env=env, check=False)
    err = proc.stderr.decode("utf-8", "replace")
    assert "Traceback" not in err, err
    assert proc.returncode != 0, (proc.stdout.decode(), err)
    after = snapshot(ws)
    assert after["canary"] == before["canary"] and after["outside"] == before["outside"]
    assert after["beside"] == before["beside"]
    for path, entry in before["src"].items():
        assert after["src"].get(path) == entry, path
    assert not any(p.startswith("escape/") for p in after["src"])


def test_pull_refuses_content_that_does_not_match_the_listing(robot, tmp_path):
    env, ws, canary = robot
    env = hostile(env, tmp_path, "wrong_content", canary)
    before = snapshot(ws)
    proc = fetchsync("pull", "--yes", env=env, check=False)
    err = proc.stderr.decode("utf-8", "replace")
    assert "Traceback" not in err, err
    assert proc.returncode != 0, (proc.stdout.decode(), err)
    after = snapshot(ws)
    assert "my_pkg/lie.txt" not in after["src"]
    assert after == before


# --------------------------------------------------------------------------- fuzzing
# Whatever a robot (or a laptop) sends, the parsers and the store answer with
# ProtocolError or per-operation failure results: never another exception, a
# hang or a huge allocation. FETCHSYNC_FUZZ_EXAMPLES=1000000 runs far more.

import io  # noqa: E402
import resource  # noqa: E402
import struct  # noqa: E402
import tempfile  # noqa: E402

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from fetchsync.protocol import delta as D  # noqa: E402
from fetchsync.protocol import hashing, wire  # noqa: E402
from fetchsync.protocol import messages as M  # noqa: E402
from fetchsync.protocol.errors import ProtocolError  # noqa: E402
from fetchsync.protocol.store import Store, is_temp  # noqa: E402

FUZZ = int(os.environ.get("FETCHSYNC_FUZZ_EXAMPLES", "0"))


def fuzz(default: int):
    return settings(
        max_examples=FUZZ or default,
        deadline=None,
        database=None,
        suppress_health_check=list(HealthCheck),
    )


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@pytest.fixture(autouse=False)
def bounded_memory():
    before = _peak_rss_mb()
    yield
    assert _peak_rss_mb() - before < 512, "a fuzz case allocated hundreds of MiB"


json_leaf = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(1 << 70), 1 << 70),
    st.text(max_size=20),
    st.sampled_from(["", ".", "..", "/", "a/../b", "\x00", "f:00", "l:x", "-", "d"]),
)
json_value = st.one_of(
    json_leaf,
    st.lists(json_leaf, max_size=3),
    st.dictionaries(st.text(max_size=3), json_leaf, max_size=3),
)
op_keys = st.sampled_from(["k", "p", "e", "m", "t", "h", "s", "src", "b", "fp", "bl", "u", "z"])
op_like = (
    st.dictionaries(op_keys, json_value, max_size=13)
    | st.fixed_dictionaries(
        {"k": st.sampled_from(M.OP_KINDS), "p": json_leaf},
        optional={
            "e": json_leaf,
            "bl": json_value,
            "src": st.sampled_from(M.SOURCES),
            "m": json_leaf,
            "s": json_leaf,
            "u": json_leaf,
        },
    )
    | json_value
)

frame_bytes = st.one_of(
    st.binary(max_size=300),
    st.builds(
        lambda blen, t, f, body: struct.pack(">IBBI", blen, t, f, 1) + body,
        st.integers(0, (1 << 32) - 1),
        st.integers(0, 5),
        st.integers(0, 5),
        st.binary(max_size=200),
    ),
    st.builds(
        lambda hdr, blob, comp: wire.encode_frame(wire.Frame(1, 1, hdr, blob), compress=comp),
        st.dictionaries(st.text(max_size=5), json_leaf, max_size=4),
        st.binary(max_size=600),
        st.booleans(),
    ).map(lambda b: b[:-1] if len(b) % 3 == 0 else b),
)


@pytest.mark.slow
@fuzz(2500)
@given(data=frame_bytes)
def test_fuzz_reader_read_frame(data, bounded_memory):
    reader = wire.Reader(io.BytesIO(data).read)
    try:
        for _ in range(4):
            if reader.read_frame() is None:
                break
    except (ProtocolError, EOFError):
        pass


@pytest.mark.slow
@fuzz(1500)
@given(
    ftype=st.integers(0, 255),
    flags=st.integers(0, 255),
    body=st.binary(max_size=300)
    | st.binary(max_size=200).map(lambda b: __import__("zlib").compress(b)),
)
def test_fuzz_decode_body(ftype, flags, body, bounded_memory):
    try:
        wire.decode_body(ftype, flags, 1, body)
    except ProtocolError:
        pass


@given(
    kind=st.sampled_from(M.OP_KINDS),
    path=st.sampled_from(["a", "a/b c", "d/\udcff"]),
    mode=st.integers(0, 0o7777),
    size=st.integers(0, 1 << 40),
    z=st.integers(0, 1),
)
def test_op_from_wire_is_the_op_sent(kind, path, mode, size, z):
    """Decoding builds the instance's fields at once (not through the frozen dataclass's
    __init__): what arrives must equal, hash and behave as the operation sent."""
    op = M.Op(
        kind=kind,
        path=path,
        expect=M.ABSENT,
        mode=mode,
        target="t" if kind == M.SYMLINK else "",
        hash="ab",
        size=size,
        source=M.SRC_DATA if kind == M.WRITE else "",
        blob=(3, 4),
        z=z,
        upload="u1" if kind == M.UPLOAD else "",
    )
    got = M.Op.from_wire(op.to_wire())
    assert got == op and hash(got) == hash(op) and got.blob == (3, 4)
    with pytest.raises(__import__("dataclasses").FrozenInstanceError):  # still frozen
        got.path = "x"  # type: ignore[misc]


def test_op_but_is_dataclasses_replace():
    """Op.but() copies without the frozen __init__; it must give what replace() gives,
    leave the original as it was, and refuse a field Op does not have."""
    import dataclasses

    op = M.Op(
        kind=M.WRITE,
        path="a/b",
        expect=M.ABSENT,
        mode=0o644,
        hash="ab",
        size=3,
        source=M.SRC_DATA,
        blob=(0, 3),
    )
    got = op.but(blob=(7, 3), z=1, source=M.SRC_UPLOAD, upload="u1")
    assert got == dataclasses.replace(op, blob=(7, 3), z=1, source=M.SRC_UPLOAD, upload="u1")
    assert hash(got) == hash(
        dataclasses.replace(op, blob=(7, 3), z=1, source=M.SRC_UPLOAD, upload="u1")
    )
    assert op.blob == (0, 3) and op.z == 0 and op.source == M.SRC_DATA
    with pytest.raises(TypeError, match="no field sizes"):
        op.but(sizes=1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        got.z = 0  # type: ignore[misc]


@pytest.mark.parametrize(
    "wire_op, says",
    [
        ({"p": "a", "e": "-"}, "lacks 'k'"),
        ({"k": "write", "p": 5, "e": "-"}, "path is not a string"),
        ({"k": "write", "p": "a", "e": "-", "h": ["x"]}, "hash is not a string"),
        ({"k": "write", "p": "a", "e": "-", "bl": [1]}, "bad blob reference"),
        ("write", "not an object"),
    ],
)
def test_op_from_wire_refuses_malformed_fields(wire_op, says):
    with pytest.raises(ProtocolError, match=says):
        M.Op.from_wire(wire_op)


@pytest.mark.slow
@fuzz(2000)
@given(obj=op_like)
def test_fuzz_op_from_wire(obj):
    try:
        M.Op.from_wire(obj)
    except ProtocolError:
        pass


@pytest.mark.slow
@fuzz(1500)
@given(
    obj=st.lists(json_leaf, min_size=5, max_size=5)
    | st.tuples(
        st.sampled_from(["a", "a/b", "..", "/x", "a\x00"]),
        st.sampled_from(["f", "d", "l", "x"]),
        json_leaf,
        json_leaf,
        json_leaf,
    ).map(list)
    | json_value
)
def test_fuzz_listed_from_wire(obj):
    try:
        M.Listed.from_wire(obj)
    except ProtocolError:
        pass


def _mutations(good: bytes) -> st.SearchStrategy[bytes]:
    return st.one_of(
        st.binary(max_size=200),
        st.tuples(st.integers(0, max(len(good) - 1, 0)), st.binary(min_size=1, max_size=8)).map(
            lambda t: good[: t[0]] + t[1] + good[t[0] + len(t[1]) :]
        ),
        st.integers(0, len(good)).map(lambda n: good[:n]),
    )


_BASE = b"".join(b"line %d of the base file\n" % i for i in range(400))
_NEW = b"a new first line\n" + _BASE[:5000] + b"inserted\n" + _BASE[5000:]
_SIG = D.signature(_BASE)
_DELTA_BYTES = D.encode_delta(D.delta(_NEW, _SIG))


@fuzz(1500)
@given(data=_mutations(_DELTA_BYTES))
def test_fuzz_decode_delta(data, bounded_memory):
    try:
        d = D.decode_delta(data, max_size=1 << 20)
        D.patch(_BASE, d)
    except ProtocolError:
        pass


@fuzz(1500)
@given(data=_mutations(_SIG.to_bytes()))
def test_fuzz_signature_from_bytes(data, bounded_memory):
    try:
        D.Signature.from_bytes(data)
    except ProtocolError:
        pass


_names = st.sampled_from(
    [
        "a",
        "b",
        "a/b",
        "a/b/c",
        "d",
        "d/x",
        "../x",
        "/abs",
        "a//b",
        "lnk",
        "lnk/in",
        ".fetchsync-tmp-x",
        "",
    ]
)
_expects = st.sampled_from([None, "-", "d", "f:" + "0" * 32, "l:a", "l:/etc", "x"])
fuzz_op = st.builds(
    lambda kind, path, expect, mode, target, src, size, blob, z, upload, fp: {
        "k": kind,
        "p": path,
        "e": expect,
        "m": mode,
        "t": target,
        "h": "ab" * 16,
        "s": size,
        "src": src,
        "b": "ab" * 16,
        "fp": fp,
        "bl": blob,
        "u": upload,
        "z": z,
    },
    st.sampled_from(M.OP_KINDS),
    _names,
    _expects,
    st.integers(0, 0o7777),
    st.sampled_from(["", "a", "/etc", "../..", "lnk"]),
    st.sampled_from(M.SOURCES + ("",)),
    st.integers(0, 1 << 40),
    st.lists(st.integers(0, 1 << 40), min_size=2, max_size=2),
    st.integers(0, 1),
    st.sampled_from(["", "u1", "u2"]),
    _names,
)


@fuzz(300)
@given(
    raw_ops=st.lists(fuzz_op, max_size=8),
    blob=st.binary(max_size=256),
    zpart=st.none() | st.lists(st.integers(0, 1 << 30), min_size=2, max_size=2),
)
def test_fuzz_store_apply(raw_ops, blob, zpart, bounded_memory):
    with tempfile.TemporaryDirectory() as tmp:
        outside = Path(tmp) / "outside"
        outside.mkdir()
        store = Store(os.path.join(tmp, "ws"), algorithm=hashing.FALLBACK)
        os.makedirs(os.path.join(store.root, "d"))
        os.symlink(str(outside), os.path.join(store.root, "lnk"))
        ops = []
        for raw in raw_ops:
            try:
                ops.append(M.Op.from_wire({k: v for k, v in raw.items() if v is not None}))
            except ProtocolError:
                pass
        try:
            results = store.apply(ops, blob, zpart=zpart)
            assert len(results) == len(ops)
        except ProtocolError:
            pass
        store.discard_uploads()
        assert os.listdir(outside) == []
        assert not [n for _d, _s, files in os.walk(store.root) for n in files if is_temp(n)]


# --------------------------------------------------------------------------- awkward files
SPARSE_SIZE = "2G" if os.environ.get("FETCHSYNC_TEST_2G_SPARSE") else "64M"


@pytest.fixture
def local_env(tmp_path: Path) -> dict:
    (tmp_path / "ws" / "src").mkdir(parents=True)
    return helpers.local_env(tmp_path)


def _bytes_tree(root: Path) -> dict:
    """Like tree_of, with bytes names (non-UTF-8 names compare exactly)."""
    out = {}
    broot = os.fsencode(root)
    for dirpath, dirs, files in os.walk(broot):
        for name in dirs + files:
            full = os.path.join(dirpath, name)
            rel = os.path.relpath(full, broot)
            st_ = os.lstat(full)
            if os.path.islink(full):
                out[rel] = ("l", os.readlink(full))
            elif os.path.isdir(full):
                out[rel] = ("d",)
            elif not os.path.isfile(full):
                out[rel] = ("special",)  # never open a FIFO: it would block
            else:
                with open(full, "rb") as fh:
                    out[rel] = (
                        "f",
                        st_.st_mode & 0o777,
                        hashing.digest(hashing.FALLBACK, fh.read()),
                    )
    return out


def test_awkward_files_round_trip(local_env, tmp_path):
    import socket
    import unicodedata

    src = Path(local_env["FETCHSYNC_WORKSPACE"]) / "src"
    (src / "with space.txt").write_text("space\n")
    (src / "new\nline.txt").write_text("newline\n")
    with open(os.path.join(os.fsencode(src), b"latin1-\xe9.txt"), "wb") as fh:
        fh.write(b"not utf-8 name\n")
    nfc, nfd = unicodedata.normalize("NFC", "caf\u00e9"), unicodedata.normalize("NFD", "caf\u00e9")
    (src / (nfc + ".txt")).write_text("nfc\n")
    (src / (nfd + ".txt")).write_text("nfd\n")
    (src / "loop_a").symlink_to("loop_b")
    (src / "loop_b").symlink_to("loop_a")
    (src / "hard1.txt").write_text("same inode\n")
    os.link(src / "hard1.txt", src / "hard2.txt")
    os.mkfifo(src / "a.fifo")
    sock = socket.socket(socket.AF_UNIX)
    sock_path = src / "a.sock"
    sock.bind(str(sock_path))
    subprocess_run = __import__("subprocess").run
    subprocess_run(["truncate", "-s", SPARSE_SIZE, str(src / "sparse.img")], check=True)
    try:
        proc = fetchsync("push", "--json", env=local_env)
        robot = Path(local_env["FETCHSYNC_LOCAL_ROBOT_HOME"]) / "robot_ws" / "src"
        want = _bytes_tree(src)
        want.pop(b"a.fifo")
        want.pop(b"a.sock")
        assert _bytes_tree(robot) == want
        assert not (robot / "a.fifo").exists() and not (robot / "a.sock").exists()
        # and back: wipe the local copy of everything but the special files, pull
        for name in os.listdir(os.fsencode(src)):
            if name not in (b"a.fifo", b"a.sock"):
                os.unlink(os.path.join(os.fsencode(src), name))
        fetchsync("pull", "--yes", env=local_env)
        got = _bytes_tree(src)
        got.pop(b"a.fifo", None)
        got.pop(b"a.sock", None)
        assert got == want
        assert (src / "hard1.txt").read_text() == (src / "hard2.txt").read_text() == "same inode\n"
        assert proc.returncode == 0
    finally:
        sock.close()
