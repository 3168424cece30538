"""Exclude rules (fetchsync.protocol.ignore): git's gitignore semantics, defaults, wire, 3.8."""

from __future__ import annotations

import json
import os
import random
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import local_env

from fetchsync.protocol import ignore as ignore_mod
from fetchsync.protocol.ignore import (
    DEFAULT_PATTERNS,
    IGNORE_FILENAME,
    MAX_IGNORE_FILE_SIZE,
    IgnoreMatch,
    IgnoreRules,
    read_ignore_file,
)

PY38 = Path("/root/.pyenv/versions/3.8.18/bin/python3.8")
MODULE = Path(ignore_mod.__file__)


def rules(text: str, *, extra: tuple[str, ...] = ()) -> IgnoreRules:
    """Rules of one root ignore file, without the defaults."""
    return IgnoreRules.build(defaults=False, extra=extra).with_file("", text)


def ign(r: IgnoreRules, path: str, is_dir: bool = False) -> bool:
    return r.ignored_any(path, is_dir)


# --------------------------------------------------------------------------
# Lines: comments, blanks, escapes, spaces


def test_blank_lines_and_comments_are_skipped() -> None:
    r = rules("\n   \n# foo\n#bar\n\nbaz\n")
    assert not ign(r, "foo")
    assert not ign(r, "#bar")
    assert not ign(r, "# foo")
    assert ign(r, "baz")


def test_escaped_hash_is_a_pattern() -> None:
    r = rules("\\#notes\n")
    assert ign(r, "#notes")
    assert ign(r, "a/#notes")


def test_hash_not_at_line_start_is_literal() -> None:
    r = rules("a#b\n")
    assert ign(r, "a#b")


def test_escaped_bang_is_literal() -> None:
    r = rules("*\n\\!important\n")
    # "\!important" is an exclusion of the file named "!important", not a re-include.
    assert ign(r, "!important")
    r = rules("\\!important\n")
    assert ign(r, "!important")
    assert not ign(r, "important")


def test_trailing_spaces_are_trimmed() -> None:
    r = rules("foo   \n")
    assert ign(r, "foo")
    assert not ign(r, "foo   ")


def test_escaped_trailing_space_is_kept() -> None:
    r = rules("foo\\ \n")
    assert ign(r, "foo ")
    assert not ign(r, "foo")
    r = rules("foo\\  \n")  # one escaped space kept, the unescaped one after it trimmed
    assert ign(r, "foo ")
    assert not ign(r, "foo  ")


def test_tabs_are_not_trimmed() -> None:
    r = rules("foo\t\n")
    assert ign(r, "foo\t")
    assert not ign(r, "foo")


def test_crlf_and_bom() -> None:
    r = rules("\ufefffoo\r\nbar\r\n")
    assert ign(r, "foo")
    assert ign(r, "bar")
    assert not ign(r, "bar\r")


def test_last_line_without_newline() -> None:
    assert ign(rules("a\nb"), "b")


def test_trailing_backslash_matches_nothing() -> None:
    r = rules("foo\\\n")
    assert not ign(r, "foo")
    assert not ign(r, "foo\\")


def test_empty_negation_and_lone_slash_match_nothing() -> None:
    r = rules("!\n/\n")
    assert not ign(r, "a")
    assert not ign(r, "a", True)


# --------------------------------------------------------------------------
# Negation


def test_negation_reincludes() -> None:
    r = rules("*.log\n!keep.log\n")
    assert ign(r, "a.log")
    assert not ign(r, "keep.log")
    assert not ign(r, "sub/keep.log")


def test_negation_only_overrides_earlier_patterns() -> None:
    r = rules("!keep.log\n*.log\n")
    assert ign(r, "keep.log")


def test_file_in_excluded_directory_cannot_be_reincluded() -> None:
    r = rules("build/\n!build/keep.txt\n")
    assert ign(r, "build", True)
    assert ign(r, "build/keep.txt")
    # The walker never asks about it; a direct question on the file alone
    # (no parent check) sees the re-include, which is why ignored_any exists.
    assert not r.ignored("build/keep.txt", False)


def test_reinclude_works_when_only_the_contents_are_excluded() -> None:
    r = rules("build/*\n!build/keep.txt\n")
    assert not ign(r, "build", True)
    assert ign(r, "build/other.txt")
    assert not ign(r, "build/keep.txt")


def test_reinclude_of_directory_then_contents() -> None:
    r = rules("/*\n!/pkg/\n/pkg/*\n!/pkg/src/\n")
    assert ign(r, "top.txt")
    assert not ign(r, "pkg", True)
    assert ign(r, "pkg/CMakeLists.txt")
    assert not ign(r, "pkg/src/node.cpp")
    assert ign(r, "pkg/scripts/x.py")


# --------------------------------------------------------------------------
# Anchoring


def test_pattern_without_slash_matches_at_any_depth() -> None:
    r = rules("foo\n")
    assert ign(r, "foo")
    assert ign(r, "a/foo")
    assert ign(r, "a/b/c/foo", True)
    assert not ign(r, "foobar")
    assert not ign(r, "a/xfoo")


def test_leading_slash_anchors_to_the_root() -> None:
    r = rules("/foo\n")
    assert ign(r, "foo")
    assert not ign(r, "a/foo")


def test_middle_slash_anchors_too() -> None:
    r = rules("a/foo\n")
    assert ign(r, "a/foo")
    assert not ign(r, "b/a/foo")
    assert not ign(r, "foo")


def test_anchored_pattern_excludes_the_subtree() -> None:
    r = rules("a/b\n")
    assert ign(r, "a/b", True)
    assert ign(r, "a/b/c/d.txt")


