"""Pushes that span many pipelined batches (the protocol without SSH, over the local robot)."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import tree_of

from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State


@pytest.fixture
def syncer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(sync, "BATCH_OPS", 40)
    monkeypatch.setattr(sync, "BATCH_BYTES", 64 * 1024)
    src = tmp_path / "ws" / "src"
    for d in range(12):
        (src / f"pkg{d}").mkdir(parents=True)
        for f in range(30):
            (src / f"pkg{d}" / f"f{f}.txt").write_text(f"{d} {f}\n" * (50 + f * d))
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    state = State(tmp_path / "state.sqlite")
    s = sync.Syncer(
        conn, state, local_root=str(src), remote_workspace="~/ws", rules=sync.build_rules()
    )
    yield s, src, tmp_path / "robot-home" / "ws" / "src"
    conn.close()
    state.close()


def test_a_push_of_many_batches_lands_whole_in_one_round(syncer):
    s, src, robot_src = syncer
    report = s.push()
    assert report.errors == [] and report.rounds == 1
    assert report.files == 360 and report.dirs == 12
    assert tree_of(src) == tree_of(robot_src)
    for f in list(src.rglob("f1*.txt"))[:60]:
        f.write_text("changed\n")
    report = s.push()
    assert report.errors == [] and report.rounds == 1 and report.files == 60
    assert tree_of(src) == tree_of(robot_src)


@pytest.mark.parametrize("deflate", ["isal", "zlib"])
def test_compressed_batches_inflate_on_the_robot_from_either_compressor(
    syncer, monkeypatch, deflate
):
    """The laptop deflates with ISA-L when it can, else with zlib; the robot's
    standard library inflates both."""
    import zlib

    if deflate == "isal":
        from isal import isal_zlib  # a dependency: never skipped

        monkeypatch.setattr(sync, "_deflate", isal_zlib)
    else:
        monkeypatch.setattr(sync, "_deflate", zlib)
    s, src, robot_src = syncer
    report = s.push()
    assert report.errors == [] and report.files == 360
    assert tree_of(src) == tree_of(robot_src)
    assert report.bytes_sent < sum(f.stat().st_size for f in src.rglob("*.txt")) // 2  # compressed


def test_another_writer_between_batches_is_detected_and_survived(syncer, tmp_path):
    s, src, robot_src = syncer
    s.push()
    # a second laptop writes to the same robot workspace
    other = Connection.open(LocalTransport(tmp_path / "robot-home"))
    other_state = State(tmp_path / "other.sqlite")
    other_src = tmp_path / "other" / "src"
    other_src.mkdir(parents=True)
    (other_src / "theirs.txt").write_text("theirs\n")
    sync.Syncer(
        other,
        other_state,
        local_root=str(other_src),
        remote_workspace="~/ws",
        rules=sync.build_rules(),
    ).push(confirm_deletions=True)  # it replaces everything
    other.close()
    other_state.close()
    # our next push must notice, re-list, and still end identical, keeping their work aside
    (src / "pkg0" / "f0.txt").write_text("ours\n")
    report = s.push()
    assert report.errors == []
    assert tree_of(src) == tree_of(robot_src)
    kept = list((robot_src.parent / ".fetchsync" / "conflicts").rglob("theirs.txt"))
    assert kept and kept[0].read_text() == "theirs\n"


def test_binary_files_keep_no_signature_yet_an_edit_still_travels_as_a_delta(syncer):
    s, src, robot_src = syncer
    rnd = __import__("random").Random(3)
    mesh = bytes(rnd.getrandbits(8) for _ in range(300_000))  # NULs: binary
    (src / "pkg0" / "mesh.stl").write_bytes(mesh)
    (src / "pkg0" / "table.cpp").write_text("".join(f"int t{i} = {i * 7};\n" for i in range(20000)))
    s.push()
    signed = s.state.signed_paths()
    assert "pkg0/table.cpp" in signed and "pkg0/mesh.stl" not in signed
    (src / "pkg0" / "mesh.stl").write_bytes(mesh[:150_000] + b"edited" + mesh[150_006:])
    report = s.push()
    assert report.errors == [] and report.files == 1
    assert (robot_src / "pkg0" / "mesh.stl").read_bytes() == (
        src / "pkg0" / "mesh.stl"
    ).read_bytes()
    # the robot signed its copy and only the changed region travelled
    assert report.bytes_sent < 60_000, report.bytes_sent


def test_the_no_op_shortcut_still_sees_every_kind_of_change(syncer):
    s, src, robot_src = syncer
    s.push()
    r = s.push()
    assert (r.files, r.dirs, r.deleted, r.rounds) == (0, 0, 0, 0)
    changes = [
        lambda: (src / "pkg1" / "empty").mkdir(),
        lambda: (src / "pkg1" / "f1.txt").chmod(0o755),
        lambda: (src / "pkg2").chmod(0o700),
        lambda: (robot_src / "pkg3" / "f2.txt").write_text("edited on the robot\n"),
        lambda: (robot_src / "pkg3" / "f3.txt").unlink(),
        lambda: (src / "pkg4" / "f4.txt").unlink(),
        lambda: (src / "link").symlink_to("pkg0"),
    ]
    for change in changes:
        change()
        r = s.push()
        assert r.errors == [] and r.rounds == 1, r
        assert tree_of(src) == tree_of(robot_src)


def test_a_lost_robot_index_is_rebuilt_by_the_next_push(syncer):
    """Files the robot already holds are adopted into its index after a full listing:
    else every later drift check there reports all of them, forever."""
    s, src, robot_src = syncer
    s.push()
    (robot_src.parent / ".fetchsync" / "index").unlink()
    s.opened = None  # a new session: the robot reloads its (now missing) index
    s.conn.close()
    s.conn = Connection.open(LocalTransport(robot_src.parent.parent))
    relisted = s.push()
    assert relisted.errors == [] and relisted.files == 0 and relisted.bytes_received > 10_000
    again = s.push()
    assert again.errors == [] and again.files == 0
    assert again.bytes_received < 1_000, again.bytes_received  # an empty drift, not a listing
    assert tree_of(src) == tree_of(robot_src)


def test_drift_the_laptop_already_matches_is_adopted_too(syncer):
    """A robot index that forgot its records but kept its generation reports every path
    as drift; once found identical they are adopted, and the next drift is empty."""
    from fetchsync.protocol.store import Store

    s, src, robot_src = syncer
    s.push()
    robot = Store(str(robot_src.parent), algorithm=s.algorithm)
    robot.synced.clear()
    robot._write_snapshot()  # same epoch and generation, no records
    s.opened = None
    s.conn.close()
    s.conn = Connection.open(LocalTransport(robot_src.parent.parent))
    first = s.push()
    assert first.errors == [] and first.files == 0 and first.bytes_received > 10_000
    again = s.push()
    assert again.errors == [] and again.bytes_received < 1_000, again.bytes_received


def test_a_few_local_changes_are_pushed_path_by_path_with_reuse(syncer):
    s, src, robot_src = syncer
    s.push()
    (src / "pkg5" / "f7.txt").rename(src / "pkg6" / "moved.txt")
    (src / "pkg1" / "f1.txt").write_text("edited\n")
    (src / "pkg2" / "f2.txt").unlink()
    (src / "pkg3" / "newdir" / "sub").mkdir(parents=True)
    (src / "pkg3" / "newdir" / "sub" / "n.txt").write_text("new\n")
    r = s.push()
    assert r.errors == [] and r.reused == 1 and r.deleted == 2 and r.files == 3 and r.dirs == 2, r
    assert tree_of(src) == tree_of(robot_src)
    assert s.push().changed == 0


class _Clock:
    """sync's time, advanced by the fake link below as it carries bytes."""

    def __init__(self) -> None:
        self.now = 1000.0

    def monotonic(self) -> float:
        return self.now


