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
