"""The coalescer, driven by scripted items and invented times: one rule per test.

Times are binary fractions (quiet 0.25 s, cap 1 s) so that they compare exactly.
"""

from __future__ import annotations

import pytest

from fetchsync.agent.coalescer import (
    CLOSED,
    CREATED,
    DELETED,
    MODIFIED,
    MOVED,
    Batch,
    Change,
    Coalescer,
    Rescan,
)

QUIET = 0.25
CAP = 1.0


def make(**kw: float) -> Coalescer:
    return Coalescer(
        quiet=kw.get("quiet", QUIET),
        cap=kw.get("cap", CAP),
        max_paths=int(kw.get("max_paths", 1000)),
    )


def feed(c: Coalescer, *script: tuple[float, Change | Rescan]) -> None:
    for at, item in script:
        c.add(item, at)


def f(path: str, kind: str = MODIFIED) -> Change:
    return Change(path, kind)  # type: ignore[arg-type]


def d(path: str, kind: str = CREATED) -> Change:
    return Change(path, kind, is_dir=True)  # type: ignore[arg-type]


def take_due(c: Coalescer) -> Batch:
    """The pending batch, taken at the moment it is due."""
    wait = c.due(0.0)
    assert wait is not None
    batch = c.take(wait)
    assert batch is not None
    return batch


# -- the model ----------------------------------------------------------------


def test_change_rejects_an_unknown_kind() -> None:
    with pytest.raises(ValueError):
        Change("a", "renamed")  # type: ignore[arg-type]


@pytest.mark.parametrize("path", ["", "/abs", "dir/"])
def test_change_rejects_a_path_that_is_not_relative(path: str) -> None:
    with pytest.raises(ValueError):
        Change(path, MODIFIED)


def test_items_are_frozen_and_hashable() -> None:
    c = Change("a", MODIFIED)
    with pytest.raises(AttributeError):
        c.path = "b"  # type: ignore[misc]
    assert len({c, Change("a", MODIFIED), Rescan("x"), Rescan("x")}) == 2


# -- timing -------------------------------------------------------------------------


def test_nothing_pending_means_no_due_time_and_no_batch() -> None:
    c = make()
    assert c.due(5.0) is None
    assert c.take(5.0) is None
    assert not c.pending


def test_a_batch_is_due_after_the_quiet_window() -> None:
    c = make()
    feed(c, (10.0, f("a")))
    assert c.due(10.0) == QUIET
    assert c.take(10.0) is None
    assert c.take(10.125) is None
    batch = c.take(10.25)
    assert batch == Batch(frozenset({"a"}), frozenset(), None, 10.0, 10.0, 1)


def test_each_new_item_restarts_the_quiet_window() -> None:
    c = make()
    feed(c, (10.0, f("a")), (10.125, f("b")))
    assert c.due(10.125) == QUIET
    assert c.take(10.25) is None  # 0.25 after the first, but only 0.125 after the second
    batch = c.take(10.375)
    assert batch is not None and batch.paths == {"a", "b"}


def test_the_cap_bounds_the_latency_of_a_continuous_stream() -> None:
    c = make()
    t = 10.0
    while t < 10.875:
        c.add(f(f"p{t}"), t)
        t += 0.125  # always inside the quiet window
    c.add(f("last"), 10.875)  # quiet would make it due at 11.125
    assert c.due(10.875) == pytest.approx(0.125)  # first (10.0) + cap (1.0)
    assert c.take(10.9375) is None
    batch = c.take(11.0)
    assert batch is not None
    assert len(batch.paths) == 8 and (batch.first_at, batch.last_at) == (10.0, 10.875)


def test_an_existing_file_written_and_closed_is_due_at_once() -> None:
    c = make()
    feed(c, (10.0, f("a")), (10.0, f("a", CLOSED)))  # open(O_TRUNC), write, close
    assert c.due(10.0) == 0.0
    batch = c.take(10.0)
    assert batch is not None and batch.paths == {"a"}


