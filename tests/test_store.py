"""The filesystem endpoint's rules, one test each (no transport involved)."""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import pytest

from fetchsync.protocol import hashing, wire
from fetchsync.protocol import messages as M
from fetchsync.protocol import store as store_mod
from fetchsync.protocol.errors import ProtocolError
from fetchsync.protocol.store import TRASH_KEEP_BATCHES, Store

LARGE = 512 * 1024

ALG = "blake2b-128"


def h(data: bytes) -> str:
    return hashing.digest(ALG, data).hex()


def write(path: str, data: bytes, *, expect: str = M.ABSENT, at: int = 0) -> M.Op:
    return M.Op(
        M.WRITE,
        path,
        expect=expect,
        mode=0o644,
        hash=h(data),
        size=len(data),
        source=M.SRC_DATA,
        blob=(at, len(data)),
    )


@pytest.fixture
def store(tmp_path: Path) -> Store:
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    yield s
    s.unlock()


def src(store: Store) -> Path:
    return Path(store.root)


def test_write_lands_whole_and_leaves_no_temporary(store):
    [r] = store.apply([write("a.txt", b"hello")], b"hello")
    assert r.ok and (src(store) / "a.txt").read_bytes() == b"hello"
    assert M.Listed.from_wire(r.written).hash == h(b"hello")
    assert [p.name for p in src(store).iterdir()] == ["a.txt"]


def test_content_not_matching_its_hash_is_refused(store):
    op = M.Op(
        M.WRITE, "a.txt", expect=M.ABSENT, hash=h(b"other"), size=5, source=M.SRC_DATA, blob=(0, 5)
    )
    [r] = store.apply([op], b"hello")
    assert not r.ok and not (src(store) / "a.txt").exists()


def test_a_file_changed_here_is_kept_in_conflicts_before_replacement(store):
    store.apply([write("a.txt", b"v1")], b"v1")
    (src(store) / "a.txt").write_bytes(b"edited on the robot")
    [r] = store.apply([write("a.txt", b"v2", expect=M.expect_file(h(b"v1")))], b"v2")
    assert r.ok and r.preserved
    assert (src(store) / "a.txt").read_bytes() == b"v2"
    assert (Path(store.workspace) / r.preserved).read_bytes() == b"edited on the robot"


def test_refuse_policy_leaves_the_robot_version(store):
    store.apply([write("a.txt", b"v1")], b"v1")
    (src(store) / "a.txt").write_bytes(b"edited")
    [r] = store.apply(
        [write("a.txt", b"v2", expect=M.expect_file(h(b"v1")))], b"v2", policy="refuse"
    )
    assert r.code == M.CONFLICT and (src(store) / "a.txt").read_bytes() == b"edited"


def test_deleted_files_go_to_a_bounded_trash(store):
    for i in range(TRASH_KEEP_BATCHES + 5):
        data = b"gen %d" % i
        store.apply([write("x.txt", data)], data)
        store.apply([M.Op(M.DELETE, "x.txt", expect=M.expect_file(h(data)))], b"")
    batches = list((Path(store.meta) / "trash").iterdir())
    assert len(batches) == TRASH_KEEP_BATCHES
    assert not (src(store) / "x.txt").exists()


def test_files_edited_here_inside_a_deleted_directory_are_kept_apart_from_the_trash(store):
    store.apply([M.Op(M.MKDIR, "d", expect=M.ABSENT, mode=0o755), write("d/a", b"a")], b"a")
    (src(store) / "d" / "a").write_bytes(b"robot work")
    [r] = store.apply([M.Op(M.DELETE, "d", expect=M.IS_DIR)], b"")
    assert r.ok and not (src(store) / "d").exists()
    kept = list((Path(store.meta) / "conflicts").rglob("a"))
    assert [k.read_bytes() for k in kept] == [b"robot work"]


