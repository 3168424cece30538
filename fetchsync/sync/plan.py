"""Planning: from two trees and the last-synced state to a list of operations.

Pure functions over in-memory trees (``dict[path, Listed]``): no I/O, no
transport. ``plan()`` makes ``dest`` identical to ``source``; every operation
carries the expectation of what ``dest`` holds (what was last synced), and
chooses the cheapest way to get content there: reuse content ``dest``
already holds by hash, a delta against the last-synced version when its
signature is known, else the whole content.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping

from fetchsync.protocol import messages as M
from fetchsync.protocol.paths import ancestors

WHOLE = "whole"
DELTA = "delta"
COPY = "copy"


@dataclass(frozen=True)
class Planned:
    """An operation and, for writes, how its content will be produced."""

    op: M.Op
    how: str = ""  # WHOLE, DELTA or COPY for writes
    item: M.Listed | None = None  # the source entry this op makes dest hold


CATKIN_TOPLEVEL = "catkin/cmake/toplevel.cmake"


def catkin_toplevel(
    path: str, *, laptop: M.Listed | None, robot: M.Listed | None, last_synced: str
) -> bool:
    """Whether ``path`` is the ``src/CMakeLists.txt`` link the robot's ``catkin_make``
    made where the laptop has none: push and pull leave it alone. ``last_synced`` is
    the expectation of what was last synced there: a link this laptop pushed (it ran
    ``catkin_make`` itself) is the laptop's, and deleting it here deletes it there.

    ``catkin_make`` creates it when ``src/`` has no ``CMakeLists.txt``, as a symlink to
    its installed ``toplevel.cmake`` (``/opt/ros/<distro>/share/catkin/cmake/``,
    Debian's ``/usr/share/catkin/cmake/``). Mirroring would delete it on every push
    (a conflict each time, a copy in ``.fetchsync/conflicts/``, and a full rebuild
    when ``catkin_make`` makes it again), or pull a link into the robot's ROS install
    onto the laptop. A laptop that has its own ``src/CMakeLists.txt`` pushes it.
    """
    return (
        path == "CMakeLists.txt"
        and laptop is None
        and robot is not None
        and robot.kind == "l"
        and (robot.target == CATKIN_TOPLEVEL or robot.target.endswith("/" + CATKIN_TOPLEVEL))
        and last_synced != robot.expectation()
    )


def _same(a: M.Listed, b: M.Listed) -> bool:
    if a.kind != b.kind:
        return False
    if a.kind == "f":
        return a.hash == b.hash and a.mode == b.mode
    if a.kind == "l":
        return a.target == b.target
    return a.mode == b.mode


def plan(
    source: Mapping[str, M.Listed],
    dest: Mapping[str, M.Listed],
    expect: Callable[[str], str],
    *,
    has_signature: Callable[[str, M.Listed], bool] = lambda p, d: False,
    reuse: bool = True,
) -> list[Planned]:
    """Operations that make ``dest`` hold what ``source`` holds.

    ``expect(path)`` is what dest should hold at ``path`` (the last-synced
    expectation, ``"-"`` when unknown). ``has_signature(path, dest_item)``
    says whether a delta against dest's current file is possible.
    """
    by_hash: dict[str, str] = {}
    if reuse:
        for path, item in dest.items():
            if item.kind == "f" and item.size > 0:
                by_hash.setdefault(item.hash, path)
    mkdirs: list[Planned] = []
    writes: list[Planned] = []
    deletes: list[Planned] = []
    for path in sorted(set(source) | set(dest)):
        src = source.get(path)
        dst = dest.get(path)
        if src is None:
            # a parent that is not a directory in source takes this path with it
            if all(a in source and source[a].kind == "d" for a in ancestors(path)):
                deletes.append(Planned(M.Op(M.DELETE, path, expect=expect(path))))
        elif dst is not None and _same(src, dst):
            continue
        elif src.kind == "d":
            mkdirs.append(_make_dir(path, src, dst, expect(path)))
        else:
            writes.append(_write(path, src, dst, expect(path), by_hash, has_signature))
    # parents before children; content before deletes, so a renamed file's
    # old copy is still there to be reused
    return mkdirs + writes + deletes


def _make_dir(path: str, src: M.Listed, dst: M.Listed | None, exp: str) -> Planned:
    """A directory: made, or only its mode set where dest has one already."""
    kind = M.CHMOD if dst is not None and dst.kind == "d" else M.MKDIR
    return Planned(M.Op(kind, path, expect=exp, mode=src.mode), item=src)


def _write(
    path: str,
    src: M.Listed,
    dst: M.Listed | None,
    exp: str,
    by_hash: Mapping[str, str],
    has_signature: Callable[[str, M.Listed], bool],
) -> Planned:
    """A file or link, by the cheapest way: its mode alone if dest holds the content,
    content dest holds at another path, a delta against dest's version, or whole."""
    if src.kind == "l":
        return Planned(M.Op(M.SYMLINK, path, expect=exp, target=src.target), item=src)
    if dst is not None and dst.kind == "f" and dst.hash == src.hash:
        return Planned(M.Op(M.CHMOD, path, expect=exp, mode=src.mode), item=src)
    base: dict[str, Any] = dict(
        kind=M.WRITE, path=path, expect=exp, mode=src.mode, hash=src.hash, size=src.size
    )
    reuse_from = by_hash.get(src.hash) if src.size > 0 else None
    if reuse_from is not None:
        op = M.Op(source=M.SRC_COPY, base=src.hash, from_path=reuse_from, **base)
        return Planned(op, COPY, src)
    if dst is not None and dst.kind == "f" and dst.size > 0 and has_signature(path, dst):
        return Planned(M.Op(source=M.SRC_DELTA, base=dst.hash, **base), DELTA, src)
    return Planned(M.Op(source=M.SRC_DATA, **base), WHOLE, src)
