"""Tiny real workspaces for the build tests: two packages, ``beta`` depending on ``alpha``.

``alpha`` exports a header (``alpha/alpha.h``, one ``#define``); ``beta``
builds the program ``beta_hello`` from it, which prints that string. So a
change of alpha's header shows in what the program prints only when the
build tool built alpha before beta and beta again after alpha changed.

- :func:`catkin_workspace`: catkin packages (package.xml format 2), for
  catkin_make and ``catkin build``; ``beta_hello`` lands in
  ``devel/lib/beta/`` (``catkin build`` and catkin_make alike).
- :func:`colcon_workspace`: plain CMake packages (package.xml format 3,
  ``<build_type>cmake</build_type>``), which colcon builds with no ROS
  installed; ``beta_hello`` is installed to ``install/beta/bin``, on the
  ``PATH`` of ``install/setup.bash``.
"""

from __future__ import annotations

from pathlib import Path

GREETING = "hello from alpha"

# The system's Python has catkin's modules; a python3 of pyenv or a venv first on
# PATH (CI, and the robot's login shell here) has not, and CMake would find that one.
SYSTEM_PYTHON_DEFINE = "-DPYTHON_EXECUTABLE=/usr/bin/python3"

_CATKIN_XML = """<?xml version="1.0"?>
<package format="2">
  <name>{name}</name>
  <version>0.0.1</version>
  <description>A package for fetchsync's build tests.</description>
  <maintainer email="dev@example.com">dev</maintainer>
  <license>BSD</license>
  <buildtool_depend>catkin</buildtool_depend>
{depends}</package>
"""

_CMAKE_XML = """<?xml version="1.0"?>
<package format="3">
  <name>{name}</name>
  <version>0.0.1</version>
  <description>A package for fetchsync's build tests.</description>
  <maintainer email="dev@example.com">dev</maintainer>
  <license>BSD</license>
{depends}  <export>
    <build_type>cmake</build_type>
  </export>
</package>
"""

_CATKIN_ALPHA = """cmake_minimum_required(VERSION 3.0.2)
project(alpha)
find_package(catkin REQUIRED)
catkin_package(INCLUDE_DIRS include)
"""

_CATKIN_BETA = """cmake_minimum_required(VERSION 3.0.2)
project(beta)
find_package(catkin REQUIRED COMPONENTS alpha)
catkin_package()
include_directories(${catkin_INCLUDE_DIRS})
add_executable(beta_hello src/hello.cpp)
"""

_CMAKE_ALPHA = """cmake_minimum_required(VERSION 3.5)
project(alpha NONE)
install(DIRECTORY include/ DESTINATION include)
file(WRITE ${CMAKE_CURRENT_BINARY_DIR}/alphaConfig.cmake
     "set(alpha_INCLUDE_DIRS \\${CMAKE_CURRENT_LIST_DIR}/../../../include)\\n")
install(FILES ${CMAKE_CURRENT_BINARY_DIR}/alphaConfig.cmake DESTINATION share/alpha/cmake)
"""

_CMAKE_BETA = """cmake_minimum_required(VERSION 3.5)
project(beta CXX)
find_package(alpha REQUIRED)
include_directories(${alpha_INCLUDE_DIRS})
add_executable(beta_hello src/hello.cpp)
install(TARGETS beta_hello DESTINATION bin)
"""

_HELLO = """#include <cstdio>
#include <alpha/alpha.h>
int main() { std::puts(ALPHA_GREETING); return 0; }
"""


def set_greeting(src: Path, text: str) -> None:
    """Rewrite alpha's header so that ``beta_hello`` prints ``text``."""
    (src / "alpha/include/alpha/alpha.h").write_text(f'#define ALPHA_GREETING "{text}"\n')


def _write(root: Path, *, xml: str, alpha: str, beta: str) -> Path:
    src = root / "src"
    (src / "alpha/include/alpha").mkdir(parents=True)
    (src / "beta/src").mkdir(parents=True)
    (src / "alpha/package.xml").write_text(xml.format(name="alpha", depends=""))
    (src / "beta/package.xml").write_text(
        xml.format(name="beta", depends="  <depend>alpha</depend>\n")
    )
    (src / "alpha/CMakeLists.txt").write_text(alpha)
    (src / "beta/CMakeLists.txt").write_text(beta)
    (src / "beta/src/hello.cpp").write_text(_HELLO)
    set_greeting(src, GREETING)
    return root


def catkin_workspace(root: Path) -> Path:
    """Two catkin packages under ``root/src`` (see the module's docstring)."""
    return _write(root, xml=_CATKIN_XML, alpha=_CATKIN_ALPHA, beta=_CATKIN_BETA)


def colcon_workspace(root: Path) -> Path:
    """Two plain CMake packages under ``root/src`` (see the module's docstring)."""
    return _write(root, xml=_CMAKE_XML, alpha=_CMAKE_ALPHA, beta=_CMAKE_BETA)
