"""fetchsync lint's two styles with the real linters: roslint (fetch_tools' rules exactly) for
catkin packages, ament (ROS 2's) for format 3 / ament_* packages; each clean package lints clean."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from fetchsync.cli import cli

CATKIN_XML = """<?xml version="1.0"?>
<package format="2">
  <name>{name}</name>
  <version>0.1.0</version>
  <description>A catkin package for the lint tests.</description>
  <maintainer email="dev@example.com">Dev</maintainer>
  <license>BSD</license>
  <buildtool_depend>catkin</buildtool_depend>
</package>
"""

CATKIN_CMAKE = """cmake_minimum_required(VERSION 3.0.2)
project({name})
find_package(catkin REQUIRED)
catkin_package()
"""

AMENT_XML = """<?xml version="1.0"?>
<package format="3">
  <name>{name}</name>
  <version>0.1.0</version>
  <description>A ROS 2 package for the lint tests.</description>
  <maintainer email="dev@example.com">Dev</maintainer>
  <license>Apache-2.0</license>
  <buildtool_depend>{buildtool}</buildtool_depend>
  <export>
    <build_type>{buildtool}</build_type>
  </export>
</package>
"""

# Clean by ROS 1's C++ style: every brace that opens a scope on its own line.
ROS1_CPP = """/*
 * Copyright (c) 2026, Dev
 * All rights reserved.
 */

#include <string>
#include <vector>

namespace talker
{

class Counter
{
public:
  explicit Counter(int start) : count_(start) {}

  int next()
  {
    return ++count_;
  }

private:
  int count_;
};

}  // namespace talker

int main(int argc, char** argv)
{
  talker::Counter counter(0);
  std::vector<std::string> names;
  if (argc > 1)
  {
    names.push_back(argv[1]);
  }
  else
  {
    names.push_back("none");
  }
  int n = 0;
  do
  {
    n = counter.next();
  }
  while (n < 3);
  return 0;
}
"""

# Clean by ROS 2's (ament_cpplint's) rules: Google's style, with the copyright line.
ROS2_CPP = """// Copyright 2026 Dev
//
// Licensed under the Apache License, Version 2.0.

#include <cstdio>
#include <string>

namespace talker
{

std::string greeting(const std::string & name)
{
  return "hello " + name;
}

}  // namespace talker

