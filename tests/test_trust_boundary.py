"""The endpoint's trust boundary: nothing is ever written outside ``src/`` and
``.fetchsync/``, whatever a robot-side process does to the tree meanwhile (issue 22,
item 9), and a replacement never destroys the robot's version (items 1, 2, 3)."""

from __future__ import annotations

import os
import subprocess
import threading
from pathlib import Path

import pytest
from endpoint_client import ALG, Endpoint
from helpers import fetchsync, local_env, ssh_env

from fetchsync.protocol import hashing
from fetchsync.protocol import messages as M
from fetchsync.protocol.store import Store, StoreError


def h(data: bytes) -> str:
    return hashing.digest(ALG, data).hex()


def write(
    path: str, data: bytes, *, expect: str = M.ABSENT, at: int = 0, mode: int = 0o644
) -> M.Op:
    return M.Op(
        M.WRITE,
        path,
        expect=expect,
        mode=mode,
        hash=h(data),
        size=len(data),
        source=M.SRC_DATA,
        blob=(at, len(data)),
    )


def mkdir(path: str) -> M.Op:
    return M.Op(M.MKDIR, path, expect=M.ABSENT, mode=0o755)


def snapshot(top: Path) -> dict[str, bytes | str]:
    """Everything under ``top``: file contents, link targets, directories."""
    out: dict[str, bytes | str] = {}
    for dirpath, dirs, files in os.walk(top):
        for name in dirs + files:
            full = Path(dirpath) / name
            rel = str(full.relative_to(top))
            out[rel] = (
                os.readlink(full)
                if full.is_symlink()
                else "dir"
                if full.is_dir()
                else full.read_bytes()
            )
    return out


@pytest.fixture
def store(tmp_path: Path):
    s = Store(str(tmp_path / "ws"), algorithm=ALG)
    s.lock()
    yield s
    s.unlock()


@pytest.fixture
def ssh_dir(tmp_path: Path) -> Path:
    """A stand-in for the robot user's ~/.ssh, outside the workspace."""
    d = tmp_path / "home" / ".ssh"
    d.mkdir(parents=True)
    (d / "authorized_keys").write_bytes(b"ssh-ed25519 AAAA the-real-key\n")
    return d


# ------------------------------------------------------------------ deterministic
def test_a_package_swapped_for_a_symlink_to_ssh_between_saves_is_refused(store, ssh_dir):
    """The authorized_keys scenario: one endpoint (a watch's, hours long) writes into
    ``src/pkg``; someone replaces ``src/pkg`` with a symlink to ``~/.ssh``; the next save
    of ``pkg/authorized_keys`` must not reach ``~/.ssh`` (the old endpoint had cached
    that ``pkg`` was a directory, and overwrote the keys)."""
    before = snapshot(ssh_dir)
    assert all(
        r.ok for r in store.apply([mkdir("pkg"), write("pkg/authorized_keys", b"v1")], b"v1")
    )
    store.unlock()
    root = Path(store.root)
    os.rename(root / "pkg", root / "pkg.moved")
    os.symlink(ssh_dir, root / "pkg")
    store.lock()
    ops = [
        write("pkg/authorized_keys", b"attacker", expect=M.expect_file(h(b"v1"))),
        write("pkg/new", b"attacker", at=0),
        mkdir("pkg/sub"),
        M.Op(M.SYMLINK, "pkg/l", expect=M.ABSENT, target="/etc"),
        M.Op(M.CHMOD, "pkg/authorized_keys", expect=M.expect_file(h(b"v1")), mode=0o777),
        M.Op(M.DELETE, "pkg/authorized_keys", expect=M.expect_file(h(b"v1"))),
    ]
    results = store.apply(ops, b"attacker")
    assert [r.code for r in results] == [M.PATH_ERROR] * len(ops)
    assert all("symlink" in r.message for r in results)
    assert snapshot(ssh_dir) == before
    assert os.stat(ssh_dir / "authorized_keys").st_mode & 0o777 != 0o777