def test_trailing_slash_alone_does_not_anchor() -> None:
    r = rules("foo/\n")
    assert ign(r, "x/y/foo", True)


# --------------------------------------------------------------------------
# Directories only


def test_trailing_slash_matches_directories_only() -> None:
    r = rules("foo/\n")
    assert ign(r, "foo", True)
    assert not ign(r, "foo", False)
    assert ign(r, "foo/bar.txt")


def test_negated_directory_pattern_leaves_files_alone() -> None:
    r = rules("foo\n!foo/\n")
    assert ign(r, "foo", False)
    assert not ign(r, "foo", True)


def test_symlink_to_directory_is_not_a_directory(tmp_path: Path) -> None:
    # The caller passes is_dir=False for symlinks; check git agrees.
    repo = _git_repo(tmp_path)
    (repo / "real").mkdir()
    (repo / "lnk").symlink_to("real")
    (repo / ".gitignore").write_text("lnk/\nreal/\n")
    assert _git_check_ignore(repo, ["lnk", "real"]) == {
        "lnk": None,
        "real": (".gitignore", "real/"),
    }
    r = rules("lnk/\nreal/\n")
    assert not r.ignored("lnk", False)
    assert r.ignored("real", True)


# --------------------------------------------------------------------------
# Wildcards


WILDCARD_CASES = [
    ("*.py", "a.py", True),
    ("*.py", "dir/a.py", True),
    ("*.py", "a.pyc", False),
    ("a*", "a", True),
    ("*", "anything/at/all", True),
    ("a/*", "a/b", True),
    ("a/*", "a/b/c", True),  # via the excluded parent a/b
    ("a/*/c", "a/b/c", True),
    ("a/*/c", "a/b/x/c", False),
    ("a*b/c", "a/b/c", False),  # "*" never matches "/"
    ("?.txt", "a.txt", True),
    ("?.txt", "ab.txt", False),
    ("?.txt", ".txt", False),
    ("a?b/x", "a/b/x", False),
    ("[abc].txt", "b.txt", True),
    ("[abc].txt", "d.txt", False),
    ("[a-c].txt", "b.txt", True),
    ("[a-c].txt", "d.txt", False),
    ("[!a-c].txt", "d.txt", True),
    ("[!a-c].txt", "a.txt", False),
    ("[^a-c].txt", "d.txt", True),
    ("[^a-c].txt", "b.txt", False),
    ("[]].txt", "].txt", True),
    ("[!]].txt", "].txt", False),
    ("[!]].txt", "a.txt", True),
    ("[a-].txt", "-.txt", True),
    ("[-a].txt", "-.txt", True),
    ("[-b].txt", "a.txt", False),  # "-" first is literal, not a range
    ("[a-c-e].txt", "d.txt", False),  # no range right after a range
    ("[a-c-e].txt", "-.txt", True),
    ("[c-a].txt", "b.txt", False),  # reversed range: empty
    ("[[:digit:]]x", "7x", True),
    ("[[:digit:]]x", "ax", False),
    ("[[:alpha:][:digit:]]x", "ax", True),
    ("[[:upper:]]*", "Readme", True),
    ("[[:upper:]]*", "readme", False),
    ("[[:space:]]x", " x", True),
    ("[[:bogus:]]x", "bx", False),  # unknown class: the pattern never matches
    ("[[:a]x", ":x", True),  # no ":]": a plain set holding "[", ":", "a"
    ("[ab", "[ab", False),  # unclosed: never matches
    ("[ab", "a", False),
    ("a[/]b", "a/b", False),  # a set never matches "/"
    ("a[!x]b", "a/b", False),
    ("\\*", "*", True),
    ("\\*", "a", False),
    ("\\?", "?", True),
    ("\\[a]", "[a]", True),
    ("\\a", "a", True),
    ("[\\]]", "]", True),
    ("[a\\-z]", "-", True),
    ("[a\\-z]", "m", False),
    ("foo.[ch]", "foo.c", True),
    ("é", "é", True),
    ("?", "é", False),  # git matches bytes: "é" is two
    ("??", "é", True),
    ("*", ".hidden", True),  # no special case for dot files
]


@pytest.mark.parametrize(("pattern", "path", "expected"), WILDCARD_CASES)
def test_wildcards(pattern: str, path: str, expected: bool) -> None:
    assert ign(rules(pattern + "\n"), path) is expected


def test_wildcards_work_on_non_utf8_names() -> None:
    name = b"caf\xe9.txt".decode("utf-8", "surrogateescape")
    assert ign(rules("caf?.txt\n"), name)
    assert ign(rules(name + "\n"), name)


def test_newline_in_a_name_is_an_ordinary_character() -> None:
    assert ign(rules("a*b\n"), "a\nb")
    assert ign(rules("a?b\n"), "a\nb")


# --------------------------------------------------------------------------
# Double asterisk