int main()
{
  std::puts(talker::greeting("world").c_str());
  return 0;
}
"""

CLEAN_PY = '''"""Say hello."""


def greeting(name):
    """Return the greeting for ``name``."""
    return 'hello ' + name
'''

SETUP_PY = '''"""Set up the package."""
from setuptools import setup

setup(
    name='py_talker',
    version='0.1.0',
    packages=['py_talker'],
    entry_points={'console_scripts': ['talker = py_talker.talker:main']},
)
'''


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def catkin_package(src: Path, name: str = "cat_talker") -> Path:
    pkg = src / name
    write(pkg / "package.xml", CATKIN_XML.format(name=name))
    write(pkg / "CMakeLists.txt", CATKIN_CMAKE.format(name=name))
    write(pkg / "src/talker.cpp", ROS1_CPP)
    write(pkg / "src/cat_talker/__init__.py", CLEAN_PY)
    return pkg


def ament_python_package(src: Path, name: str = "py_talker") -> Path:
    pkg = src / name
    write(pkg / "package.xml", AMENT_XML.format(name=name, buildtool="ament_python"))
    write(pkg / "setup.py", SETUP_PY)
    write(pkg / f"{name}/__init__.py", "")
    write(pkg / f"{name}/talker.py", CLEAN_PY)
    return pkg


def ament_cmake_package(src: Path, name: str = "cpp_talker") -> Path:
    pkg = src / name
    write(pkg / "package.xml", AMENT_XML.format(name=name, buildtool="ament_cmake"))
    write(pkg / "CMakeLists.txt", f"cmake_minimum_required(VERSION 3.8)\nproject({name})\n")
    write(pkg / "src/talker.cpp", ROS2_CPP)
    return pkg


@pytest.fixture(autouse=True)
def _lint_env(tmp_path: Path, clean_process_env: None, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_HOME", str(tmp_path / "ros_home"))
    monkeypatch.chdir(tmp_path)


def run(*args: str) -> Result:
    return CliRunner().invoke(cli, ["lint", *args], catch_exceptions=False)


def findings(result: Result) -> list[str]:
    return [ln for ln in result.output.splitlines() if ": [" in ln]


ament = pytest.mark.skipif(
    any(importlib.util.find_spec(m) is None for m in ("flake8", "ament_pep257", "ament_cpplint")),
    reason="the ament linters are not installed (pip install -e '.[test]')",
)


# --------------------------------------------------------------------------- roslint
def test_a_clean_catkin_package_lints_clean_with_fetch_tools_rules(tmp_path):
    catkin_package(tmp_path / "src")
    result = run("src/cat_talker")
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0].startswith("lint: style roslint (fetch_tools' rules")
    assert lines[1:] == [
        "pycodestyle: no findings (1 file checked)",
        "cpplint: no findings (1 file checked)",
        "catkin_lint: no findings (1 package checked)",
    ]


def test_roslint_reports_a_brace_that_does_not_stand_alone(tmp_path):
    pkg = catkin_package(tmp_path / "src")
    write(
        pkg / "src/talker.cpp",
        ROS1_CPP.replace("int main(int argc, char** argv)\n{", "int main(int argc, char** argv) {"),
    )
    result = run("--tool", "cpplint", "src/cat_talker")
    assert result.exit_code == 1
    assert findings(result) == [
        "src/cat_talker/src/talker.cpp:28: [cpplint] whitespace/braces when starting a new scope, "
        "{ should be on a line by itself"
    ]


def test_roslint_runs_pep8_as_fetch_tools_did(tmp_path):
    # 80 columns is one too many; pep8's default ignores (E226) were dropped by fetch_tools'
    # --ignore; E266 (`## ` Doxygen comments) was ignored
    write(
        tmp_path / "a.py", '"""Doc."""\n\n## A Doxygen comment.\nx = 1+2\ny = "' + "a" * 74 + '"\n'
    )
    result = run("a.py")
    assert findings(result) == [
        "a.py:4: [pycodestyle] E226 missing whitespace around arithmetic operator",
        "a.py:5: [pycodestyle] E501 line too long (80 > 79 characters)",
    ]


# --------------------------------------------------------------------------- ament
@ament
def test_clean_ros2_packages_lint_clean_with_the_ament_rules_and_no_catkin_lint(tmp_path):
    ament_python_package(tmp_path / "src")
    ament_cmake_package(tmp_path / "src")
    result = run("src")
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0].startswith("lint: style ament (ament_lint_common's rules")
    assert "flake8 with ament_flake8's settings" in lines[0]
    assert lines[1:] == [
        "flake8: no findings (3 files checked)",
        "ament_pep257: no findings (3 files checked)",
        "ament_cpplint: no findings (1 file checked)",
    ]
    assert "catkin_lint" not in result.output


@ament
def test_ament_rules_find_what_ros2_ci_would(tmp_path):
    pkg = ament_python_package(tmp_path / "src")
    write(
        pkg / "py_talker/talker.py",
        CLEAN_PY.replace('"""Return', '"""return') + "\n\nz = '" + "a" * 95 + "'\n",
    )
    cpp = ament_cmake_package(tmp_path / "src")
    write(cpp / "src/talker.cpp", ROS2_CPP.replace("// Copyright 2026 Dev\n", ""))
    result = run("--json", "src")
    assert result.exit_code == 1
    report = json.loads(result.output)
    codes = {
        tool: sorted({f["code"] for f in r["findings"]}) for tool, r in report["tools"].items()
    }
    assert codes == {
        "flake8": ["E501"],
        "ament_pep257": ["D403"],
        "ament_cpplint": ["legal/copyright"],
    }
    assert report["styles"] == {"ament": ["cpp_talker", "py_talker"]}


@ament
def test_auto_gives_each_package_its_style(tmp_path):
    catkin_package(tmp_path / "src")
    ament_python_package(tmp_path / "src")
    result = run("src")
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0].startswith("lint: style roslint for cat_talker; ament for py_talker (")
    assert "catkin_lint: no findings (1 package checked)" in lines  # the catkin one only
    assert "pycodestyle: no findings (1 file checked)" in lines
    assert "flake8: no findings (3 files checked)" in lines
    # a style chosen by hand applies to everything
    result = run("--style", "roslint", "--tool", "catkin_lint", "src")
    assert "catkin_lint: " in result.output and "(2 packages checked)" in result.output