@pytest.mark.parametrize("what", ["src", ".fetchsync"])
def test_a_symlinked_src_or_fetchsync_is_refused_with_a_clear_error(tmp_path, what):
    outside = tmp_path / "outside"
    outside.mkdir()
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / ("src" if what == ".fetchsync" else ".fetchsync")).mkdir()
    os.symlink(outside, ws / what)
    with pytest.raises(StoreError, match="symlink"):
        s = Store(str(ws), algorithm=ALG)
        s.lock()
    assert list(outside.iterdir()) == []


@pytest.mark.parametrize("where", ["trash", "conflicts", "tmp"])
def test_a_symlinked_trash_conflicts_or_tmp_is_never_followed(store, tmp_path, where):
    """A per-file error, and nothing written where the symlink points."""
    outside = tmp_path / "outside"
    outside.mkdir()
    assert store.apply([write("a", b"v1"), write("b", b"v1")], b"v1")[0].ok
    meta = Path(store.meta)
    if (meta / where).exists():
        import shutil

        shutil.rmtree(meta / where)
    os.symlink(outside, meta / where)
    (Path(store.root) / "a").write_bytes(b"edited on the robot")
    if where == "tmp":
        [r] = store.apply([M.Op(M.UPLOAD, "", upload="u1", size=0, blob=(0, 4))], b"data")
    elif where == "trash":
        [r] = store.apply([M.Op(M.DELETE, "b", expect=M.expect_file(h(b"v1")))], b"")
        assert (Path(store.root) / "b").read_bytes() == b"v1"
    else:
        [r] = store.apply([write("a", b"v2", expect=M.expect_file(h(b"v1")))], b"v2")
        assert (Path(store.root) / "a").read_bytes() == b"edited on the robot"  # kept in place
    assert not r.ok and "symlink" in r.message
    assert list(outside.iterdir()) == []


# ------------------------------------------------------------------ races
def _swapper(root: Path, name: str, outside: Path, stop: threading.Event, swaps: list[int]) -> None:
    """Swap ``root/name`` for a symlink to ``outside`` and back, in a loop."""
    real = root / (name + ".real")
    while not stop.is_set():
        try:
            os.rename(root / name, real)
            os.symlink(outside, root / name)
            swaps[0] += 1
            os.unlink(root / name)
            os.rename(real, root / name)
        except OSError:
            try:  # the endpoint made the directory again meanwhile: start over
                if (root / name).is_symlink():
                    os.unlink(root / name)
            except OSError:
                pass


def test_a_directory_swapped_for_a_symlink_in_a_loop_never_redirects_a_write(store, tmp_path):
    """The race harness, at the store: batches of every kind of operation under
    ``pkg/`` while another thread swaps ``pkg`` for a symlink to an outside directory
    and back as fast as it can. Nothing may ever appear or change outside."""
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep.txt").write_bytes(b"outside\n")
    before = snapshot(outside)
    assert store.apply([mkdir("pkg")], b"")[0].ok
    stop, swaps = threading.Event(), [0]
    t = threading.Thread(target=_swapper, args=(Path(store.root), "pkg", outside, stop, swaps))
    t.start()
    try:
        for i in range(150):
            data = b"round %d\n" % i
            ops = [
                write("pkg/f%d" % (i % 7), data, expect=M.ABSENT),
                mkdir("pkg/d%d" % i),
                write("pkg/d%d/x" % i, data),
                M.Op(M.SYMLINK, "pkg/l%d" % i, expect=M.ABSENT, target="x"),
                M.Op(M.CHMOD, "pkg/f%d" % (i % 7), expect=M.expect_file(h(data)), mode=0o600),
                M.Op(M.DELETE, "pkg/l%d" % i, expect=M.expect_link("x")),
            ]
            store.apply(ops, data)
    finally:
        stop.set()
        t.join()
    assert swaps[0] > 10
    assert snapshot(outside) == before