def test_no_write_through_a_symlinked_directory(store, tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    os.symlink(outside, src(store) / "link")
    [r] = store.apply([write("link/evil", b"x")], b"x")
    assert r.code == M.PATH_ERROR and not (outside / "evil").exists()


@pytest.mark.parametrize("path", ["../escape", "/etc/passwd", "a/../../b"])
def test_paths_out_of_the_root_are_protocol_errors(store, path):
    with pytest.raises(ProtocolError):
        M.Op.from_wire(
            {"k": "write", "p": path, "e": "-", "h": "00", "s": 1, "src": "data", "bl": [0, 1]}
        )


def test_delta_against_the_wrong_base_is_a_base_mismatch(store):
    store.apply([write("a.txt", b"v1")], b"v1")
    op = M.Op(
        M.WRITE,
        "a.txt",
        expect=M.expect_file(h(b"v1")),
        hash=h(b"v2"),
        size=2,
        source=M.SRC_DELTA,
        base=h(b"not v1"),
        blob=(0, 0),
    )
    [r] = store.apply([op], b"")
    assert r.code == M.BASE_MISMATCH and (src(store) / "a.txt").read_bytes() == b"v1"


def test_copy_reuses_content_held_here(store):
    store.apply([write("a.txt", b"payload")], b"payload")
    op = M.Op(
        M.WRITE,
        "b.txt",
        expect=M.ABSENT,
        hash=h(b"payload"),
        size=7,
        source=M.SRC_COPY,
        base=h(b"payload"),
        from_path="a.txt",
    )
    [r] = store.apply([op], b"")
    assert r.ok and (src(store) / "b.txt").read_bytes() == b"payload"


def test_compressed_part_is_inflated_once_and_addressed(store):
    data = b"text " * 1000
    zpart = zlib.compress(data)
    op = write("z.txt", data).but(z=1)
    [r] = store.apply([op], zpart, zpart=[len(zpart), len(data)])
    assert r.ok and (src(store) / "z.txt").read_bytes() == data


@pytest.mark.parametrize("zpart", [[10**9, 5], [0, wire.MAX_BODY + 1], "x", [1]])
def test_bad_compressed_part_references_are_refused(store, zpart):
    with pytest.raises(ProtocolError):
        store.apply([], b"abc", zpart=zpart)


def test_an_interrupted_batch_is_cleaned_up_by_the_next_writer_only(tmp_path):
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()  # a writer mid-batch
    tmp = Path(s.root) / ".x.fetchsync-tmp-abcdef012345"
    tmp.write_bytes(b"half")
    (Path(s.meta) / "batch-in-progress").write_bytes(b"")
    other = Store(str(tmp_path / "ws"), algorithm=ALG)
    assert tmp.exists()  # opening must not take a live batch's temporaries away
    s.unlock()  # ... and it dies without cleaning up
    other.lock()
    assert not tmp.exists() and not (Path(s.meta) / "batch-in-progress").exists()
    other.unlock()


def test_drift_reports_edits_made_here_since_the_last_sync(store):
    store.apply([write("a.txt", b"v1"), write("b.txt", b"b", at=2)], b"v1b")
    (src(store) / "a.txt").write_bytes(b"robot edit")
    (src(store) / "b.txt").unlink()
    (src(store) / "new.txt").write_bytes(b"new")
    changed, gone = store.drift()
    assert sorted(c.path for c in changed) == ["a.txt", "new.txt"]
    assert gone == ["b.txt"]


def test_pack_skips_incompressible_data():
    data, z = wire.pack(os.urandom(100000))
    assert not z
    data, z = wire.pack(b"abc" * 100000)
    assert z and zlib.decompress(data) == b"abc" * 100000


def test_a_rename_copies_before_the_source_is_deleted(store):
    # a copy runs in a writer thread; the delete of its source later in the
    # same batch must wait for it (a rename, as the planner emits it)
    data = os.urandom(3 * 1024 * 1024)
    store.apply([write("old.bin", data)], data)
    for i in range(20):
        new, old = f"new{i}.bin", ("old.bin" if i == 0 else f"new{i - 1}.bin")
        copy = M.Op(
            M.WRITE,
            new,
            expect=M.ABSENT,
            hash=h(data),
            size=len(data),
            source=M.SRC_COPY,
            base=h(data),
            from_path=old,
        )
        results = store.apply([copy, M.Op(M.DELETE, old, expect=M.expect_file(h(data)))], b"")
        assert [r.code for r in results] == [M.OK, M.OK]
        assert (src(store) / new).read_bytes() == data and not (src(store) / old).exists()


def test_names_reserved_for_temporaries_are_refused(store):
    [r] = store.apply([write(".x.fetchsync-tmp-abc", b"x")], b"x")
    assert r.code == M.PATH_ERROR and not list(src(store).iterdir())


@pytest.mark.parametrize("damage", [b"", b"\x00garbage", None])
def test_a_damaged_index_costs_a_new_epoch_not_the_files(tmp_path, damage):
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    s.apply([write("a.txt", b"v1")], b"v1")
    s.save_index()
    s.unlock()
    index = Path(s.meta) / "index"
    if damage is None:  # a valid marshal stream of the wrong shape
        import marshal

        index.write_bytes(marshal.dumps({"v": 2, "algorithm": ALG, "synced": [], "cache": {}}))
    else:
        index.write_bytes(damage)
    again = Store(str(tmp_path / "ws"), algorithm=ALG)
    assert again.epoch != s.epoch and again.synced == {}
    assert (src(again) / "a.txt").read_bytes() == b"v1"


def test_the_index_survives_a_reopen_and_an_old_format_is_dropped(tmp_path):
    meta = tmp_path / "ws" / ".fetchsync"
    meta.mkdir(parents=True)
    (meta / "index.json").write_text("{}")
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    s.apply([write("caf\udce9.txt", b"v1")], b"v1")
    s.save_index()
    s.unlock()
    again = Store(str(tmp_path / "ws"), algorithm=ALG)
    assert (again.epoch, again.gen) == (s.epoch, s.gen)
    assert again.synced == s.synced and "caf\udce9.txt" in again.synced
    assert not (meta / "index.json").exists()


def _reopened(s: Store) -> Store:
    return Store(s.workspace, algorithm=ALG)


def _index_of(s: Store) -> tuple:
    return (s.epoch, s.gen, s.synced, s.cache, s.trash_log)


def test_each_save_appends_a_record_and_a_reopen_replays_them(tmp_path):
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    s.apply([write("a.txt", b"v1")], b"v1")
    s.save_index()  # the first save writes the snapshot
    snapshot = (Path(s.meta) / "index").read_bytes()
    for i in range(5):
        data = b"v%d" % (i + 2)
        s.apply(
            [
                write("a.txt", data, expect=M.expect_file(h(b"v%d" % (i + 1)))),
                write(f"f{i}.txt", data),
            ],
            data + data,
        )
        s.save_index()
    s.apply([M.Op(M.DELETE, "f0.txt", expect=M.expect_file(h(b"v2")))], b"")
    s.save_index()
    s.unlock()
    assert (Path(s.meta) / "index").read_bytes() == snapshot  # only the journal grew
    assert (Path(s.meta) / "index.log").stat().st_size > 0
    again = _reopened(s)
    assert _index_of(again) == _index_of(s)
    assert "f0.txt" not in again.synced and again.synced["a.txt"][2] == h(b"v6")


def test_a_torn_journal_record_is_ignored_and_the_next_save_writes_a_snapshot(tmp_path):
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    s.apply([write("a.txt", b"v1")], b"v1")
    s.save_index()
    s.apply([write("b.txt", b"b")], b"b")
    s.save_index()
    s.unlock()
    before = _index_of(_reopened(s))
    with open(Path(s.meta) / "index.log", "ab") as fh:
        fh.write(b"\x00\x00\x01\x00garbage")  # a crash mid-append
    torn = _reopened(s)
    assert _index_of(torn) == before
    torn.lock()
    torn.apply([write("c.txt", b"c")], b"c")
    torn.save_index()
    torn.unlock()
    assert (Path(s.meta) / "index.log").stat().st_size == 0  # folded into a new snapshot
    assert _index_of(_reopened(torn)) == _index_of(torn) and "c.txt" in torn.synced


def test_a_journal_of_another_snapshot_is_never_applied(tmp_path, monkeypatch):

    monkeypatch.setattr(store_mod, "JOURNAL_MIN", 0)  # every save past the first: a snapshot
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    s.apply([write("a.txt", b"v1")], b"v1")
    s.save_index()
    old_log = Path(s.meta) / "index.log"
    s.apply([write("b.txt", b"b")], b"b")
    s.save_index()  # appends (the journal was empty)
    stale = old_log.read_bytes()
    s.apply([write("c.txt", b"c")], b"c")
    s.save_index()  # the journal outgrew the limit: a new snapshot
    s.unlock()
    assert old_log.stat().st_size == 0
    old_log.write_bytes(stale)  # as if a crash left the old journal beside the new snapshot
    again = _reopened(s)
    assert _index_of(again) == _index_of(s)


def test_another_writers_saves_are_seen_when_the_lock_is_taken(tmp_path):
    a = Store(str(tmp_path / "ws"), algorithm=ALG)
    b = Store(str(tmp_path / "ws"), algorithm=ALG)
    a.lock()
    a.apply([write("a.txt", b"v1")], b"v1")
    a.save_index()
    a.unlock()
    b.lock()
    assert "a.txt" in b.synced and b.gen == a.gen
    b.apply([write("b.txt", b"b")], b"b")
    b.save_index()
    b.unlock()
    a.lock()
    assert "b.txt" in a.synced and a.gen == b.gen
    a.unlock()


def test_a_rename_that_fails_at_commit_leaves_no_temporary(store):
    # found by the fuzzer: a symlink written, then a directory made at the same path
    # in the same batch; the symlink's rename into place fails at commit
    ops = [
        M.Op(M.SYMLINK, "b", expect=M.ABSENT, target="a"),
        M.Op(M.MKDIR, "b", expect=M.ABSENT, mode=0o755),
    ]
    results = store.apply(ops, b"")
    # the directory stood where the symlink goes at commit: it fails, or the directory is kept
    assert len(results) == 2 and (not results[0].ok or results[0].preserved)
    assert (src(store) / "b").is_dir() or (Path(store.workspace) / results[0].preserved).is_dir()
    assert not [n for _d, _s, files in os.walk(store.root) for n in files if ".fetchsync-tmp-" in n]


@pytest.fixture
def umask(monkeypatch):
    """Set this process's umask for the test (the store reads it once per process)."""
    old = os.umask(0o022)
    os.umask(old)

    def set_umask(mask: int) -> None:
        os.umask(mask)
        monkeypatch.setattr(store_mod, "_UMASK", -1)

    yield set_umask
    os.umask(old)


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o000])
@pytest.mark.parametrize("mode", [0o644, 0o600, 0o755, 0o666, 0o4755])
def test_files_and_directories_get_the_mode_asked_whatever_the_umask(store, umask, mask, mode):
    umask(mask)
    dir_mode = mode & 0o777 | 0o700
    ops = [
        M.Op(M.MKDIR, "d", expect=M.ABSENT, mode=dir_mode),
        M.Op(
            M.WRITE,
            "d/f",
            expect=M.ABSENT,
            mode=mode,
            hash=h(b"x"),
            size=1,
            source=M.SRC_DATA,
            blob=(0, 1),
        ),
    ]
    results = store.apply(ops, b"x")
    assert all(r.ok for r in results)
    assert os.lstat(src(store) / "d").st_mode & 0o7777 == dir_mode
    assert os.lstat(src(store) / "d" / "f").st_mode & 0o7777 == mode
    assert [M.Listed.from_wire(r.written).mode for r in results] == [dir_mode, mode]


