"""The coalescer holds a new directory like a burst's start (its files are reported later).

Driven by scripted items and invented times (binary fractions, so they compare exactly),
as tests/test_agent_coalescer.py.
"""

from __future__ import annotations

from fetchsync.agent.coalescer import CLOSED, CREATED, DELETED, MODIFIED, Change, Coalescer

QUIET = 0.25
BURST_QUIET = 0.5


def make() -> Coalescer:
    return Coalescer(quiet=QUIET, cap=4.0, burst=64, burst_quiet=BURST_QUIET)


def test_a_new_directory_waits_for_the_burst_window_and_takes_its_files_along() -> None:
    # mkdir d; the watch on d is added; then d's files are reported: more than the
    # quiet window after d itself. Cut at the quiet window, the burst went as d (and the
    # few files written by then) and the rest in a second push after the first's answer.
    c = make()
    c.add(Change("d", CREATED, is_dir=True), 10.0)
    assert c.due(10.0) == BURST_QUIET
    assert c.take(10.375) is None  # past the quiet window: not due yet
    for k in range(3):
        c.add(Change(f"d/f{k}", CREATED), 10.375)
        c.add(Change(f"d/f{k}", CLOSED), 10.375)
    assert c.take(10.75) is None  # the burst window runs from the last item
    batch = c.take(10.875)
    assert batch is not None
    assert batch.dirs == frozenset({"d"}) and batch.paths == frozenset()  # one rescan of d


def test_a_directory_moved_in_is_held_the_same_way() -> None:
    # a rename into the tree is reported as "moved" at the source (outside: not seen) and
    # "created" at the destination: the same event as a mkdir for the coalescer
    c = make()
    c.add(Change("pkg/new", CREATED, is_dir=True), 10.0)
    c.add(Change("pkg/new", MODIFIED, is_dir=True), 10.0)
    assert c.due(10.0) == BURST_QUIET


def test_a_new_directory_cut_by_the_cap_goes_on_as_a_burst() -> None:
    # a slow writer: the cap cuts the new directory's batch; the files reported after
    # it are the same burst, not a save to send after the quiet window
    c = Coalescer(quiet=QUIET, cap=1.0, burst=64, burst_quiet=BURST_QUIET)
    c.add(Change("d", CREATED, is_dir=True), 10.0)
    for k, at in enumerate((10.25, 10.5, 10.75)):
        c.add(Change(f"d/f{k}", CLOSED), at)
    assert c.take(11.0) is not None  # the cap
    c.add(Change("d/f3", CLOSED), 11.125)
    assert c.due(11.125) == BURST_QUIET


def test_files_and_deleted_directories_keep_the_short_window() -> None:
    # only a directory that appeared announces files to come: a deleted one does not,
    # and a new file alone is an editor's save pattern (the quiet window)
    c = make()
    c.add(Change("gone", DELETED, is_dir=True), 10.0)
    assert c.due(10.0) == QUIET
    assert c.take(10.25) is not None
    c2 = make()
    c2.add(Change("a.cpp", CREATED), 10.0)
    assert c2.due(10.0) == QUIET
