"""fetchsync lint: the real pycodestyle, cpplint and catkin_lint on small workspaces."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from fetchsync.chores.lint import (
    CPPLINT,
    PYCODESTYLE,
    classify,
    resolve_targets,
    run_catkin_lint,
)
from fetchsync.cli import cli

sys.path.insert(0, str(Path(__file__).resolve().parent))
from helpers import fetchsync

REPO = Path(__file__).resolve().parent.parent
ROSLINT_LINE = (
    "lint: style roslint (fetch_tools' rules: pep8 at 79 columns, roslint's cpplint, "
    "catkin_lint -W2)"
)

CLEAN_PY = '"""A clean module."""\n\n\ndef answer():\n    return 42\n'
# A 110-character line: fine by roslint's cpplint (120), not by pep8's 79 as fetch_tools ran it.
LONG_OK = "\n\nx = '" + "a" * 104 + "'\n"
BAD_PY = "import os\ndef f():\n    return os.sep\n" + "y = '" + "b" * 130 + "'\n"

CLEAN_CPP = """\
// Copyright 2024 Example
#include <pkg_a/thing.h>
#include <iostream>
#include <string>

namespace pkg_a
{

Thing::Thing(const std::string& name) : name_(name)
{
}

}  // namespace pkg_a
"""

# Everything here is Google-style trouble that roslint lets pass: braces on
# their own line, `else` after `}`, access specifiers unindented, include
# order, strtok, a 115-character line.
ROS_STYLE_CPP = """\
// Copyright 2024 Example
#include <string>
#include <cstring>
#include <algorithm>

class Widget
{
public:
  int size() const;
};

int pick(int x)
{
  char buf[] = "a,b";
  char* tok = strtok(buf, ",");
  if (x > 0)
  {
    return 1;
  }
  else
  {
    return tok == nullptr;  // a comment that makes this line long, but under roslint's limit of 120 chars
  }
}
"""

GOOD_HEADER = """\
// Copyright 2024 Example
#ifndef PKG_A_THING_H
#define PKG_A_THING_H

#include <string>

namespace pkg_a
{
class Thing
{
public:
  explicit Thing(const std::string& name);

private:
  std::string name_;
};
}  // namespace pkg_a

#endif  // PKG_A_THING_H
"""

MANIFEST = """\
<?xml version="1.0"?>
<package format="2">
  <name>{name}</name>
  <version>0.1.0</version>
  <description>Moves widgets around for the {name} tests.</description>
  <maintainer email="dev@example.com">Dev</maintainer>
  <license>BSD</license>
  <buildtool_depend>catkin</buildtool_depend>