def test_a_directory_made_in_a_setgid_one_has_the_mode_asked(store):
    os.chmod(src(store), 0o2755)  # new directories inherit the setgid bit
    [r] = store.apply([M.Op(M.MKDIR, "d", expect=M.ABSENT, mode=0o755)], b"")
    assert r.ok and os.lstat(src(store) / "d").st_mode & 0o7777 == 0o755
    assert M.Listed.from_wire(r.written).mode == 0o755


def test_results_done_as_asked_travel_as_one_number(store):
    """An answer spells out only what differs from what the operation asked: a file,
    directory or link made exactly as asked is AS_ASKED on the wire, and reads back as
    the full result with the operation in hand."""
    store.apply([write("old.txt", b"v1"), write("c.txt", b"c", at=2)], b"v1c")
    (src(store) / "old.txt").write_bytes(b"edited on the robot")
    ops = [
        M.Op(M.MKDIR, "d", expect=M.ABSENT, mode=0o750),
        write("d/f", b"data"),
        M.Op(M.SYMLINK, "d/l", expect=M.ABSENT, target="f"),
        M.Op(M.CHMOD, "c.txt", expect=M.expect_file(h(b"c")), mode=0o600),
        write("old.txt", b"v2", expect=M.expect_file(h(b"v1")), at=4),
    ]
    results = store.apply(ops, b"datav2")
    assert all(r.ok for r in results)
    wire_form = [r.to_wire(op) for r, op in zip(results, ops)]
    assert wire_form[:3] == [M.AS_ASKED] * 3
    assert wire_form[3]["c"] == M.OK and wire_form[3]["w"][2] == 0o600  # a chmod does not say
    assert wire_form[4]["pv"] == results[4].preserved  # a kept conflict is spelled out
    assert [M.Result.from_wire(w, op) for w, op in zip(wire_form, ops)] == results
    assert results[0].to_wire() == {"c": M.OK, "w": ["d", "d", 0o750, 0, ""]}  # no op: in full


