import os

import pytest

from fetchsync.protocol import paths
from fetchsync.protocol.errors import PathError


@pytest.mark.parametrize(
    "bad",
    [
        "",
        "/etc/passwd",
        "../x",
        "a/../b",
        "a/./b",
        "a//b",
        "a/",
        ".",
        "..",
        "a\x00b",
        "x" * 5000,
        "a/" + "n" * 300,
    ],
)
def test_bad_paths_are_refused(bad):
    with pytest.raises(PathError):
        paths.validate(bad)


@pytest.mark.parametrize(
    "good",
    [
        "a",
        "pkg/src/node.cpp",
        "with space/new\nline",
        "caf\u00e9",
        os.fsdecode(b"latin\xe9"),
        "...",
        "..a",
        "a..b",
    ],
)
def test_good_paths_pass(good):
    assert paths.validate(good) == good


def test_root_refuses_walking_through_a_symlinked_directory(tmp_path):
    root = tmp_path / "root"
    (root / "real" / "sub").mkdir(parents=True)
    (root / "link").symlink_to(tmp_path)
    (root / "real" / "file").write_text("x")
    r = paths.Root(os.open(root, os.O_RDONLY | os.O_DIRECTORY), str(root))
    try:
        with r.parent("real/sub/f") as (fd, name):
            assert name == "f" and os.path.samestat(os.fstat(fd), os.stat(root / "real" / "sub"))
        with r.parent("top") as (fd, name):
            assert fd == r.fd and name == "top"
        for bad in ("link/file", "link/sub/file", "missing/file", "real/file/x"):
            with pytest.raises(PathError):
                with r.parent(bad):
                    pass
        for bad in ("../x", "a//b", "/abs", "a/./b", "", None, 3):
            with pytest.raises(PathError):
                with r.parent(bad):  # type: ignore[arg-type]
                    pass
    finally:
        os.close(r.fd)