def test_vims_save_by_rename_is_due_at_its_close() -> None:
    # the file moved to its backup (ignored, never reported), written anew, closed
    c = make()
    feed(c, (10.0, f("a", MOVED)), (10.0, f("a", CREATED)), (10.0, f("a", CLOSED)))
    assert c.due(10.0) == 0.0
    assert c.take(10.0) == Batch(frozenset({"a"}), frozenset(), None, 10.0, 10.0, 3)


def test_a_file_created_in_the_batch_waits_for_the_quiet_window_when_closed() -> None:
    # an editor's temporary, about to be renamed over the file
    c = make()
    feed(c, (10.0, f("a.tmp", CREATED)), (10.0, f("a.tmp", CLOSED)))
    assert c.due(10.0) == QUIET
    c.add(f("a.tmp", MOVED), 10.0625)
    c.add(f("a", CREATED), 10.0625)
    batch = c.take(10.3125)
    assert batch is not None and batch.paths == {"a"}


def test_an_item_after_the_close_brings_the_quiet_window_back() -> None:
    c = make()
    feed(c, (10.0, f("a", CLOSED)), (10.0, f("b", DELETED)))
    assert c.due(10.0) == QUIET
    feed(c, (10.0, f("c", CLOSED)), (10.0, f("c")))  # written again after its close
    assert c.due(10.0) == QUIET


def test_a_file_deleted_then_written_waits_for_the_quiet_window() -> None:
    # git checkout rewrites a file by unlinking and creating it: a burst, not a save
    c = make()
    feed(c, (10.0, f("a", DELETED)), (10.0, f("a", CREATED)), (10.0, f("a", CLOSED)))
    assert c.due(10.0) == QUIET


def test_a_save_right_after_the_last_batch_waits_for_the_quiet_window() -> None:
    # a formatter rewriting file after file, a checkout cut by the cap or a stall: the
    # first save goes at once, the stream after it coalesces
    c = Coalescer(quiet=0.25, cap=4.0, burst=64, burst_quiet=0.5)
    feed(c, (10.0, f("a")), (10.0, f("a", CLOSED)))
    assert c.take(10.0) is not None
    feed(c, (10.125, f("b")), (10.125, f("b", CLOSED)))
    assert c.due(10.125) == 0.25
    assert c.take(10.375) is not None
    feed(c, (12.0, f("c", CLOSED)))  # long after: a save again
    assert c.due(12.0) == 0.0


def test_a_close_inside_a_burst_does_not_end_it() -> None:
    c = Coalescer(quiet=0.25, cap=4.0, burst=4, burst_quiet=0.5)
    feed(c, *[(10.0, f(f"p{k}")) for k in range(4)])
    c.add(f("p0", CLOSED), 10.0)
    assert c.due(10.0) == 0.5


def test_a_burst_widens_the_quiet_window() -> None:
    c = Coalescer(quiet=0.25, cap=4.0, burst=4, burst_quiet=0.5)
    feed(c, (10.0, f("a")), (10.0, f("b")), (10.0, f("c")))
    assert c.due(10.0) == 0.25  # a save: the short window
    c.add(f("d"), 10.0)
    assert c.due(10.0) == 0.5  # the fourth item makes it a burst
    assert c.take(10.25) is None  # a hiccup does not end it
    c.add(f("e"), 10.375)
    assert c.take(10.75) is None
    batch = c.take(10.875)
    assert batch is not None and len(batch.paths) == 5


def test_a_burst_cut_by_the_cap_goes_on_in_the_next_batch() -> None:
    c = Coalescer(quiet=0.25, cap=1.0, burst=4, burst_quiet=0.5)
    feed(c, *[(10.0 + k / 8, f(f"p{k}")) for k in range(8)])  # 10.0 .. 10.875
    assert c.take(11.0) is not None  # cut by the cap
    c.add(f("next"), 11.125)  # 0.25 after the last
    assert c.due(11.125) == 0.5  # still a burst
    assert c.take(11.5) is None and c.take(11.625) is not None


def test_after_a_pause_the_next_batch_is_not_a_burst() -> None:
    c = Coalescer(quiet=0.25, cap=1.0, burst=4, burst_quiet=0.5)
    feed(c, *[(10.0 + k / 8, f(f"p{k}")) for k in range(8)])
    assert c.take(11.0) is not None
    c.add(f("save"), 12.0)  # 1.125 after the burst
    assert c.due(12.0) == 0.25


