"""The mass-deletion guard whatever the batching: it counts the robot's files a push
removes, not the paths the watcher happened to name.

On a busy machine the watcher reports an ``rm -rf`` in pieces: a first batch may name a
few of the files only, while the scan made for it finds their whole directory gone, so
the push deletes the directory and everything the robot holds below it (a fresh-clone
full run saw the guard's test lose the robot's 40 files this way, one "deleted" at a
time, with no pause). A directory replaced by a file or a link takes its files with it
the same way. And the chain of small deleting pushes outlives a reconnection.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from helpers import local_sync_loop, make_workspace

from fetchsync.errors import TransportError
from fetchsync.link.connection import Connection
from fetchsync.link.transport import LocalTransport
from fetchsync.sync import engine as sync
from fetchsync.sync.state import State

N = 40  # files in my_pkg/many: most of the robot's 47


def many_files(src: Path) -> None:
    (src / "my_pkg/many").mkdir()
    for i in range(N):
        (src / f"my_pkg/many/f{i}.txt").write_text(f"file {i}\n")


def left(robot_src: Path) -> int:
    many = robot_src / "my_pkg/many"
    return sum(1 for p in many.rglob("*") if p.is_file()) if many.is_dir() else 0


@pytest.fixture
def engine(tmp_path: Path):
    """A Syncer over the local robot after a first push of make_workspace's tree + 40 files."""
    src = make_workspace(tmp_path / "ws") / "src"
    many_files(src)
    conn = Connection.open(LocalTransport(tmp_path / "robot-home"))
    state = State(tmp_path / "state.sqlite")
    s = sync.Syncer(
        conn, state, local_root=str(src), remote_workspace="~/ws", rules=sync.build_rules()
    )
    assert s.push().errors == []
    robot_src = tmp_path / "robot-home" / "ws" / "src"
    assert left(robot_src) == N
    yield s, src, robot_src
    conn.close()
    state.close()


def test_a_gone_directory_counts_whole_when_the_batch_names_a_few_of_its_files(engine):
    s, src, robot = engine
    shutil.rmtree(src / "my_pkg/many")
    with pytest.raises(sync.MassDeletionError, match=f"delete {N} of"):
        s.push_paths({f"my_pkg/many/f{i}.txt" for i in range(3)})
    assert left(robot) == N


def test_each_file_in_its_own_batch_stops_at_the_first(engine):
    """The watcher's events fed one file a batch: the first push would take the directory."""
    s, src, robot = engine
    shutil.rmtree(src / "my_pkg/many")
    for i in range(N):
        with pytest.raises(sync.MassDeletionError):
            s.push_paths({f"my_pkg/many/f{i}.txt"})
    assert left(robot) == N


@pytest.mark.parametrize("replacement", ["file", "link"])
@pytest.mark.parametrize("how", ["full", "touched"])
def test_a_directory_replaced_by_a_file_counts_what_it_held(engine, replacement, how):
    s, src, robot = engine
    many = src / "my_pkg/many"
    shutil.rmtree(many)
    if replacement == "file":
        many.write_text("not a directory any more\n")
    else:
        many.symlink_to("package.xml")
    with pytest.raises(sync.MassDeletionError):
        if how == "full":
            s.push()
        else:
            s.push_paths({"my_pkg/many"}, {"my_pkg/many"})
    assert left(robot) == N
    r = s.push(confirm_deletions=True)
    assert r.errors == [] and left(robot) == 0


def test_a_few_files_of_a_big_directory_still_go(engine):
    """Not a pause for everything: deleting a few files whose directory stays is a push."""
    s, src, robot = engine
    for i in range(3):
        (src / f"my_pkg/many/f{i}.txt").unlink()
    assert s.push_paths({f"my_pkg/many/f{i}.txt" for i in range(3)}).deleted == 3
    assert left(robot) == N - 3


# ---------------------------------------------------------------- the watch agent


@pytest.fixture
def agent(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """The watch agent's sync loop against the local robot, fed batches by the test (its
    own watcher off), after the first sync."""
    src = make_workspace(tmp_path / "ws") / "src"
    many_files(src)
    with local_sync_loop(tmp_path, monkeypatch) as (a, robot):
        assert left(robot) == N
        yield a, src, robot


def test_the_agent_pauses_when_the_batches_name_one_file_each(agent):
    """An rm -rf reported one file a batch, each pushed before the next arrives."""
    a, src, robot = agent
    shutil.rmtree(src / "my_pkg/many")
    done, why = a.wait_for(a.request(paths={"my_pkg/many/f0.txt"}), 60)
    assert not done and why.startswith("paused:"), why
    for i in range(1, 5):
        done, why = a.wait_for(a.request(paths={f"my_pkg/many/f{i}.txt"}), 60)
        assert not done and why.startswith("paused:"), why
    assert a.status()["state"] == "paused"
    assert left(robot) == N


def test_the_count_goes_on_across_a_reconnection(agent):
    """Half an rm -rf pushed, the link lost and back (a new connection, a new Syncer), the
    other half: one deletion still, so the agent pauses before the second half."""
    a, src, robot = agent
    half = N // 2  # not more than MASS_MIN: alone, each half goes without a question
    assert half <= sync.MASS_MIN
    for i in range(half):
        (src / f"my_pkg/many/f{i}.txt").unlink()
    assert a.wait_for(a.request(paths={f"my_pkg/many/f{i}.txt" for i in range(half)}), 60) == (
        True,
        "",
    )
    assert left(robot) == N - half
    a._went_offline(None, TransportError("the link was lost"))
    for i in range(half, N):
        (src / f"my_pkg/many/f{i}.txt").unlink()
    done, why = a.wait_for(a.request(paths={f"my_pkg/many/f{i}.txt" for i in range(half, N)}), 60)
    assert not done and why.startswith("paused:"), why
    assert f"{half} of them deleted by the pushes just before" in why
    assert left(robot) == N - half