DOUBLE_STAR_CASES = [
    ("**/foo", "foo", False, True),
    ("**/foo", "a/b/foo", False, True),
    ("**/foo/bar", "foo/bar", False, True),
    ("**/foo/bar", "x/foo/bar", False, True),
    ("**/foo/bar", "x/foo/y/bar", False, False),
    ("abc/**", "abc", True, False),  # the inside, not the directory itself
    ("abc/**", "abc/x", False, True),
    ("abc/**", "abc/x/y/z", False, True),
    ("a/**/b", "a/b", False, True),
    ("a/**/b", "a/x/b", False, True),
    ("a/**/b", "a/x/y/b", False, True),
    ("a/**/b", "a/xb", False, False),
    ("a/**/b", "x/a/b", False, False),
    ("**", "a/b/c", False, True),
    ("**/", "a", True, True),
    ("**/", "a", False, False),
    ("a/**/", "a/b", True, True),
    ("a/**/", "a/b", False, False),
    ("/**/x", "x", False, True),
    ("a/**/**/b", "a/b", False, True),
    ("a/**/**/b", "a/x/y/b", False, True),
    # Any other "**" is a "*"...
    ("a/x**y/b", "a/xzy/b", False, True),
    ("a/x**y/b", "a/x/y/b", False, False),
    ("foo**", "foobar", False, True),
    ("**foo", "a/xfoo", False, True),
    # ...except right after the literal prefix git compares apart
    # (match_pathname): then git treats it as leading.
    ("a**/b", "a/b", False, True),
    ("a**/b", "ax/y/b", False, True),
    ("foo/bar**", "foo/barx/z/q", False, True),
    ("foo/x*y**", "foo/xa/yb", False, False),
    ("a/*x**/b", "a/zx/q/b", False, False),  # not after the prefix: a plain "*"
    ("a/*x**/b", "a/zxy/b", False, True),
    ("a/[ab]**/c", "a/a/z/c", False, False),
]


@pytest.mark.parametrize(("pattern", "path", "is_dir", "expected"), DOUBLE_STAR_CASES)
def test_double_asterisk(pattern: str, path: str, is_dir: bool, expected: bool) -> None:
    r = rules(pattern + "\n")
    assert r.ignored_any(path, is_dir) is expected


# --------------------------------------------------------------------------
# Precedence


def test_last_matching_pattern_wins() -> None:
    r = rules("*.txt\n!a*.txt\nab.txt\n")
    assert ign(r, "x.txt")
    assert not ign(r, "a.txt")
    assert ign(r, "ab.txt")


def test_nested_file_applies_to_its_subtree_with_its_own_anchoring() -> None:
    r = rules("*.bag\n").with_file("pkg", "/data/\nlocal.yaml\n")
    assert ign(r, "pkg/data", True)
    assert not ign(r, "pkg/sub/data", True)
    assert not ign(r, "data", True)
    assert ign(r, "pkg/a/b/local.yaml")
    assert not ign(r, "local.yaml")
    assert not ign(r, "other/local.yaml")
    assert ign(r, "pkg/x.bag")


def test_nested_file_does_not_apply_to_its_own_directory() -> None:
    r = IgnoreRules.build(defaults=False).with_file("pkg", "pkg\n*\n")
    assert not ign(r, "pkg", True)
    assert ign(r, "pkg/x")


def test_nested_file_does_not_apply_to_a_sibling_with_a_common_prefix() -> None:
    r = IgnoreRules.build(defaults=False).with_file("pkg", "*.c\n")
    assert not ign(r, "pkg2/a.c")
    assert not ign(r, "pk/a.c")
    assert ign(r, "pkg/a.c")


def test_deeper_file_wins_over_parent_file() -> None:
    r = rules("!*.log\n").with_file("a", "*.log\n").with_file("a/b", "!keep.log\n")
    assert not ign(r, "x.log")
    assert ign(r, "a/x.log")
    assert ign(r, "a/b/x.log")
    assert not ign(r, "a/b/keep.log")
    # ...whatever order the files were added in
    r2 = rules("!*.log\n").with_file("a/b", "!keep.log\n").with_file("a", "*.log\n")
    assert r2 == r
    assert not ign(r2, "a/b/keep.log")


def test_parent_file_still_applies_when_nested_file_is_silent() -> None:
    r = rules("*.o\n").with_file("a", "*.tmp2\n").with_file("a/b", "x\n")
    assert ign(r, "a/b/c/z.o")
    assert ign(r, "a/b/c/z.tmp2")


def test_command_line_patterns_win_over_every_file() -> None:
    r = (
        IgnoreRules.build(defaults=False, extra=["secret.yaml"])
        .with_file("", "!secret.yaml\n")
        .with_file("a", "!secret.yaml\n")
    )
    assert ign(r, "secret.yaml")
    assert ign(r, "a/b/secret.yaml")


def test_command_line_patterns_are_anchored_at_the_root() -> None:
    r = IgnoreRules.build(defaults=False, extra=["/top", "any", "d/"]).with_file("a", "x\n")
    assert ign(r, "top")
    assert not ign(r, "a/top")
    assert ign(r, "a/b/any")
    assert ign(r, "a/d", True)


def test_command_line_negation_reincludes_a_default() -> None:
    r = IgnoreRules.build(extra=["!*.tmp"])
    assert not ign(r, "a/x.tmp")


def test_file_can_reinclude_a_default() -> None:
    r = IgnoreRules.build().with_file("", "!*.pyc\n")
    assert not ign(r, "a/x.pyc")
    assert ign(r, "a/x.pyo")
    r = IgnoreRules.build().with_file("pkg", "!*.pyc\n")
    assert not ign(r, "pkg/x.pyc")
    assert ign(r, "other/x.pyc")


def test_extra_patterns_are_lines() -> None:
    r = IgnoreRules.build(defaults=False, extra=["#comment", "", "a  ", "\\#b"])
    assert r.to_wire()[-1] == ["", ["a", "\\#b"]]
    with pytest.raises(ValueError, match="one-line"):
        IgnoreRules.build(extra=["a\nb"])
    with pytest.raises(TypeError):
        IgnoreRules.build(extra="*.log")


# --------------------------------------------------------------------------
# Building, replacing, value semantics