def test_the_burst_window_is_never_shorter_than_the_quiet_one() -> None:
    c = Coalescer(quiet=0.25, cap=4.0, burst=1, burst_quiet=0.125)
    c.add(f("a"), 10.0)
    assert c.due(10.0) == 0.25


def test_a_full_batch_is_due_at_once() -> None:
    c = make(max_paths=3)
    feed(c, (10.0, f("a")), (10.0, f("b")))
    assert not c.full and c.due(10.0) == QUIET
    c.add(f("c"), 10.0)
    assert c.full
    assert c.due(10.0) == 0.0
    batch = c.take(10.0)
    assert batch is not None and batch.paths == {"a", "b", "c"}


def test_take_can_be_forced_before_the_batch_is_due() -> None:
    c = make()
    feed(c, (10.0, f("a")))
    batch = c.take(10.0, force=True)
    assert batch is not None and batch.paths == {"a"}


def test_taking_starts_a_new_batch() -> None:
    c = make()
    feed(c, (10.0, f("a")))
    assert c.take(10.25) is not None
    assert not c.pending and c.due(10.25) is None
    feed(c, (11.0, f("b")))
    batch = c.take(11.25)
    assert batch is not None
    assert batch.paths == {"b"} and batch.first_at == 11.0 and batch.items == 1


def test_items_with_earlier_timestamps_widen_the_batch() -> None:
    # items come from several threads, each with the time it saw its event
    c = make()
    feed(c, (10.0, f("a")), (9.5, f("b")))
    batch = c.take(10.25)
    assert batch is not None and (batch.first_at, batch.last_at) == (9.5, 10.0)


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError):
        Coalescer(quiet=-1)
    with pytest.raises(ValueError):
        Coalescer(max_paths=0)


# -- one entry per path ------------------------------------------------------------


def test_a_path_touched_many_times_appears_once() -> None:
    c = make()
    feed(c, (10.0, f("a", CREATED)), (10.0, f("a")), (10.0, f("a")), (10.0, f("b")))
    batch = take_due(c)
    assert batch.paths == {"a", "b"} and batch.items == 4


def test_created_then_deleted_cancels_out() -> None:
    c = make()
    feed(
        c, (10.0, f("tmp", CREATED)), (10.0, f("tmp")), (10.0, f("tmp", DELETED)), (10.0, f("kept"))
    )
    assert take_due(c).paths == {"kept"}


def test_created_then_moved_away_cancels_out() -> None:
    # a safe-write temporary the ignore rules do not know: written, renamed over the file
    c = make()
    feed(
        c,
        (10.0, f("file.c.x7Gq", CREATED)),
        (10.0, f("file.c.x7Gq", MOVED)),
        (10.0, f("file.c", CREATED)),
    )
    assert take_due(c).paths == {"file.c"}


def test_deleted_then_created_is_kept() -> None:
    # the file existed before: it was replaced
    c = make()
    feed(c, (10.0, f("a", DELETED)), (10.0, f("a", CREATED)))
    assert take_due(c).paths == {"a"}


def test_a_deletion_of_an_existing_path_is_kept() -> None:
    c = make()
    feed(c, (10.0, f("a")), (10.0, f("a", DELETED)))
    assert take_due(c).paths == {"a"}


def test_created_deleted_created_again_is_kept() -> None:
    c = make()
    feed(c, (10.0, f("a", CREATED)), (10.0, f("a", DELETED)), (10.0, f("a", CREATED)))
    assert take_due(c).paths == {"a"}


def test_a_batch_that_cancels_out_entirely_is_none_and_is_dropped() -> None:
    c = make()
    feed(c, (10.0, f("4913", CREATED)), (10.0, f("4913", DELETED)))
    assert c.due(10.0) == QUIET
    assert c.take(10.25) is None
    assert not c.pending


# -- directories ---------------------------------------------------------------------


def test_a_directory_change_is_reported_as_a_directory() -> None:
    c = make()
    feed(c, (10.0, d("pkg", DELETED)), (10.0, f("other")))
    batch = take_due(c)
    assert batch.dirs == {"pkg"} and batch.paths == {"other"}


