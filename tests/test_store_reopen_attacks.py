"""Attacks on the robot endpoint's Store kept between re-opens of one session
(server.do_open, redteam, session 23): the workspace's ``.fetchsync`` swapped for a
symlink between two opens is refused as for a fresh endpoint, nothing written through
it; the index replaced by another writer's between two opens is the one read."""

from __future__ import annotations

import shutil
from pathlib import Path

from endpoint_client import Endpoint
from helpers import make_workspace


def test_a_metadata_directory_swapped_for_a_symlink_between_opens_is_refused(
    tmp_path: Path,
) -> None:
    ws = tmp_path / "ws"
    make_workspace(ws)
    home = tmp_path / "home"
    home.mkdir()
    elsewhere = tmp_path / "elsewhere"
    with Endpoint(str(home)) as ep:
        for _ in range(2):  # the second open keeps the Store
            f = ep.request({"op": "open", "workspace": str(ws)})
            assert f.type == 2, f.header
            assert ep.request({"op": "list"}).type == 2
        shutil.copytree(ws / ".fetchsync", elsewhere)
        before = sorted(p.name for p in elsewhere.rglob("*"))
        shutil.rmtree(ws / ".fetchsync")
        (ws / ".fetchsync").symlink_to(elsewhere)
        f = ep.request({"op": "open", "workspace": str(ws)})
        assert f.type != 2, f.header  # refused, as a fresh endpoint refuses it
        assert "symlink" in str(f.header).lower() or "not a directory" in str(f.header), f.header
        f = ep.request({"op": "list"})
        assert f.type != 2, f.header
    assert sorted(p.name for p in elsewhere.rglob("*")) == before  # nothing made there


def test_an_index_replaced_between_opens_is_the_one_read(tmp_path: Path) -> None:
    """Another endpoint's push between two opens of a long-lived one: its index (a new
    file) is read, not the kept Store's memory: the generation it answers is the new."""
    ws = tmp_path / "ws"
    make_workspace(ws)
    home = tmp_path / "home"
    home.mkdir()
    with Endpoint(str(home)) as kept:
        first = kept.request({"op": "open", "workspace": str(ws)})
        assert first.type == 2
        second = kept.request({"op": "open", "workspace": str(ws)})
        assert second.type == 2
        with Endpoint(str(home)) as other:  # another endpoint: opens and saves, a new epoch
            assert other.request({"op": "open", "workspace": str(ws)}).type == 2
            shutil.rmtree(ws / ".fetchsync")  # the index gone and made again by the other
            f = other.request({"op": "open", "workspace": str(ws)})
            assert f.type == 2
            fresh = (f.header.get("epoch"), f.header.get("gen"))
        again = kept.request({"op": "open", "workspace": str(ws)})
        assert again.type == 2
        assert (again.header.get("epoch"), again.header.get("gen")) == fresh
        assert fresh != (first.header.get("epoch"), first.header.get("gen"))