</package>
"""

CMAKE = """\
cmake_minimum_required(VERSION 3.0.2)
project({name})
find_package(catkin REQUIRED{components})
catkin_package({exports})
"""


def write(path: Path, text: str, mode: int | None = None) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    if mode is not None:
        path.chmod(mode)
    return path


def make_package(src: Path, name: str, *, depends_on: str | None = None) -> Path:
    """A catkin package; with ``depends_on``, used by CMakeLists.txt but not declared."""
    pkg = src / name
    write(pkg / "package.xml", MANIFEST.format(name=name))
    components = f" COMPONENTS {depends_on}" if depends_on else ""
    exports = f"CATKIN_DEPENDS {depends_on}" if depends_on else ""
    write(pkg / "CMakeLists.txt", CMAKE.format(name=name, components=components, exports=exports))
    return pkg


def make_workspace(root: Path) -> Path:
    """ws/src with pkg_a (clean sources) and pkg_b (uses pkg_a without declaring it)."""
    ws = root / "ws"
    src = ws / "src"
    pkg_a = make_package(src, "pkg_a")
    write(pkg_a / "include" / "pkg_a" / "thing.h", GOOD_HEADER)
    write(pkg_a / "src" / "thing.cpp", CLEAN_CPP)
    write(pkg_a / "src" / "pkg_a" / "__init__.py", CLEAN_PY)
    make_package(src, "pkg_b", depends_on="pkg_a")
    return ws


@pytest.fixture(autouse=True)
def _lint_env(tmp_path: Path, clean_process_env: None, monkeypatch: pytest.MonkeyPatch) -> None:
    """No workspace from the developer's environment; catkin_lint's cache in tmp."""
    monkeypatch.setenv("ROS_HOME", str(tmp_path / "ros_home"))
    monkeypatch.chdir(tmp_path)


def run(*args: str) -> Result:
    return CliRunner().invoke(cli, ["lint", *args], catch_exceptions=False)


def finding_lines(result: Result) -> list[str]:
    return [ln for ln in result.output.splitlines() if ": [" in ln]


# --------------------------------------------------------------------------- files


def test_clean_python_file_exits_0(tmp_path: Path) -> None:
    write(tmp_path / "clean.py", CLEAN_PY)
    result = run("clean.py")
    assert result.exit_code == 0, result.output
    assert result.output.splitlines() == [
        ROSLINT_LINE,
        "pycodestyle: no findings (1 file checked)",
        "cpplint: no files to check",
        "catkin_lint: no packages to check",
    ]


def test_python_findings_are_reported_with_exit_1(tmp_path: Path) -> None:
    write(tmp_path / "bad.py", BAD_PY)
    result = run("bad.py")
    assert result.exit_code == 1
    assert finding_lines(result) == [
        "bad.py:2: [pycodestyle] E302 expected 2 blank lines, found 0",
        (
            "bad.py:4: [pycodestyle] E305 expected 2 blank lines after class or function "
            "definition, found 0"
        ),
        "bad.py:4: [pycodestyle] E501 line too long (136 > 79 characters)",
    ]
    assert "pycodestyle: 3 findings in 1 file (1 file checked)" in result.output


def test_max_line_length_option(tmp_path: Path) -> None:
    write(tmp_path / "long.py", CLEAN_PY + LONG_OK)
    result = run("--max-line-length", "100", "long.py")
    assert result.exit_code == 1
    assert finding_lines(result) == [
        "long.py:8: [pycodestyle] E501 line too long (110 > 100 characters)"
    ]


def test_python_script_found_by_shebang(tmp_path: Path) -> None:
    script = write(tmp_path / "node", "#!/usr/bin/env python3\nimport os,sys\n", 0o755)
    write(tmp_path / "run.sh", "#!/bin/sh\necho hi\n")
    assert classify(script) == PYCODESTYLE
    assert classify(tmp_path / "run.sh") is None
    assert classify(write(tmp_path / "a.hpp", "")) == CPPLINT
    result = run("node")
    assert result.exit_code == 1
    assert "node:2: [pycodestyle] E401 multiple imports on one line" in finding_lines(result)


def test_cpp_roslint_filters(tmp_path: Path) -> None:
    write(tmp_path / "ros_style.cpp", ROS_STYLE_CPP)
    assert run("ros_style.cpp").output.splitlines() == [
        ROSLINT_LINE,
        "pycodestyle: no files to check",
        "cpplint: no findings (1 file checked)",
        "catkin_lint: no packages to check",
    ]
    bad = ROS_STYLE_CPP.replace("if (x > 0)", "if(x > 0)").replace(
        "under roslint's limit", "well over roslint's limit of 120 characters, which it reports"
    )
    write(tmp_path / "bad.cpp", bad)
    result = run("bad.cpp")
    assert result.exit_code == 1
    assert finding_lines(result) == [
        "bad.cpp:16: [cpplint] whitespace/parens Missing space before ( in if(",
        "bad.cpp:22: [cpplint] whitespace/line_length Lines should be <= 120 characters long",
    ]


def test_header_guards_follow_ros_style(tmp_path: Path) -> None:
    pkg = make_package(tmp_path / "src", "pkg_a")
    write(pkg / "include" / "pkg_a" / "thing.h", GOOD_HEADER)
    write(
        pkg / "include" / "pkg_a" / "other.h",
        GOOD_HEADER.replace("PKG_A_THING_H", "OTHER_H_INCLUDED"),
    )
    write(pkg / "src" / "local.h", GOOD_HEADER.replace("PKG_A_THING_H", "SRC_LOCAL_H"))
    result = run("--tool", "cpplint", str(pkg))
    assert [ln for ln in finding_lines(result) if "header_guard" in ln] == [
        (
            "src/pkg_a/include/pkg_a/other.h:2: [cpplint] build/header_guard "
            "#ifndef header guard has wrong style, please use: PKG_A_OTHER_H"
        ),
        (
            "src/pkg_a/include/pkg_a/other.h:19: [cpplint] build/header_guard "
            '#endif line should be "#endif  // PKG_A_OTHER_H"'
        ),
    ]


def test_unlintable_or_missing_path_is_a_usage_error(tmp_path: Path) -> None:
    write(tmp_path / "notes.txt", "hello\n")
    result = run("notes.txt")
    assert result.exit_code == 2
    assert result.output == (
        "fetchsync: error: cannot lint notes.txt: not a Python or C/C++ "
        "file, nor a package.xml or CMakeLists.txt of a package\n"
    )
    result = run("./missing.py")
    assert result.exit_code == 2
    assert result.output == (
        "fetchsync: error: cannot lint ./missing.py: no such file or directory\n"
    )


# --------------------------------------------------------------------------- packages


def test_catkin_lint_needs_the_workspace_as_search_path(tmp_path: Path) -> None:
    ws = make_workspace(tmp_path)
    pkg_b = ws / "src" / "pkg_b"
    alone = run_catkin_lint({pkg_b: "pkg_b"}, search_path=())
    assert alone.checked == 1 and alone.findings == []
    with_ws = run_catkin_lint({pkg_b: "pkg_b"}, search_path=[ws / "src"])
    assert {(f.path, f.code, f.message) for f in with_ws.findings} == {
        (str(pkg_b / "package.xml"), "MISSING_DEPEND", "missing build_depend on 'pkg_a'"),
        (str(pkg_b / "package.xml"), "MISSING_DEPEND", "missing build_export_depend on 'pkg_a'"),
    }


def test_package_by_name_reports_missing_sibling_dependency(tmp_path: Path) -> None:
    make_workspace(tmp_path)
    result = run("--workspace", "ws", "pkg_b")
    assert result.exit_code == 1
    assert finding_lines(result) == [
        "ws/src/pkg_b/package.xml: [catkin_lint] MISSING_DEPEND missing build_depend on 'pkg_a'",
        (
            "ws/src/pkg_b/package.xml: [catkin_lint] MISSING_DEPEND "
            "missing build_export_depend on 'pkg_a'"
        ),
    ]
    assert "catkin_lint: 2 findings in 1 file (1 package checked)" in result.output


def test_package_by_name_lints_its_files_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ws = make_workspace(tmp_path)
    write(ws / "src" / "pkg_a" / "scripts" / "node", "#!/usr/bin/env python\nimport os,sys\n")
    write(ws / "src" / "pkg_b" / "scripts" / "other.py", "import os,sys\n")
    monkeypatch.setenv("FETCHSYNC_WORKSPACE", str(ws))  # resolved like the other verbs
    result = run("pkg_a")
    assert result.exit_code == 1
    assert finding_lines(result) == [
        "ws/src/pkg_a/scripts/node:2: [pycodestyle] E231 missing whitespace after ','",
        "ws/src/pkg_a/scripts/node:2: [pycodestyle] E401 multiple imports on one line",
    ]
    assert result.output.splitlines()[-3:] == [
        "pycodestyle: 2 findings in 1 file (2 files checked)",
        "cpplint: no findings (2 files checked)",
        "catkin_lint: no findings (1 package checked)",
    ]


def test_unknown_package_name_is_one_line_with_close_matches(tmp_path: Path) -> None:
    make_workspace(tmp_path)
    result = run("--workspace", "ws", "pkg_c")
    assert result.exit_code == 2
    assert result.output.count("\n") == 1
    assert result.output.startswith(
        "fetchsync: error: cannot lint pkg_c: no such file or "
        "directory, nor a package of that name in "
    )
    assert (
        "did you mean pkg_a, pkg_b?" in result.output
        or "did you mean pkg_b, pkg_a?" in result.output
    )


def test_package_name_without_a_workspace_is_a_config_error() -> None:
    result = run("pkg_a")
    assert result.exit_code == 2
    assert result.output.startswith(
        "fetchsync: error: pkg_a is not a file or directory, so it "
        "names a package, but no workspace given"
    )
    assert result.output.count("\n") == 1


def test_manifest_file_lints_its_package(tmp_path: Path) -> None:
    ws = make_workspace(tmp_path)
    found = resolve_targets(str(ws / "src" / "pkg_b" / "CMakeLists.txt"))
    assert found.packages == {ws / "src" / "pkg_b": "pkg_b"}
    assert found.search_path == [ws / "src"]  # the enclosing workspace, without --workspace
    result = run("ws/src/pkg_b/package.xml")
    assert result.exit_code == 1
    assert "catkin_lint: 2 findings in 1 file (1 package checked)" in result.output


def test_a_package_catkin_lint_cannot_read_is_a_finding(tmp_path: Path) -> None:
    write(
        tmp_path / "ws" / "src" / "broken" / "package.xml",
        '<package format="2"><name>broken</name></package>\n',
    )
    result = run("ws/src")
    assert result.exit_code == 1
    [line] = finding_lines(result)
    assert line.startswith("ws/src/broken: [catkin_lint] failed ")  # catkin_pkg's reason


# --------------------------------------------------------------------------- directories


def test_directory_walk_honours_excludes(tmp_path: Path) -> None:
    ws = make_workspace(tmp_path)
    src = ws / "src"
    bad = "import os,sys\n"
    write(src / "pkg_a" / ".git" / "hook.py", bad)
    write(src / "pkg_a" / "__pycache__" / "cached.py", bad)
    write(src / "pkg_a" / "generated" / "gen.py", bad)
    write(src / ".fetchsyncignore", "generated/\n")
    write(src / "skipped" / "CATKIN_IGNORE", "")
    make_package(src / "skipped", "pkg_skipped")
    write(src / "skipped" / "pkg_skipped" / "x.py", bad)
    os.symlink(src / "pkg_a" / "generated" / "gen.py", src / "pkg_a" / "link.py")
    found = resolve_targets(str(src))
    assert found.python_files == [src / "pkg_a" / "src" / "pkg_a" / "__init__.py"]
    assert sorted(found.packages.values()) == ["pkg_a", "pkg_b"]
    result = run("ws/src")
    assert result.exit_code == 1  # pkg_b's undeclared dependency
    assert [ln.split(":")[0] for ln in finding_lines(result)] == ["ws/src/pkg_b/package.xml"] * 2


def test_tool_option_restricts(tmp_path: Path) -> None:
    ws = make_workspace(tmp_path)
    write(ws / "src" / "pkg_a" / "bad.py", BAD_PY)
    result = run("--tool", "pycodestyle", "--tool", "cpplint", "ws/src")
    assert result.exit_code == 1
    assert {ln.split("] ")[0].split("[")[1] for ln in finding_lines(result)} == {"pycodestyle"}
    assert result.output.splitlines()[-2:] == [
        "pycodestyle: 3 findings in 1 file (2 files checked)",
        "cpplint: no findings (2 files checked)",
    ]
    assert run("--tool", "pylint", "ws/src").exit_code == 2


def test_json_shape(tmp_path: Path) -> None:
    ws = make_workspace(tmp_path)
    write(ws / "src" / "pkg_b" / "bad.py", BAD_PY)
    result = run("--json", "--workspace", "ws", "pkg_b")
    assert result.exit_code == 1
    report = json.loads(result.output)
    assert set(report) == {"tools", "total", "styles"}
    assert report["styles"] == {"roslint": ["pkg_b"]}
    assert set(report["tools"]) == {"pycodestyle", "cpplint", "catkin_lint"}
    assert report["tools"]["cpplint"] == {"files": 0, "findings": []}
    assert report["tools"]["catkin_lint"]["files"] == 1
    assert report["tools"]["pycodestyle"] == {
        "files": 1,
        "findings": [
            {
                "path": "ws/src/pkg_b/bad.py",
                "line": 2,
                "code": "E302",
                "message": "expected 2 blank lines, found 0",
            },
            {
                "path": "ws/src/pkg_b/bad.py",
                "line": 4,
                "code": "E305",
                "message": "expected 2 blank lines after class or function definition, found 0",
            },
            {
                "path": "ws/src/pkg_b/bad.py",
                "line": 4,
                "code": "E501",
                "message": "line too long (136 > 79 characters)",
            },
        ],
    }
    catkin = report["tools"]["catkin_lint"]["findings"]
    assert [(f["path"], f["line"], f["code"]) for f in catkin] == [
        ("ws/src/pkg_b/package.xml", None, "MISSING_DEPEND")
    ] * 2
    assert report["total"] == 5


# --------------------------------------------------------------------------- end to end


def test_end_to_end_subprocess(tmp_path: Path) -> None:
    ws = make_workspace(tmp_path)
    env = {**os.environ, "PYTHONPATH": str(REPO), "FETCHSYNC_WORKSPACE": str(ws)}
    proc = fetchsync("lint", "--json", "pkg_b", env=env, check=False)
    assert proc.returncode == 1, proc.stderr.decode()
    report = json.loads(proc.stdout)
    assert report["total"] == 2
    assert {f["code"] for f in report["tools"]["catkin_lint"]["findings"]} == {"MISSING_DEPEND"}
    proc = fetchsync("lint", "pkg_a", env=env, check=False)
    assert proc.returncode == 0, proc.stdout.decode() + proc.stderr.decode()
    assert proc.stdout.decode().splitlines() == [
        ROSLINT_LINE,
        "pycodestyle: no findings (1 file checked)",
        "cpplint: no findings (2 files checked)",
        "catkin_lint: no findings (1 package checked)",
    ]
    proc = fetchsync("lint", "pkg_zzz", env=env, check=False)
    assert proc.returncode == 2
    assert proc.stderr.decode().count("\n") == 1 and b"Traceback" not in proc.stderr
