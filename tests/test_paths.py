import os

import pytest

from fetchsync.protocol import paths
from fetchsync.protocol.errors import PathError


@pytest.mark.parametrize("bad", ["", "/etc/passwd", "../x", "a/../b", "a/./b", "a//b", "a/", ".",
                                 "..", "a\x00b", "x" * 5000, "a/" + "n" * 300])
def test_bad_paths_are_refused(bad):
    with pytest.raises(PathError):
        paths.validate(bad)


@pytest.mark.parametrize("good", ["a", "pkg/src/node.cpp", "with space/new\nline", "caf\u00e9",
                                  os.fsdecode(b"latin\xe9"), "...", "..a", "a..b"])
def test_good_paths_pass(good):
    assert paths.validate(good) == good


def test_resolver_refuses_writing_through_a_symlinked_parent(tmp_path):
    root = tmp_path / "root"
    (root / "real").mkdir(parents=True)
    (root / "link").symlink_to(tmp_path)
    r = paths.Resolver(str(root))
    r.check_parents("real/file")
    with pytest.raises(PathError):
        r.check_parents("link/file")
    with pytest.raises(PathError):
        r.check_parents("missing/file")


def test_resolver_full_validates_every_path_it_has_not_seen_and_stays_bounded(tmp_path):
    from fetchsync.protocol import paths as paths_mod
    r = paths_mod.Resolver(str(tmp_path))
    for i in range(paths_mod.FULL_CACHE + 10):
        assert r.full(f"d/f{i}") == os.path.join(str(tmp_path), f"d/f{i}")
    assert len(r._full) <= paths_mod.FULL_CACHE
    for bad in ("../x", "a//b", "/abs", "a/./b", "", None, 3):
        with pytest.raises(PathError):
            r.full(bad)  # type: ignore[arg-type]
        with pytest.raises(PathError):
            r.check_parents(bad)  # type: ignore[arg-type]
