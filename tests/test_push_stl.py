"""Binary STL meshes travel with their records split (protocol.stl, messages.SRC_STL):
the same files land on the robot, byte for byte, with fewer bytes on the wire; a file
only shaped like an STL in part (its count and size disagree, truncated, empty, a huge
count) travels as it is; a split the robot cannot join, or one that joins to other
content than the operation's hash, never lands. Through the real sshd and through a real
Python 3.6 endpoint."""

from __future__ import annotations

import math
import os
import random
import struct
from pathlib import Path
from typing import Iterator

import pytest
from helpers import fetchsync, local_env, make_workspace, report, tree_of

from fetchsync.link.client import Endpoint
from fetchsync.link.connection import Connection
from fetchsync.link.ssh import SSHTransport
from fetchsync.protocol import hashing, stl
from fetchsync.protocol import messages as M
from fetchsync.protocol.store import Store
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State

ALG = "blake2b-128"
PY36 = "/root/.pyenv/versions/3.6.15/bin/python3.6"


def mesh(triangles: list[tuple[tuple[float, float, float], ...]], name: str = "part") -> bytes:
    """A binary STL as CAD exporters write it: a facet normal, three vertices, attribute 0."""
    out = [name.encode().ljust(80, b"\0"), struct.pack("<I", len(triangles))]
    for a, b, c in triangles:
        u = [b[i] - a[i] for i in range(3)]
        v = [c[i] - a[i] for i in range(3)]
        n = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])
        length = math.sqrt(sum(x * x for x in n)) or 1.0
        out.append(struct.pack("<12fH", *(x / length for x in n), *a, *b, *c, 0))
    return b"".join(out)


def sphere(rings: int, segments: int, radius: float = 0.05) -> bytes:
    """A UV sphere: neighbouring triangles share their vertices, as real meshes do."""

    def at(i: int, j: int) -> tuple[float, float, float]:
        t, p = math.pi * i / rings, 2 * math.pi * j / segments
        return (
            radius * math.sin(t) * math.cos(p),
            radius * math.sin(t) * math.sin(p),
            radius * math.cos(t),
        )

    tris = []
    for i in range(rings):
        for j in range(segments):
            a, b, c, d = at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)
            tris += [(a, b, c), (a, c, d)]
    return mesh(tris, "sphere")


def plate(n: int) -> bytes:
    """A flat gripper plate of ``n`` x ``n`` squares: the same normal in every record."""
    tris = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = (i, j, 0.0), (i + 1, j, 0.0), (i + 1, j + 1, 0.0), (i, j + 1, 0.0)
            tris += [(a, b, c), (a, c, d)]
    return mesh([tuple(tuple(x * 0.001 for x in v) for v in t) for t in tris], "plate")


def odd_files() -> dict[str, bytes]:
    """Files an STL's shape test must leave as they are, and the smallest real ones."""
    rng = random.Random(24)
    real = sphere(6, 8)
    n = (len(real) - 84) // 50
    return {
        "count_mismatch.stl": real + b"\0",  # one byte more than its count says
        "truncated.stl": real[:-7],
        "empty.stl": b"empty".ljust(80, b"\0") + struct.pack("<I", 0),  # 0 triangles: 84 bytes
        "short.stl": real[:83],
        "huge_count.stl": real[:80] + struct.pack("<I", 0xFFFFFFFF) + real[84:],
        "wrong_count.stl": real[:80] + struct.pack("<I", n - 1) + real[84:],
        "one.stl": real[: 84 + 50][:80] + struct.pack("<I", 1) + real[84 : 84 + 50],
        "ascii.stl": b"solid x\n  facet normal 0 0 1\n" * 40,
        "random_shaped.pcd": real[:84] + rng.randbytes(50 * n),  # STL-shaped, any extension
    }


def test_split_and_join_give_back_every_shape_exactly() -> None:
    rng = random.Random(7)
    for data in (sphere(12, 16), plate(9), *(mesh([]) for _ in range(1))):
        split = stl.split(data)
        if stl.triangles(data) < 1:
            assert split is None
            continue
        assert split is not None and split != data and len(split) == len(data)
        assert bytes(stl.join(split) or b"") == data
    for n in (1, 2, 3, 49, 50, 51, 1000):
        data = rng.randbytes(80) + struct.pack("<I", n) + rng.randbytes(50 * n)
        assert bytes(stl.join(stl.split(data) or b"") or b"") == data
    for name, data in odd_files().items():
        if name in ("one.stl", "random_shaped.pcd"):
            assert bytes(stl.join(stl.split(data) or b"") or b"") == data, name
        else:
            assert stl.split(data) is None, name  # travels as it is
    over = bytearray(84)
    n = stl.SIZE_MAX // 50
    over[80:84] = struct.pack("<I", n)
    assert stl.triangles(bytes(over) + bytes(50 * n)) == -1  # over SIZE_MAX: as it is


def test_split_meshes_are_smaller_deflated() -> None:
    """What it is for: ISA-L's level 1, as binary data travels (a facet normal repeats on
    a flat face, a vertex is shared by its neighbours)."""
    from isal import isal_zlib

    for data in (sphere(40, 60), plate(40)):
        plain = len(isal_zlib.compress(data, 1))
        split = len(isal_zlib.compress(stl.split(data) or b"", 1))
        assert split < 0.95 * plain, (plain, split)


@pytest.fixture
def store(tmp_path: Path) -> Iterator[Store]:
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    yield s
    s.unlock()