def test_with_file_replaces_and_without_file_removes() -> None:
    base = IgnoreRules.build(defaults=False)
    r1 = base.with_file("a", "*.x\n")
    r2 = r1.with_file("a", "*.y\n")
    assert ign(r1, "a/f.x") and not ign(r1, "a/f.y")
    assert ign(r2, "a/f.y") and not ign(r2, "a/f.x")
    assert r2.without_file("a") == base
    assert base.with_file("a", "# only comments\n\n") == base
    assert base.without_file("nope") == base


def test_rules_are_immutable_values() -> None:
    base = IgnoreRules.build()
    derived = base.with_file("", "*.log\n")
    assert not base.ignored("a.log", False)
    assert derived.ignored("a.log", False)
    assert IgnoreRules.build() == base
    assert hash(IgnoreRules.build()) == hash(base)
    assert derived != base
    with pytest.raises(AttributeError):
        base.foo = 1  # type: ignore[attr-defined]
    assert "IgnoreRules(" in repr(derived)


@pytest.mark.parametrize("bad", ["/abs", "a/", "a//b", "./a", "a/../b", "..", ".", "a\0b"])
def test_with_file_rejects_bad_directory_paths(bad: str) -> None:
    with pytest.raises(ValueError):
        IgnoreRules.build().with_file(bad, "x\n")


def test_ignored_any_uses_the_directory_cache_consistently() -> None:
    r = rules("/a/b/\n")
    assert r.ignored_any("a/b/c/d", False)
    assert r.ignored_any("a/b/c", True)
    assert not r.ignored_any("a/c/d", False)
    assert r.ignored_any("a/b/c/d/e", False)
    assert not r.ignored_any("a/c/d/e", False)
    assert not r.ignored_any("a", True)
    assert not r.ignored_any("x", False)


def test_explain() -> None:
    r = IgnoreRules.build(extra=["*.bag"]).with_file("", "build/\n!keep.pyc\n")
    r = r.with_file("pkg", "/gen/\n")
    assert r.explain("a/x.pyc", False) == IgnoreMatch("default", "", "*.pyc", "a/x.pyc", True)
    assert r.explain("a/keep.pyc", False) == IgnoreMatch(
        "file", "", "!keep.pyc", "a/keep.pyc", False
    )
    assert r.explain("pkg/gen/a/b.cpp", False) == IgnoreMatch(
        "file", "pkg", "/gen/", "pkg/gen", True
    )
    assert r.explain("pkg/x.bag", False) == IgnoreMatch("extra", "", "*.bag", "pkg/x.bag", True)
    assert r.explain("pkg/x.cpp", False) is None
    assert "pattern='/gen/'" in repr(r.explain("pkg/gen", True))


# --------------------------------------------------------------------------
# Defaults


@pytest.mark.parametrize(
    ("path", "is_dir"),
    [
        (".git", True),
        (".git", False),  # a gitfile, in submodules and worktrees
        ("pkg/.git", False),
        ("pkg/.git", True),
        (".hg", True),
        (".svn", True),
        (".bzr", True),
        ("pkg/scripts/__pycache__", True),
        ("pkg/scripts/node.pyc", False),
        ("pkg/scripts/node.pyo", False),
        ("pkg/src/node.cpp.swp", False),
        ("pkg/src/node.cpp.swo", False),
        ("pkg/src/node.cpp.swx", False),
        ("pkg/src/.node.cpp.swp", False),
        ("pkg/src/.node.cpp.swn", False),
        ("pkg/src/4913", False),
        ("pkg/src/node.cpp~", False),
        ("pkg/src/.#node.cpp", False),
        ("pkg/src/#node.cpp#", False),
        ("pkg/src/.node.cpp.kate-swp", False),
        ("pkg/src/node.cpp.tmp", False),
        ("pkg/src/node.cpp.___jb_tmp___", False),
        ("pkg/src/node.cpp.___jb_old___", False),
        ("pkg/src/.goutputstream-XYZ123", False),
        ("pkg/.DS_Store", False),
        (".fetchsync", True),
        ("pkg/src/.node.cpp.fetchsync-tmp-1234", False),
    ],
)
def test_defaults_exclude(path: str, is_dir: bool) -> None:
    r = IgnoreRules.build()
    assert r.ignored_any(path, is_dir)
    match = r.explain(path, is_dir)
    assert match is not None and match.origin == "default"


@pytest.mark.parametrize(
    ("path", "is_dir"),
    [
        ("pkg/CATKIN_IGNORE", False),
        ("pkg/COLCON_IGNORE", False),
        ("pkg/AMENT_IGNORE", False),
        (IGNORE_FILENAME, False),
        ("pkg/" + IGNORE_FILENAME, False),
        ("pkg/.gitignore", False),
        ("pkg/.gitmodules", False),
        ("pkg/.gitattributes", False),
        ("build", True),
        ("devel", True),
        ("install", True),
        ("pkg/src/node.cpp", False),
        ("pkg/scripts/node.py", False),
        ("pkg/package.xml", False),
        ("pkg/CMakeLists.txt", False),
        ("pkg/launch/robot.launch", False),
        ("pkg/.clang-format", False),
        ("pkg/src/.hidden_config.yaml", False),
        ("pkg/src/49130", False),
        ("pkg/src/#notes", False),
        ("pkg/src/node.swp.cpp", False),
        ("pkg/.fetchsync", False),  # only the directory
        ("pkg/__pycache__", False),
    ],
)
def test_defaults_keep(path: str, is_dir: bool) -> None:
    assert not IgnoreRules.build().ignored_any(path, is_dir)