def test_a_directory_subsumes_later_changes_below_it() -> None:
    c = make()
    feed(
        c,
        (10.0, d("new")),
        (10.0, f("new/a", CREATED)),
        (10.0, d("new/sub")),
        (10.0, f("new/sub/b", CREATED)),
        (10.0, f("newer", CREATED)),
    )
    batch = take_due(c)
    assert batch.dirs == {"new"} and batch.paths == {"newer"}


def test_a_directory_subsumes_earlier_changes_below_it() -> None:
    # rm -r deletes bottom-up: the files first, then their directories
    c = make()
    feed(
        c,
        (10.0, f("pkg/src/a.cpp", DELETED)),
        (10.0, d("pkg/src", DELETED)),
        (10.0, f("pkg/b", DELETED)),
        (10.0, d("pkg", DELETED)),
        (10.0, f("pkgx")),
    )
    batch = take_due(c)
    assert batch.dirs == {"pkg"} and batch.paths == {"pkgx"}


def test_a_directory_does_not_subsume_a_sibling_with_its_name_as_prefix() -> None:
    c = make()
    feed(c, (10.0, d("pkg")), (10.0, f("pkg2/a")), (10.0, f("pkg.txt")))
    batch = take_due(c)
    assert batch.dirs == {"pkg"} and batch.paths == {"pkg2/a", "pkg.txt"}


def test_a_moved_directory_is_two_directory_changes() -> None:
    c = make()
    feed(
        c,
        (10.0, d("old", MOVED)),
        (10.0, d("new", CREATED)),
        (10.0, f("old/a", MOVED)),
        (10.0, f("new/a", CREATED)),
    )
    batch = take_due(c)
    assert batch.dirs == {"old", "new"} and batch.paths == frozenset()


def test_a_directory_created_and_removed_within_the_batch_cancels_out() -> None:
    c = make()
    feed(
        c,
        (10.0, d("tmpdir")),
        (10.0, f("tmpdir/x", CREATED)),
        (10.0, f("tmpdir/x", DELETED)),
        (10.0, d("tmpdir", DELETED)),
    )
    assert c.take(10.25) is None


def test_a_directory_staged_then_moved_into_place_is_one_directory() -> None:
    c = make()
    feed(
        c,
        (10.0, d("stage")),
        (10.0, f("stage/a", CREATED)),
        (10.0, d("stage", MOVED)),
        (10.0, d("final")),
        (10.0, f("stage/a", MOVED)),
        (10.0, f("final/a", CREATED)),
    )
    batch = take_due(c)
    assert batch.dirs == {"final"} and batch.paths == frozenset()


def test_a_directory_replaced_by_a_file_stays_a_directory_change() -> None:
    # the robot's subtree there must go: the consumer rescans below it
    c = make()
    feed(c, (10.0, d("x", DELETED)), (10.0, f("x", CREATED)))
    batch = take_due(c)
    assert batch.dirs == {"x"} and batch.paths == frozenset()


def test_changes_below_a_directory_count_once_toward_the_size_cap() -> None:
    c = make(max_paths=3)
    feed(c, (10.0, d("big")), *[(10.0, f(f"big/{i}", CREATED)) for i in range(100)])
    assert not c.full
    assert take_due(c).dirs == {"big"}


# -- rescans --------------------------------------------------------------------------


def test_a_rescan_subsumes_everything_before_it() -> None:
    c = make()
    feed(c, (10.0, f("a")), (10.0, d("b")), (10.0, Rescan("overflow")))
    batch = take_due(c)
    assert batch == Batch(frozenset(), frozenset(), "overflow", 10.0, 10.0, 3)


def test_a_rescan_subsumes_everything_after_it() -> None:
    c = make()
    feed(c, (10.0, Rescan("overflow")), (10.0, f("a")), (10.0, Rescan("again")))
    batch = take_due(c)
    assert batch.rescan == "overflow" and not batch.paths and batch.items == 3


def test_a_rescan_follows_the_same_timing_rules() -> None:
    c = make()
    feed(c, (10.0, Rescan("started")))
    assert c.due(10.0) == QUIET
    assert c.take(10.125) is None
    batch = c.take(10.25)
    assert batch is not None and batch.rescan == "started"