def _push_race(env: dict, robot_src: Path, outside: Path) -> None:
    local = Path(env["FETCHSYNC_WORKSPACE"]) / "src" / "my_pkg" / "many"
    local.mkdir()
    for i in range(120):
        (local / f"f{i}.txt").write_text(f"{i}\n")
    fetchsync("push", env=env)
    before = snapshot(outside)
    stop, swaps = threading.Event(), [0]
    t = threading.Thread(target=_swapper, args=(robot_src / "my_pkg", "many", outside, stop, swaps))
    t.start()
    try:
        for round_ in range(4):
            for i in range(120):
                (local / f"f{i}.txt").write_text(f"{i} round {round_}\n")
            (local / f"new{round_}").mkdir()
            (local / f"new{round_}" / "x").write_text("x\n")
            fetchsync("push", env=env, check=False)
    finally:
        stop.set()
        t.join()
    assert swaps[0] > 0
    assert snapshot(outside) == before


@pytest.mark.slow
def test_pushes_through_the_local_robot_never_write_outside_src_under_a_swap_race(tmp_path):
    robot_home = tmp_path / "robot-home"
    outside = robot_home / ".ssh"
    outside.mkdir(parents=True)
    (outside / "authorized_keys").write_text("the real key\n")
    env = local_env(tmp_path, XDG_STATE_HOME=str(tmp_path / "st"))
    _push_race(env, robot_home / "robot_ws" / "src", outside)


@pytest.mark.slow
@pytest.mark.ssh
def test_pushes_over_ssh_never_write_outside_src_under_a_swap_race(ssh_home, remote_dir, tmp_path):
    outside = tmp_path / "outside-ssh"
    outside.mkdir()
    (outside / "authorized_keys").write_text("the real key\n")
    env = ssh_env(ssh_home.home, remote_dir, tmp_path)
    _push_race(env, remote_dir / "src", outside)


def test_a_symlinked_fetchsync_fails_a_push_with_one_line(tmp_path):
    robot_home = tmp_path / "robot-home"
    outside = tmp_path / "outside"
    outside.mkdir()
    (robot_home / "robot_ws" / "src").mkdir(parents=True)
    os.symlink(outside, robot_home / "robot_ws" / ".fetchsync")
    env = local_env(tmp_path, XDG_STATE_HOME=str(tmp_path / "st"))
    proc = fetchsync("push", env=env, check=False)
    assert proc.returncode != 0
    err = proc.stderr.decode()
    assert ".fetchsync is a symlink" in err and "Traceback" not in err
    assert list(outside.iterdir()) == []


# ------------------------------------------------------------------ replacing never destroys
def test_a_chmod_after_a_robot_side_edit_keeps_the_edit(store):
    """Item 1: the laptop only chmods a file the robot edited: the robot's content is
    kept in conflicts/ at once (whatever the laptop sends next), nothing is changed in
    place, and the result says so (BASE_MISMATCH: send it whole; preserved: counted)."""
    assert store.apply([write("run.sh", b"v1")], b"v1")[0].ok
    path = Path(store.root) / "run.sh"
    path.write_bytes(b"fixed on the robot\n")
    [r] = store.apply([M.Op(M.CHMOD, "run.sh", expect=M.expect_file(h(b"v1")), mode=0o755)], b"")
    assert r.code == M.BASE_MISMATCH and r.preserved
    assert (Path(store.workspace) / r.preserved).read_bytes() == b"fixed on the robot\n"
    assert path.read_bytes() == b"fixed on the robot\n" and path.stat().st_mode & 0o777 == 0o644
    # the laptop's next round sends it whole, even against what it now knows: the edit stays kept
    [r2] = store.apply(
        [write("run.sh", b"v1", expect=M.expect_file(h(b"fixed on the robot\n")), mode=0o755)],
        b"v1",
    )
    assert r2.ok and path.read_bytes() == b"v1"
    assert (Path(store.workspace) / r.preserved).read_bytes() == b"fixed on the robot\n"


def test_a_chmod_with_the_refuse_policy_is_refused(store):
    assert store.apply([write("run.sh", b"v1")], b"v1")[0].ok
    (Path(store.root) / "run.sh").write_bytes(b"edited")
    [r] = store.apply(
        [M.Op(M.CHMOD, "run.sh", expect=M.expect_file(h(b"v1")), mode=0o755)], b"", policy="refuse"
    )
    assert r.code == M.CONFLICT and (Path(store.root) / "run.sh").stat().st_mode & 0o777 == 0o644