def test_defaults_are_normalized_lines_with_a_reason_each() -> None:
    assert len(set(DEFAULT_PATTERNS)) == len(DEFAULT_PATTERNS)
    # Each survives the parser unchanged (no accidental comment such as "#*#").
    assert IgnoreRules.from_wire([["", list(DEFAULT_PATTERNS)], ["", []]]) == IgnoreRules.build()
    source = MODULE.read_text()
    block = source[
        source.index("DEFAULT_PATTERNS: ") : source.index(
            "\n)\n", source.index("DEFAULT_PATTERNS: ")
        )
    ]
    assert block.count("#") >= 10  # documented, not a bare list


def test_without_defaults_nothing_is_excluded_but_version_control() -> None:
    r = IgnoreRules.build(defaults=False)
    assert r.ignored_any(".git", True)  # see the test below
    assert not r.ignored_any("a.pyc", False)


HOSTILE = "!.git\n!.git/**\n!.hg/\n!**/.svn\n!.bzr\n!*\n"


@pytest.mark.parametrize("where", ["root", "nested", "extra"])
def test_no_rule_re_includes_version_control_directories(where: str) -> None:
    """Issue 22 item 10: a hostile robot's ``.fetchsyncignore`` (or anyone's rules) holding
    ``!.git`` and ``!.git/**`` must never bring ``.git/config`` (its ``core.fsmonitor``
    runs on the laptop at the next git prompt)."""
    base = IgnoreRules.build()
    if where == "root":
        r = base.with_file("", HOSTILE)
    elif where == "nested":
        r = base.with_file("pkg", HOSTILE)
    else:
        r = IgnoreRules.build(extra=HOSTILE.splitlines())
    r = IgnoreRules.from_wire(r.to_wire())  # as the rules travel between the ends
    for vcs in (".git", ".hg", ".svn", ".bzr"):
        for top in ("", "pkg/"):
            assert r.ignored(f"{top}{vcs}", True) and r.ignored(f"{top}{vcs}", False)
            assert r.ignored(f"{top}{vcs}/config", False)
            assert r.ignored_any(f"{top}{vcs}/hooks/pre-commit", False)
    assert not r.ignored("pkg/.gitignore", False) and not r.ignored("pkg/my.git", True)
    assert not r.ignored("pkg/.github", True) and not r.ignored(".git-blame-ignore-revs", False)


def test_pull_never_brings_a_robots_git_directory(tmp_path: Path) -> None:
    import subprocess
    import sys

    env = local_env(
        tmp_path,
        make_ws=False,
        FETCHSYNC_LOCAL_ROBOT_HOME=str(tmp_path / "robot"),
        FETCHSYNC_REMOTE_WORKSPACE="~/ws",
    )
    (tmp_path / "ws/src/pkg").mkdir(parents=True)
    (tmp_path / "ws/src/pkg/package.xml").write_text("<package/>\n")
    robot = tmp_path / "robot/ws/src"
    for top in (robot, robot / "pkg"):
        (top / ".git/hooks").mkdir(parents=True)
        (top / ".git/config").write_text("[core]\n\tfsmonitor = touch /tmp/pwned\n")
        (top / ".git/hooks/post-checkout").write_text("#!/bin/sh\nid\n")
        (top / ".hg").mkdir()
        (top / ".hg/hgrc").write_text("[hooks]\n")
    (robot / ".fetchsyncignore").write_text(HOSTILE.replace("!*\n", ""))
    (robot / "pkg/.fetchsyncignore").write_text(HOSTILE.replace("!*\n", ""))
    (robot / "pkg/robot_only.txt").write_text("from the robot\n")
    proc = subprocess.run(
        [sys.executable, "-m", "fetchsync", "pull", "--yes"],
        env=env,
        capture_output=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr.decode()
    local = tmp_path / "ws/src"
    assert (local / "pkg/robot_only.txt").exists()  # the pull did happen
    found = [
        str(p.relative_to(local))
        for p in local.rglob("*")
        if {".git", ".hg", ".svn", ".bzr"} & set(p.relative_to(local).parts)
    ]
    assert found == []


# --------------------------------------------------------------------------
# Wire


def test_wire_round_trip_through_json() -> None:
    r = (
        IgnoreRules.build(extra=["*.bag", "!keep.bag"])
        .with_file("", "build/\n\\#x\nfoo\\ \n")
        .with_file("pkg/a", "x\n")
        .with_file("pkg", "/gen/\n")
        .with_file("caf\xe9", "*.o\n")
    )
    wire = r.to_wire()
    back = IgnoreRules.from_wire(json.loads(json.dumps(wire)))
    assert back == r
    assert back.to_wire() == wire
    assert [e[0] for e in wire] == ["", "", "caf\xe9", "pkg", "pkg/a", ""]
    assert wire[0] == ["", list(DEFAULT_PATTERNS)]
    assert wire[-1] == ["", ["*.bag", "!keep.bag"]]
    for path in ("pkg/gen", "pkg/a/x", "foo ", "#x", "a/keep.bag", "caf\xe9/z.o"):
        assert back.ignored_any(path, True) == r.ignored_any(path, True)


def test_wire_of_empty_rules() -> None:
    r = IgnoreRules.build(defaults=False)
    assert r.to_wire() == [["", []], ["", []]]
    assert IgnoreRules.from_wire([["", []], ["", []]]) == r


def test_wire_accepts_tuples_and_drops_empty_files() -> None:
    r = IgnoreRules.from_wire((("", ()), ("a", ()), ("", ("x",))))
    assert r == IgnoreRules.build(defaults=False, extra=["x"])


@pytest.mark.parametrize(
    "obj",
    [
        None,
        "",
        {},
        [],
        [["", []]],
        [["", []], ["", []], 3],
        [["", []], ["", [], 1]],
        [["", []], [""]],
        [["", "x"], ["", []]],
        [["", [1]], ["", []]],
        [["", ["a\nb"]], ["", []]],
        [["", ["# comment"]], ["", []]],
        [["", ["trailing "]], ["", []]],
        [["", [""]], ["", []]],
        [["", ["a\r"]], ["", []]],
        [["", ["a\0"]], ["", []]],
        [[None, []], ["", []]],
        [["a", []], ["", []]],
        [["", []], ["a", []]],
        [["", []], ["/abs", ["x"]], ["", []]],
        [["", []], ["a/../b", ["x"]], ["", []]],
        [["", []], ["a/", ["x"]], ["", []]],
        [["", []], ["a/b", ["x"]], ["a", ["x"]], ["", []]],
        [["", []], ["a", ["x"]], ["a", ["y"]], ["", []]],
        [["", []], ["", ["x"]], ["", ["y"]], ["", []]],
    ],
)
def test_from_wire_rejects_bad_shapes(obj: object) -> None:
    with pytest.raises(ValueError):
        IgnoreRules.from_wire(obj)


# --------------------------------------------------------------------------
# Reading ignore files


def test_read_ignore_file(tmp_path: Path) -> None:
    (tmp_path / IGNORE_FILENAME).write_text("*.log\n")
    (tmp_path / "a" / "b").mkdir(parents=True)
    (tmp_path / "a" / "b" / IGNORE_FILENAME).write_bytes(b"caf\xe9\n")
    assert read_ignore_file(str(tmp_path), "") == "*.log\n"
    assert read_ignore_file(str(tmp_path), "a") is None
    assert read_ignore_file(str(tmp_path), "missing/dir") is None
    text = read_ignore_file(str(tmp_path), "a/b")
    assert text is not None
    r = IgnoreRules.build().with_file("a/b", text)
    assert r.ignored(b"a/b/caf\xe9".decode("utf-8", "surrogateescape"), False)
    assert not r.ignored("a/b/caf\xe9", False)  # the UTF-8 "é" is other bytes


def test_read_ignore_file_does_not_follow_symlinks(tmp_path: Path) -> None:
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / IGNORE_FILENAME).write_text("secret\n")
    root = tmp_path / "root"
    root.mkdir()
    (root / IGNORE_FILENAME).symlink_to(outside / IGNORE_FILENAME)
    (root / "lnk").symlink_to(outside)
    assert read_ignore_file(str(root), "") is None
    assert read_ignore_file(str(root), "lnk") is None


