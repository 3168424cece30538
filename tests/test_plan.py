"""The planner is pure: trees in, operations out."""

from fetchsync.protocol import messages as M
from fetchsync.sync.plan import COPY, DELTA, WHOLE, plan


def f(path, h, size=10, mode=0o644):
    return M.Listed(path, "f", mode, size, hash=h)


def d(path, mode=0o755):
    return M.Listed(path, "d", mode)


def tree(*items):
    return {i.path: i for i in items}


def absent(_path):
    return M.ABSENT


def kinds(ops):
    return [(p.op.kind, p.op.path, p.how) for p in ops]


def test_identical_trees_need_nothing():
    t = tree(d("a"), f("a/x", "h1"))
    assert plan(t, dict(t), absent) == []


def test_new_tree_is_created_parents_first():
    ops = plan(tree(d("a"), d("a/b"), f("a/b/x", "h1")), {}, absent)
    assert kinds(ops) == [("mkdir", "a", ""), ("mkdir", "a/b", ""), ("write", "a/b/x", WHOLE)]


def test_rename_reuses_content_and_deletes_after():
    src = tree(f("new", "h1"))
    dst = tree(f("old", "h1"))
    ops = plan(src, dst, absent)
    assert kinds(ops) == [("write", "new", COPY), ("delete", "old", "")]
    assert ops[0].op.from_path == "old"


def test_delta_only_when_a_signature_exists():
    src, dst = tree(f("x", "h2", 50000)), tree(f("x", "h1", 50000))
    assert kinds(plan(src, dst, absent))[0][2] == WHOLE
    assert kinds(plan(src, dst, absent, has_signature=lambda p, it: True))[0][2] == DELTA


def test_deleting_a_directory_is_one_operation():
    ops = plan({}, tree(d("a"), f("a/x", "h"), d("a/b"), f("a/b/y", "h2")), absent)
    assert kinds(ops) == [("delete", "a", "")]


def test_file_becomes_directory_and_back():
    ops = plan(tree(d("a"), f("a/x", "h")), tree(f("a", "h0")), absent)
    assert kinds(ops)[:2] == [("mkdir", "a", ""), ("write", "a/x", WHOLE)]
    ops = plan(tree(f("a", "h0")), tree(d("a"), f("a/x", "h")), absent)
    assert kinds(ops) == [("write", "a", WHOLE)]


def test_mode_change_is_a_chmod():
    ops = plan(tree(f("x", "h", mode=0o755)), tree(f("x", "h", mode=0o644)), absent)
    assert kinds(ops) == [("chmod", "x", "")]
    assert ops[0].op.mode == 0o755


def test_expectations_come_from_the_caller():
    ops = plan(tree(f("x", "h2")), tree(f("x", "h1")), lambda p: "f:h1")
    assert ops[0].op.expect == "f:h1"


def test_symlink_target_change():
    ops = plan(
        tree(M.Listed("l", "l", target="/abs")), tree(M.Listed("l", "l", target="rel")), absent
    )
    assert kinds(ops) == [("symlink", "l", "")]


# reconcile (fetchsync.sync.engine): the local scan, the last-synced state and the robot's
# listing in, the push's operations out; no I/O


def synced_expect(state):
    return lambda path: state[path].expectation() if path in state else M.ABSENT


def test_reconcile_expects_what_was_last_synced_not_what_the_robot_holds():
    from fetchsync.sync.engine import reconcile

    local = tree(d("a"), f("a/x", "h1", mode=0o755))
    last = tree(d("a"), f("a/x", "h1"))
    robot = tree(d("a"), f("a/x", "h2"))  # edited on the robot since
    (p,) = reconcile(local, robot, synced_expect(last), guarded=lambda _p: False)
    assert (p.op.kind, p.op.path, p.op.expect) == (M.WRITE, "a/x", M.expect_file("h1"))


def test_reconcile_leaves_guarded_paths_as_the_robot_has_them():
    from fetchsync.sync.engine import reconcile

    local = tree(d("a"), f("a/x", "h1"))
    robot = tree(d("a"), f("a/x", "h0"), d("build"), f("build/out", "h3"), f("a/locked", "h4"))
    guarded = {"build", "a/locked", "a/x"}.__contains__  # excluded, unreadable
    assert reconcile(local, robot, synced_expect(robot), guarded=guarded) == []
    assert kinds(reconcile(local, robot, synced_expect(robot), guarded=lambda _p: False)) == [
        ("write", "a/x", WHOLE),
        ("delete", "a/locked", ""),
        ("delete", "build", ""),
    ]


def test_reconcile_of_identical_trees_is_empty():
    from fetchsync.sync.engine import reconcile

    t = tree(d("a"), f("a/x", "h1"))
    assert reconcile(t, dict(t), synced_expect(t), guarded=lambda _p: False) == []