def test_a_result_that_differs_from_what_was_asked_is_spelled_out(store):
    op = write("f", b"data")
    other_mode = M.Result(M.OK, written=["f", "f", 0o755, 4, h(b"data")])
    assert other_mode.to_wire(op) == {"c": M.OK, "w": ["f", "f", 0o755, 4, h(b"data")]}
    with pytest.raises(ProtocolError):
        M.Result.from_wire(M.AS_ASKED, M.Op(M.CHMOD, "f", expect=M.ABSENT, mode=0o600))
    with pytest.raises(ProtocolError):
        M.Result.from_wire(M.AS_ASKED)
    with pytest.raises(ProtocolError):
        M.Result.from_wire(True, op)  # JSON true is not the number 0


def test_large_files_land_whole_with_their_modes(store):
    big1, big2 = os.urandom(LARGE), os.urandom(LARGE + 12345)
    small = b"small\n"
    blob = big1 + small + big2
    ops = [
        write("a/big1.bin", big1),
        write("a/small.txt", small, at=len(big1)),
        M.Op(
            M.WRITE,
            "a/run.sh",
            expect=M.ABSENT,
            mode=0o4755,
            hash=h(big2),
            size=len(big2),
            source=M.SRC_DATA,
            blob=(len(big1) + len(small), len(big2)),
        ),
    ]
    results = store.apply([M.Op(M.MKDIR, "a", expect=M.ABSENT, mode=0o755)] + ops, blob)
    assert [r.code for r in results] == [M.OK] * 4
    root = src(store)
    assert (root / "a/big1.bin").read_bytes() == big1 and (
        root / "a/small.txt"
    ).read_bytes() == small
    assert (root / "a/run.sh").read_bytes() == big2
    assert os.stat(root / "a/run.sh").st_mode & 0o7777 == 0o4755  # past the umask, by fchmod
    assert not [p for p in root.rglob("*") if "fetchsync-tmp" in p.name]