def test_read_ignore_file_skips_non_regular_files(tmp_path: Path) -> None:
    (tmp_path / "d" / IGNORE_FILENAME).mkdir(parents=True)
    assert read_ignore_file(str(tmp_path), "d") is None
    (tmp_path / "f").mkdir()
    os.mkfifo(tmp_path / "f" / IGNORE_FILENAME)  # must not block
    assert read_ignore_file(str(tmp_path), "f") is None
    (tmp_path / "notadir").write_text("")
    assert read_ignore_file(str(tmp_path), "notadir") is None


def test_read_ignore_file_by_path_fallback(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / IGNORE_FILENAME).write_text("x\n")
    (tmp_path / "l").symlink_to(tmp_path / "a")
    fallback = ignore_mod._read_ignore_file_by_path
    assert fallback(str(tmp_path), ["a"]) == "x\n"
    assert fallback(str(tmp_path), ["l"]) is None
    assert fallback(str(tmp_path), ["missing"]) is None


def test_read_ignore_file_limits(tmp_path: Path) -> None:
    (tmp_path / IGNORE_FILENAME).write_bytes(b"#" * (MAX_IGNORE_FILE_SIZE + 1))
    with pytest.raises(ValueError, match="larger"):
        read_ignore_file(str(tmp_path), "")
    with pytest.raises(ValueError):
        read_ignore_file(str(tmp_path), "../x")
    with pytest.raises(FileNotFoundError):
        read_ignore_file(str(tmp_path / "no-root"), "")


# --------------------------------------------------------------------------
# Against git itself


def _git_env(home: Path) -> dict[str, str]:
    env = dict(os.environ)
    # No user or system configuration (core.excludesFile, core.ignorecase).
    env.update(
        HOME=str(home),
        XDG_CONFIG_HOME=str(home),
        GIT_CONFIG_NOSYSTEM="1",
        GIT_CONFIG_GLOBAL=os.devnull,
        GIT_CONFIG_SYSTEM=os.devnull,
        LC_ALL="C",
    )
    return env


def _git_repo(tmp_path: Path) -> Path:
    if shutil.which("git") is None:
        pytest.skip("git not installed")
    repo = tmp_path / "repo"
    repo.mkdir()
    subprocess.run(["git", "init", "-q", str(repo)], check=True, env=_git_env(tmp_path))
    (repo / ".git" / "info" / "exclude").write_text("")
    return repo


def _git_check_ignore(repo: Path, paths: list[str]) -> dict[str, tuple[str, str] | None]:
    """path -> (source, pattern) of git's deciding pattern (None: no match)."""
    stdin = b"".join(p.encode("utf-8", "surrogateescape") + b"\0" for p in paths)
    proc = subprocess.run(
        ["git", "check-ignore", "--no-index", "--stdin", "-z", "-v", "-n"],
        check=False,
        cwd=repo,
        input=stdin,
        capture_output=True,
        env=_git_env(repo.parent),
    )
    assert proc.returncode in (0, 1), proc.stderr.decode(errors="replace")
    fields = [f.decode("utf-8", "surrogateescape") for f in proc.stdout.split(b"\0")[:-1]]
    assert len(fields) == 4 * len(paths)
    out: dict[str, tuple[str, str] | None] = {}
    for k in range(0, len(fields), 4):
        source, _line, pattern, path = fields[k : k + 4]
        out[path] = (source, pattern) if source else None
    return out