def test_a_robot_file_in_a_directory_the_push_just_made_is_kept(store):
    """Item 3: a later batch of the same push writes into a directory its first batch
    made; a file the robot put there meanwhile is kept, not overwritten."""
    assert store.apply([mkdir("new"), mkdir("new/sub")], b"")[0].ok
    (Path(store.root) / "new" / "sub" / "a.txt").write_bytes(b"written on the robot\n")
    [r] = store.apply([write("new/sub/a.txt", b"from the laptop")], b"from the laptop")
    assert r.ok and r.preserved
    assert (Path(store.workspace) / r.preserved).read_bytes() == b"written on the robot\n"


@pytest.fixture
def tiny(tmp_path: Path):
    """A 1 MiB tmpfs (root only) for a full disk."""
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
    yield where
    subprocess.run(["umount", "-l", str(where)], check=False)


def test_a_full_disk_during_a_conflict_leaves_the_robots_version_in_place(tiny):
    """Item 2: the robot edited a file, the laptop's new version does not fit: the
    robot's version stays where it is (and is not reported kept elsewhere)."""
    s = Store(str(tiny / "ws"), algorithm=ALG)
    s.lock()
    assert s.apply([write("a.txt", b"v1")], b"v1")[0].ok
    (Path(s.root) / "a.txt").write_bytes(b"edited on the robot\n")
    big = os.urandom(2 * 1024 * 1024)
    [r] = s.apply([write("a.txt", big, expect=M.expect_file(h(b"v1")))], big)
    assert r.code == M.NO_SPACE and not r.preserved
    assert (Path(s.root) / "a.txt").read_bytes() == b"edited on the robot\n"
    # a replacement that fits afterwards keeps it, and says where
    [r] = s.apply([write("a.txt", b"v2", expect=M.expect_file(h(b"v1")))], b"v2")
    assert r.ok and r.preserved
    assert (Path(s.workspace) / r.preserved).read_bytes() == b"edited on the robot\n"
    s.unlock()


def test_a_replacement_whose_rename_fails_puts_the_directory_back(store, monkeypatch):
    """A directory replaced by a file goes to the trash only for the rename; when the
    rename fails, it is put back where it was."""
    assert all(r.ok for r in store.apply([mkdir("d"), write("d/x", b"x")], b"x"))
    real = os.rename

    def rename(a, b, *, src_dir_fd=None, dst_dir_fd=None):  # type: ignore[no-untyped-def]
        if ".fetchsync-tmp-" in str(a) and b == "d":
            raise OSError(28, "No space left on device")
        return real(a, b, src_dir_fd=src_dir_fd, dst_dir_fd=dst_dir_fd)

    monkeypatch.setattr(os, "rename", rename)
    [r] = store.apply([write("d", b"now a file", expect=M.IS_DIR)], b"now a file")
    assert r.code == M.NO_SPACE
    assert (Path(store.root) / "d" / "x").read_bytes() == b"x"
    assert not [p for p in Path(store.root).iterdir() if ".fetchsync-tmp-" in p.name]


# ------------------------------------------------------------------ read-only opens
@pytest.fixture
def readonly_ws(tmp_path: Path):
    """A workspace with a file, on a read-only mount (root ignores mode bits)."""
    if os.geteuid() != 0:
        pytest.skip("mounting needs root")
    where = tmp_path / "ro"
    where.mkdir()
    if (
        subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(where)], capture_output=True
        ).returncode
        != 0
    ):
        pytest.skip("cannot mount a tmpfs here")
    (where / "ws" / "src" / "pkg").mkdir(parents=True)
    (where / "ws" / "src" / "pkg" / "a.txt").write_bytes(b"hello\n")
    subprocess.run(["mount", "-o", "remount,ro", str(where)], check=True)
    yield where / "ws"
    subprocess.run(["umount", "-l", str(where)], check=False)