@pytest.fixture
def tiny_store(tmp_path: Path):
    """A store on a 1 MiB tmpfs (root only)."""
    import subprocess

    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    where = tmp_path / "tiny"
    where.mkdir()
    if (
        subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(where)], capture_output=True
        ).returncode
        != 0
    ):
        pytest.skip("cannot mount a tmpfs here")
    s = Store(str(where / "ws"), algorithm=ALG)
    s.lock()
    yield s
    s.unlock()
    subprocess.run(["umount", "-l", str(where)], check=False)


def test_a_large_write_that_fails_fails_its_operation_only(tiny_store):
    big1, big2 = os.urandom(LARGE + 1000), os.urandom(LARGE + 2000)
    small = b"still written\n"
    blob = big1 + big2 + small
    results = tiny_store.apply(
        [
            write("big1.bin", big1),
            write("big2.bin", big2, at=len(big1)),
            write("small.txt", small, at=len(big1) + len(big2)),
        ],
        blob,
    )
    assert [r.code for r in results] == [M.OK, M.NO_SPACE, M.OK]
    assert "big2.bin" in results[1].message
    root = src(tiny_store)
    assert (root / "big1.bin").read_bytes() == big1 and (root / "small.txt").read_bytes() == small
    assert not (root / "big2.bin").exists()
    assert not [p for p in root.rglob("*") if "fetchsync-tmp" in p.name]


def test_a_workspace_deleted_between_requests_is_made_again(tmp_path):
    """The descriptors are opened afresh for each request: a workspace deleted under a
    long-lived endpoint (a watch, a connection master's) is made again, with a new epoch,
    never written through a stale descriptor into the deleted directory."""
    import shutil

    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    assert s.apply([write("a", b"a")], b"a")[0].ok
    s.save_index()
    epoch = s.epoch
    s.unlock()
    shutil.rmtree(tmp_path / "ws")
    s.lock()
    assert s.apply([write("b", b"b")], b"b")[0].ok
    s.unlock()
    assert (tmp_path / "ws" / "src" / "b").read_bytes() == b"b" and s.epoch != epoch