_NAMES = [
    "a", "b", "ab", "ba", "foo", "bar", "foobar", "x.py", "x.pyc", "y.txt", ".hid",
    "#c#", "!bang", "sp ace", "t ", "caf\xe9", "[ab]", "a*b", "back\\s", "-", "]",
    "Up", "7", "tab\t",
]  # fmt: skip


def _segment(rnd: random.Random) -> str:
    name = rnd.choice(_NAMES)
    roll = rnd.random()
    if roll < 0.3:
        return name
    if roll < 0.33:
        return "*"
    if roll < 0.38:
        return "**"
    if roll < 0.48:
        return name[:1] + "*"
    if roll < 0.58:
        return "*" + name[-2:]
    if roll < 0.64:
        return name[:-1] + "?"
    if roll < 0.74:
        cls = rnd.choice(
            ["a-c", "!a", "^b", "ab", "]a", "a-", "-a", "[:alpha:]", "[:digit:]", "\\]", "c-a",
             "[:punct:][:upper:]", "!]", "x-\\z", "[:foo"]
        )  # fmt: skip
        return "[" + cls + "]" + name[1:]
    if roll < 0.8:
        return name + "**"
    if roll < 0.86:
        return "\\" + name
    if roll < 0.9:
        return name.replace(" ", "\\ ")
    if roll < 0.95:
        return "**" + name
    return "".join("\\" + c if c in "*?[\\" else c for c in name)


def _pattern(rnd: random.Random) -> str:
    segments = [_segment(rnd) for _ in range(rnd.choice([1, 1, 1, 2, 2, 3]))]
    while all(seg in ("*", "**") for seg in segments):
        segments = [_segment(rnd)]  # alone, they would exclude everything
    p = "/".join(segments)
    roll = rnd.random()
    if roll < 0.2:
        p = "/" + p
    elif roll < 0.3:
        p = "**/" + p
    roll = rnd.random()
    if roll < 0.2:
        p += "/"
    elif roll < 0.27:
        p += "/**"
    elif roll < 0.3:
        p += "/**/"
    if rnd.random() < 0.25:
        p = "!" + p
    roll = rnd.random()
    if roll < 0.05:
        p += "  "
    elif roll < 0.08:
        p += "\\ "
    elif roll < 0.1:
        p += "\t"
    return p


def _ignore_text(rnd: random.Random) -> str:
    lines = [_pattern(rnd) for _ in range(rnd.randint(8, 20))]
    if rnd.random() < 0.5:
        lines.insert(rnd.randrange(len(lines)), "# a comment")
    if rnd.random() < 0.5:
        lines.insert(rnd.randrange(len(lines)), "")
    eol = "\r\n" if rnd.random() < 0.2 else "\n"
    return eol.join(lines) + (eol if rnd.random() < 0.8 else "")


@pytest.mark.parametrize("seed", range(12))
def test_agrees_with_git_check_ignore(tmp_path: Path, seed: int) -> None:
    rnd = random.Random(seed)
    repo = _git_repo(tmp_path)
    kinds: dict[str, bool] = {}  # path -> is_dir
    while len(kinds) < 400:
        parts = [rnd.choice(_NAMES) for _ in range(rnd.randint(1, 4))]
        for depth in range(1, len(parts)):
            prefix = "/".join(parts[:depth])
            if kinds.get(prefix) is False:
                break
            kinds[prefix] = True
        else:
            path = "/".join(parts)
            if path not in kinds:
                kinds[path] = rnd.random() < 0.3
    for path, is_dir in sorted(kinds.items()):
        target = repo / path.encode("utf-8", "surrogateescape").decode("utf-8", "surrogateescape")
        if is_dir:
            target.mkdir(parents=True, exist_ok=True)
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(b"")
    dirs = [""] + rnd.sample(sorted(p for p, d in kinds.items() if d), 6)
    r = IgnoreRules.build(defaults=False)
    for d in dirs:
        text = _ignore_text(rnd)
        (repo / d / ".gitignore").write_bytes(text.encode("utf-8", "surrogateescape"))
        r = r.with_file(d, text)
        kinds[(d + "/" if d else "") + ".gitignore"] = False

    paths = sorted(kinds)
    git = _git_check_ignore(repo, paths)
    mismatches = []
    excluded = 0
    deciders = set()
    for path in paths:
        expected = git[path]
        match = r.explain(path, kinds[path])
        got = None if match is None else (_source(match), match.pattern)
        git_ignored = _git_ignored(expected)
        excluded += git_ignored
        deciders.add(expected)
        if got != expected or r.ignored_any(path, kinds[path]) != git_ignored:
            mismatches.append((path, kinds[path], expected, got))
    assert not mismatches, (mismatches[:10], r.to_wire())
    # The generator exercises both outcomes and many patterns.
    assert 0.05 * len(paths) < excluded < 0.95 * len(paths)
    assert len(deciders) >= 4


def test_case_tables_agree_with_git(tmp_path: Path) -> None:
    # Each case in its own directory with its own .gitignore: one git call for all.
    repo = _git_repo(tmp_path)
    cases = [(pat, path, False, exp) for pat, path, exp in WILDCARD_CASES]
    cases += DOUBLE_STAR_CASES
    queries = []
    for k, (pattern, path, is_dir, _) in enumerate(cases):
        case = repo / f"case{k}"
        target = case / path
        if is_dir:
            target.mkdir(parents=True)
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(b"")
        (case / ".gitignore").write_text(pattern + "\n")
        queries.append(f"case{k}/{path}")
    git = _git_check_ignore(repo, queries)
    disagree = [case for case, query in zip(cases, queries) if _git_ignored(git[query]) != case[3]]
    assert not disagree