def _write(store: Store, path: str, content: bytes, blob: bytes) -> M.Result:
    op = M.Op(
        M.WRITE,
        path,
        expect=M.ABSENT,
        mode=0o644,
        hash=hashing.digest(ALG, content).hex(),
        size=len(content),
        source=M.SRC_STL,
        blob=(0, len(blob)),
    )
    return store.apply([op], blob)[0]


def test_the_robot_joins_a_split_mesh_and_lands_it(store: Store, tmp_path: Path) -> None:
    data = sphere(10, 12)
    assert _write(store, "m.stl", data, stl.split(data) or b"").ok
    assert (Path(store.root) / "m.stl").read_bytes() == data


@pytest.mark.parametrize(
    "case", ["not_split", "other_mesh", "count_lies", "size_lies", "not_a_mesh", "planes_swapped"]
)
def test_a_hostile_split_never_lands(store: Store, tmp_path: Path, case: str) -> None:
    """A laptop (or a stream) that lies: the join refuses a blob not shaped as a mesh,
    and whatever it joins to is checked against the operation's hash as any write is."""
    data = sphere(10, 12)
    split = stl.split(data) or b""
    n = stl.triangles(data)
    blob = {
        "not_split": data,  # the plain file, said to be split: joins to other bytes
        "other_mesh": stl.split(sphere(10, 12, radius=0.06)) or b"",
        "count_lies": split[:80] + struct.pack("<I", n + 1) + split[84:],
        "size_lies": split + b"\0" * 50,
        "not_a_mesh": os.urandom(len(split)),
        "planes_swapped": split[:84]
        + split[84 + n : 84 + 2 * n]
        + split[84 : 84 + n]
        + split[84 + 2 * n :],
    }[case]
    res = _write(store, "m.stl", data, blob)
    assert res.code == M.BASE_MISMATCH, res
    assert not (Path(store.root) / "m.stl").exists()


def _tree(src: Path) -> None:
    meshes = src / "robot_description/meshes"
    meshes.mkdir(parents=True)
    (meshes / "base_link.stl").write_bytes(sphere(60, 80))
    (meshes / "gripper_plate.STL").write_bytes(plate(60))
    for name, data in odd_files().items():
        (meshes / name).write_bytes(data)


@pytest.fixture
def ssh_push(ssh_home, remote_dir: Path, tmp_path: Path) -> Iterator:
    """Push a fresh workspace to a fresh robot directory over the real sshd: its bytes up."""
    made: list = []

    def push(name: str) -> tuple[int, Path, Path]:
        make_workspace(tmp_path / name)
        src = tmp_path / name / "src"
        _tree(src)
        conn = Connection.open(SSHTransport.connect("robot", connect_timeout=10.0))
        state = State(tmp_path / f"{name}.sqlite")
        made.append((conn, state))
        s = sync.Syncer(
            conn,
            state,
            local_root=str(src),
            remote_workspace=str(remote_dir / name),
            rules=sync.build_rules(),
        )
        before = conn.bytes_out
        report = s.push()
        assert report.errors == [] and report.conflicts == []
        assert report.rounds == 1  # nothing the robot could not apply, sent again
        return conn.bytes_out - before, src, remote_dir / name / "src"

    yield push
    for conn, state in made:
        conn.close()
        state.close()


@pytest.mark.ssh
def test_a_push_lands_every_mesh_exactly_with_fewer_bytes(ssh_push, monkeypatch) -> None:
    sent, src, robot = ssh_push("split")
    assert tree_of(src) == tree_of(robot)
    monkeypatch.setattr(Endpoint, "stl", property(lambda self: False))  # an older robot
    plain, src2, robot2 = ssh_push("plain")
    assert tree_of(src2) == tree_of(robot2)
    assert sent < plain - 20_000, (sent, plain)


@pytest.mark.skipif(
    not os.path.exists(PY36) and not os.environ.get("CI"), reason="no Python 3.6 at " + PY36
)
def test_a_python_36_endpoint_joins_the_meshes(tmp_path: Path) -> None:
    make_workspace(tmp_path / "ws")
    src = tmp_path / "ws/src"
    _tree(src)
    env = local_env(
        tmp_path,
        FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "rh"),
        FETCHSYNC_REMOTE_WORKSPACE="~/rws",
        FETCHSYNC_REMOTE_PYTHON=PY36,
    )
    out = report(fetchsync("push", "--json", env=env))
    assert out["rounds"] == 1 and out["ok"], out  # every split mesh joined the first time
    assert tree_of(src) == tree_of(tmp_path / "rh/rws/src")
    built = [p.name for p in (tmp_path / "rh/.cache/fetchsync").iterdir()]
    assert any(name.endswith("-cpython-36") for name in built), built


class _Endpoint:
    stl = True

    class conn:  # noqa: N801 - stands for the Connection attribute
        compress = True
        bytes_in = bytes_out = 0


def test_a_mesh_the_robot_could_not_apply_goes_as_it_is_next_round() -> None:
    """A base mismatch puts the path in the round's whole_only: its next write is plain
    data, not split again (a robot that cannot join would otherwise refuse it again)."""
    data = sphere(20, 24)
    op = M.Op(M.WRITE, "m.stl", expect=M.ABSENT, hash="00", size=len(data), source=M.SRC_DATA)
    sources = []
    for unsplit in (set(), {"m.stl"}):
        batcher = sync._Batcher(
            _Endpoint(),  # type: ignore[arg-type]
            policy="preserve",
            epoch="e",
            gen=0,
            progress=None,
            total=0,
            unsplit=unsplit,
        )
        sources.append(batcher._pack(0, [(op, data, True)], [None]).ops[0].source)
    assert sources == [M.SRC_STL, M.SRC_DATA]