def test_a_robot_that_reports_holding_something_else_is_an_error(syncer, monkeypatch):
    """After a round, the laptop checks that what the robot's answers say it now holds is
    the local tree (quickly when every answer is what was sent); a path it reports
    otherwise is a failure of the push, not a silent success."""
    s, src, _robot_src = syncer
    real = sync._as_sent
    odd = "pkg3/f7.txt"

    def as_sent(wire, item):
        got = real(wire, item)
        return got._replace(mode=0o600) if got.path == odd else got

    monkeypatch.setattr(sync, "_as_sent", as_sent)
    report = s.push()
    assert [e["path"] for e in report.errors] == [odd]
    assert "still differ on the robot" in report.errors[0]["error"]
    monkeypatch.setattr(sync, "_as_sent", real)
    assert s.push().errors == []  # and the next push sets it right


def test_same_tree_compares_every_path_and_entry():
    from fetchsync.protocol import messages as M

    a = {"d": M.Listed("d", "d", 0o755), "d/f": M.Listed("d/f", "f", 0o644, 3, hash="ab")}
    assert sync._same_tree(a, dict(a))
    assert sync._same_tree(
        a, {k: M.Listed(*v) for k, v in a.items()}
    )  # equal, not the same objects
    assert not sync._same_tree(a, {**a, "d/f": a["d/f"]._replace(mode=0o600)})
    assert not sync._same_tree(a, {**a, "d/g": a["d/f"]._replace(path="d/g")})
    assert not sync._same_tree(a, {"d": a["d"]})
    assert not sync._same_tree(a, {"d": a["d"], "d/g": a["d/f"]._replace(path="d/g")})