def _git_ignored(decider: tuple[str, str] | None) -> bool:
    return decider is not None and not decider[1].startswith("!")


def _source(match: IgnoreMatch) -> str:
    return (match.dirpath + "/" if match.dirpath else "") + ".gitignore"


def test_character_classes_agree_with_git(tmp_path: Path) -> None:
    if sys.platform != "linux":
        pytest.skip("names with arbitrary bytes need Linux")
    repo = _git_repo(tmp_path)
    names = [(b"c" + bytes([b])).decode("utf-8", "surrogateescape") for b in range(1, 256)]
    names = [n for n in names if n != "c/"]
    for n in names:
        (repo / n).write_bytes(b"")
    classes = ["alnum", "alpha", "blank", "cntrl", "digit", "graph", "lower", "print",
               "punct", "space", "upper", "xdigit"]  # fmt: skip
    text = "".join(f"c[[:{c}:]]\n" for c in classes)
    git = _git_check_ignore(repo, names)  # no .gitignore yet: nothing matches
    assert all(v is None for v in git.values())
    for cls in classes:
        (repo / ".gitignore").write_text(f"c[[:{cls}:]]\n")
        git = _git_check_ignore(repo, names)
        r = rules(f"c[[:{cls}:]]\n")
        assert {n for n in names if r.ignored(n, False)} == {n for n in names if git[n]}, cls
    assert text  # all twelve classes exercised


# --------------------------------------------------------------------------
# Speed


def _tree_paths(n: int) -> list[tuple[str, bool]]:
    rnd = random.Random(0)
    dirs = ["src", "include", "launch", "config", "scripts", "msg", "test", "urdf", "meshes"]
    exts = [".cpp", ".h", ".py", ".launch", ".yaml", ".xml", ".pyc", ".swp", "~", ""]
    out: list[tuple[str, bool]] = []
    while len(out) < n:
        d = "/".join([f"pkg{rnd.randrange(200)}"] + rnd.sample(dirs, rnd.randrange(5)))
        out.append((d, True))
        for _ in range(9):
            out.append((f"{d}/file{rnd.randrange(50)}{rnd.choice(exts)}", False))
    return out[:n]


def test_100k_paths_with_many_nested_files_give_sane_answers() -> None:
    # speed is measured in bench/, not asserted here (timing asserts are flaky)
    paths = _tree_paths(100_000)
    r = IgnoreRules.build(extra=["*.bag"]).with_file("", "*.stl\n!keep.stl\n/build_*/\ndocs/\n")
    for k in range(0, 200, 4):
        r = r.with_file(f"pkg{k}", "*.bag\n/data/\n!data/keep\nsrc/**/gen_*\n")
    n_ignored = sum(r.ignored(p, d) for p, d in paths)
    assert 0 < n_ignored < len(paths)


# --------------------------------------------------------------------------
# Python 3.8 and the standard library only


_PY38_SCRIPT = r"""
import importlib.util, json, sys
spec = importlib.util.spec_from_file_location("fs_ignore", sys.argv[1])
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
assert set(sys.modules) & {"fetchsync"} == set(), "must not import the laptop package"
cases = json.loads(sys.stdin.read())
r = mod.IgnoreRules.from_wire(cases["wire"])
out = {
    "version": list(sys.version_info[:2]),
    "ignored": [r.ignored_any(p, d) for p, d in cases["paths"]],
    "explain": [getattr(r.explain(p, d), "pattern", None) for p, d in cases["paths"]],
    "wire": r.to_wire(),
    "defaults": list(mod.DEFAULT_PATTERNS),
}
print(json.dumps(out))
"""


def test_module_runs_under_python_3_8() -> None:
    if not PY38.exists():
        pytest.skip(f"{PY38} not installed")
    r = (
        IgnoreRules.build(extra=["!keep.pyc"])
        .with_file("", "*.log\n/build/\na/**/b\n[!x]?.c\n")
        .with_file("pkg", "gen/\n!important.log\n")
    )
    paths = [
        ("a.log", False),
        ("pkg/important.log", False),
        ("build", True),
        ("pkg/build", True),
        ("a/x/y/b", False),
        ("yz.c", False),
        ("xz.c", False),
        ("pkg/gen/f", False),
        ("m/.git", False),
        ("keep.pyc", False),
        ("other.pyc", False),
        ("caf\xe9/#x#", False),
    ]
    cases = {"wire": r.to_wire(), "paths": paths}
    proc = subprocess.run(
        [str(PY38), "-I", "-c", _PY38_SCRIPT, str(MODULE)],
        check=False,
        input=json.dumps(cases),
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["version"] == [3, 8]
    assert out["ignored"] == [r.ignored_any(p, d) for p, d in paths]
    assert out["explain"] == [getattr(r.explain(p, d), "pattern", None) for p, d in paths]
    assert out["wire"] == r.to_wire()
    assert out["defaults"] == list(DEFAULT_PATTERNS)


def test_module_needs_nothing_newer_than_python_3_8() -> None:
    vermin = shutil.which("vermin")
    if vermin is None:
        pytest.skip("vermin not installed (pip install vermin)")
    proc = subprocess.run(
        [vermin, "-t=3.8-", "--violations", "--no-tips", str(MODULE)],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_module_imports_only_the_standard_library() -> None:
    import ast

    tree = ast.parse(MODULE.read_text())
    imported: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            imported.add((node.module or "").split(".")[0])
    stdlib = set(getattr(sys, "stdlib_module_names", ())) | {"__future__"}
    assert imported <= stdlib, imported - stdlib