def test_a_readonly_open_lists_and_reads_a_readonly_workspace_and_writes_nothing(
    readonly_ws, tmp_path
):
    home = tmp_path / "home"
    home.mkdir()
    with Endpoint(str(home)) as ep:
        # a writing open fails on a read-only file system...
        f = ep.request({"op": "open", "workspace": str(readonly_ws)})
        assert f.type == 3 and "not writable" in f.header["error"]
        # ...a read-only one works: listing, reads, signatures
        f = ep.request({"op": "open", "workspace": str(readonly_ws), "readonly": True})
        assert f.type == 2 and f.header["readonly"] is True
        f = ep.request({"op": "list"})
        assert f.type == 2 and [e[0] for e in f.header["entries"]] == ["pkg", "pkg/a.txt"]
        f = ep.request({"op": "read", "items": [{"p": "pkg/a.txt"}]})
        assert f.type == 2 and f.blob == b"hello\n"
        f = ep.request({"op": "sigs", "items": [{"p": "pkg/a.txt"}]})
        assert f.type == 2 and f.header["items"][0]["h"] == h(b"hello\n")
        # every change is refused
        op = write("pkg/b.txt", b"x").to_wire()
        f = ep.request({"op": "sync", "ops": [op]}, b"x")
        assert f.type == 3 and "read-only" in f.header["error"]
        f = ep.request({"op": "adopt", "entries": []})
        assert f.type == 3 and "read-only" in f.header["error"]
    assert sorted(os.listdir(readonly_ws)) == ["src"]


def test_a_readonly_open_creates_nothing(tmp_path):
    """No workspace, no .fetchsync, no lock, no index: on a writable robot too."""
    home = tmp_path / "home"
    home.mkdir()
    ws = tmp_path / "ws"
    with Endpoint(str(home)) as ep:
        f = ep.request({"op": "open", "workspace": str(ws), "readonly": True})
        assert f.type == 3 and "does not exist" in f.header["error"]
        (ws / "src").mkdir(parents=True)
        (ws / "src" / "f").write_bytes(b"f\n")
        f = ep.request({"op": "open", "workspace": str(ws), "readonly": True})
        assert f.type == 2
        f = ep.request({"op": "list"})
        assert f.type == 2 and [e[0] for e in f.header["entries"]] == ["f"]
        f = ep.request(
            {"op": "list", "mode": "drift", "epoch": f.header["epoch"], "gen": f.header["gen"]}
        )
        assert f.type == 2
    assert sorted(os.listdir(ws)) == ["src"]
    assert sorted(os.listdir(ws / "src")) == ["f"]


@pytest.mark.parametrize("edit", ["in place", "replaced", "created"])
def test_a_robot_edit_between_the_check_and_the_rename_is_kept(store, monkeypatch, edit):
    """The check before a replacement and the rename are two system calls: a robot-side
    edit made between them is not lost (renameat2: the new version is exchanged in and
    the old one kept when it is not the one checked; over nothing, no replacing)."""
    from fetchsync.protocol import store as store_mod

    assert store.apply([write("a.txt", b"v1")], b"v1")[0].ok
    path = Path(store.root) / "a.txt"
    if edit == "created":
        path.unlink()
        store.apply([], b"")
    real = store_mod.Store._at
    armed = [True]

    def at(self, p, dir_fd, name):  # type: ignore[no-untyped-def]
        got = real(self, p, dir_fd, name)
        if p == "a.txt" and armed[0]:
            armed[0] = False
            if edit == "in place":
                with open(path, "r+b") as fh:
                    fh.write(b"edited on the robot, in the window\n")
            else:
                tmp = path.with_name("x")
                tmp.write_bytes(b"edited on the robot, in the window\n")
                os.rename(tmp, path)
        return got

    monkeypatch.setattr(store_mod.Store, "_at", at)
    expect = M.ABSENT if edit == "created" else M.expect_file(h(b"v1"))
    [r] = store.apply([write("a.txt", b"v2", expect=expect)], b"v2")
    monkeypatch.setattr(store_mod.Store, "_at", real)
    kept = [p.read_bytes() for p in Path(store.meta).rglob("a.txt")] + [path.read_bytes()]
    assert b"edited on the robot, in the window\n" in kept, (r, kept)
    assert not [p for p in Path(store.root).iterdir() if ".fetchsync-tmp-" in p.name]
    if r.ok:
        assert path.read_bytes() == b"v2" and r.preserved
