"""fetch_tools' README workflow, typed verbatim after ``shell-init``, against the test sshd.

fetch_tools' README ("Example Workflow")::

    ufr 0
    fetch create-account --fullname "Not A. Robot"
    fetch push --install-deps --build
    fetch run "roslaunch my_awesome_package do_stuff.launch"
    # Edit code to fix a bug
    fetch push --build "--pkg my_awesome_package"
    fetch run "roslaunch my_awesome_package do_stuff.launch"

The test runs these lines in a real bash (and zsh) that evaluated ``fetchsync
shell-init bash`` (``zsh``), with what a user of this laptop would have set up beforehand: ROS
"sourced" (``ROS_DISTRO=noetic``), ``FETCH_USER``, an ssh config entry for
``freight0`` (the test robot cannot be called that by DNS), the admin login of
the robot (``FETCHSYNC_ADMIN_USER=root``: the test robot has no ``fetch``
account) and the new account's password in ``FETCHSYNC_NEW_PASSWORD`` and,
for ``rosdep install``'s sudo, ``FETCHSYNC_SUDO_PASSWORD`` (no terminal).

The robot has rosdep as a robot has it (Debian's ``python3-rosdep2``,
``/usr/bin/rosdep``), configured offline by the test as robot-side set-up
before the typed lines: the top of the new account's ``~/.bashrc`` (which
bash reads for a command over ssh, before its non-interactive ``return``)
exports ``ROSDEP_SOURCE_PATH`` and ``ROSDISTRO_INDEX_URL``, pointing at a
``sources.list`` and rules in its home (``file://``: ``rosdep update`` needs no
network). The rules map the package's ``<depend>make</depend>`` and catkin to
Debian packages already installed, so ``rosdep install`` finds them satisfied.

Differences from the README, for the test machine's sake:

- the package is a C++ program, run by name (catkin's devel space puts its
  ``bin/`` on PATH), instead of ``roslaunch``, which Debian's catkin lacks.

The account is a real throwaway user on this machine (root only), removed after.
"""

from __future__ import annotations

import os
import secrets
import shlex
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import CATKIN_PACKAGE_XML, clean_env

REPO = Path(__file__).resolve().parents[1]

pytestmark = [
    pytest.mark.ssh,
    pytest.mark.skipif(os.geteuid() != 0, reason="creating an account on the robot needs root"),
    pytest.mark.skipif(
        shutil.which("catkin_make") is None or shutil.which("g++") is None,
        reason="catkin (catkin_make) and g++ not installed",
    ),
    pytest.mark.skipif(shutil.which("bash") is None, reason="bash not installed"),
    pytest.mark.skipif(
        not os.access("/usr/bin/rosdep", os.X_OK) and not os.environ.get("CI"),
        reason="Debian's rosdep (python3-rosdep2) not installed",
    ),
]


@pytest.fixture(params=["bash", "zsh"])
def shell(request: pytest.FixtureRequest) -> str:
    if shutil.which(request.param) is None:
        if os.environ.get("CI"):
            pytest.fail(f"{request.param} is not installed (.ci/run installs it)", pytrace=False)
        pytest.skip(f"{request.param} not installed")
    return str(request.param)


PKG = "my_awesome_package"
DEPEND = "make"  # a rosdep key whose Debian package is installed here (catkin needs it)
PACKAGE_XML = CATKIN_PACKAGE_XML.format(name=PKG).replace(
    "</package>", f"  <depend>{DEPEND}</depend>\n</package>"
)
CMAKELISTS = f"""cmake_minimum_required(VERSION 3.0.2)
project({PKG})
find_package(catkin REQUIRED)
catkin_package()
add_executable(do_stuff src/do_stuff.cpp)
# devel/bin is on PATH once devel/setup.bash is sourced: `fetch run "do_stuff"` finds it
set_target_properties(do_stuff PROPERTIES
  RUNTIME_OUTPUT_DIRECTORY ${{CATKIN_DEVEL_PREFIX}}/${{CATKIN_GLOBAL_BIN_DESTINATION}})
"""
PROGRAM = """#include <cstdio>
int main() {{ std::puts("{message}"); return 0; }}
"""


@pytest.fixture
def robot_user() -> Iterator[str]:
    name = "fswf" + secrets.token_hex(4)
    yield name
    subprocess.run(["userdel", "--remove", "--force", name], capture_output=True, check=False)


def _laptop(ssh_home, tmp_path: Path, user: str) -> dict[str, str]:
    """The laptop: a catkin workspace ~/noetic, freight0 in the ssh config, fetchsync on PATH."""
    home = ssh_home.home
    pkg = home / "noetic" / "src" / PKG
    (pkg / "src").mkdir(parents=True)
    (pkg / "package.xml").write_text(PACKAGE_XML)
    (pkg / "CMakeLists.txt").write_text(CMAKELISTS)
    (pkg / "src" / "do_stuff.cpp").write_text(PROGRAM.format(message="doing stuff, badly"))
    # As a user would: freight0 is the test robot (another Host line for its address).
    config = ssh_home.config.read_text()
    ssh_home.config.write_text(config.replace("Host robot\n", "Host robot freight0\n", 1))
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    wrapper = bin_dir / "fetchsync"  # this checkout's fetchsync, whatever is installed
    wrapper.write_text(f'#!/bin/sh\nexec {shlex.quote(sys.executable)} -m fetchsync "$@"\n')
    wrapper.chmod(0o755)
    password = "Pw-" + secrets.token_urlsafe(12)
    env = {k: v for k, v in clean_env().items() if k not in ("BASH_ENV", "ENV")}
    env.update(
        HOME=str(home),
        PATH=f"{bin_dir}:{os.environ['PATH']}",
        PYTHONPATH=str(REPO),
        ROS_DISTRO="noetic",
        FETCH_USER=user,
        FETCHSYNC_ADMIN_USER="root",
        FETCHSYNC_NEW_PASSWORD=password,
        # the account's sudo password for rosdep (a user types it at the terminal's prompt)
        FETCHSYNC_SUDO_PASSWORD=password,
        # the tests' session settings (no lingering connection master, its own cache)
        FETCHSYNC_PERSIST="0",
        XDG_RUNTIME_DIR=os.environ.get("XDG_RUNTIME_DIR", ""),
        XDG_CACHE_HOME=os.environ.get("XDG_CACHE_HOME", ""),
        XDG_STATE_HOME=str(tmp_path / "st"),
    )
    return env


def _robot_rosdep_offline(home: Path) -> None:
    """The robot account's rosdep, offline: sources in its home, named at the top of its
    ``~/.bashrc`` (what bash reads for a command over ssh, before the non-interactive
    ``return``), as an admin would configure a robot without the internet."""
    entry = home.stat()
    root = home / ".rosdep-offline"
    (root / "sources.list.d").mkdir(parents=True)
    (root / "rules.yaml").write_text(
        "".join(f"{key}:\n  debian: [{key}]\n" for key in ("catkin", DEPEND))
    )
    (root / "sources.list.d" / "10-offline.list").write_text(f"yaml file://{root}/rules.yaml\n")
    (root / "index.yaml").write_text("%YAML 1.1\n---\ndistributions: {}\ntype: index\nversion: 4\n")
    bashrc = home / ".bashrc"
    bashrc.write_text(
        f"export ROSDEP_SOURCE_PATH={shlex.quote(str(root / 'sources.list.d'))}\n"
        f"export ROSDISTRO_INDEX_URL={shlex.quote(f'file://{root}/index.yaml')}\n"
        + bashrc.read_text()
    )
    for path in (root, *root.rglob("*"), bashrc):
        os.chown(path, entry.st_uid, entry.st_gid)


def _typed(
    env: dict[str, str], cwd: Path, line: str, shell: str = "bash"
) -> subprocess.CompletedProcess[str]:
    """One README line, typed in a shell that ran shell-init (and `ufr 0`)."""
    program = f'eval "$(fetchsync shell-init {shell})"\nufr 0 >/dev/null\n{line}\n'
    argv = [shell, "--norc", "--noprofile"] if shell == "bash" else [shell, "-f"]
    return subprocess.run(
        [*argv, "-c", program],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
        stdin=subprocess.DEVNULL,
        check=False,
    )


@pytest.mark.slow
def test_fetch_tools_readme_workflow_runs_as_typed(ssh_home, tmp_path, robot_user, shell) -> None:
    env = _laptop(ssh_home, tmp_path, robot_user)
    cwd = ssh_home.home

    def _step(env: dict[str, str], cwd: Path, line: str) -> subprocess.CompletedProcess[str]:
        return _typed(env, cwd, line, shell)

    # `ufr 0` points ROS_MASTER_URI, and with it fetch, at freight0
    uri = _step(env, cwd, "ufr 0")
    assert uri.stdout == "http://freight0:11311\n", uri.stderr

    made = _step(env, cwd, 'fetch create-account --fullname "Not A. Robot"')
    assert made.returncode == 0, made.stdout + made.stderr
    assert f"create-account: created {robot_user} on freight0" in made.stdout
    assert "workspace: ~/noetic" in made.stdout
    robot_home = Path(os.path.expanduser(f"~{robot_user}"))
    assert robot_home.name == robot_user

    _robot_rosdep_offline(robot_home)
    pushed = _step(env, cwd, "fetch push --install-deps --build")
    assert pushed.returncode == 0, pushed.stdout + pushed.stderr
    assert "rosdep update (on freight0)" in pushed.stderr
    assert "rosdep install --from-paths src --ignore-src -y (on freight0)" in pushed.stderr
    assert "All required rosdeps installed successfully" in pushed.stdout, pushed.stdout
    assert (robot_home / "noetic" / "src" / PKG / "src" / "do_stuff.cpp").is_file()
    built = robot_home / "noetic" / "devel" / "bin" / "do_stuff"
    assert built.is_file()
    assert built.stat().st_uid == robot_home.stat().st_uid  # pushed and built as the account

    ran = _step(env, cwd, 'fetch run "do_stuff"')
    assert ran.returncode == 0, ran.stdout + ran.stderr
    assert ran.stdout.strip().splitlines()[-1] == "doing stuff, badly"

    # Edit code to fix a bug
    (cwd / "noetic" / "src" / PKG / "src" / "do_stuff.cpp").write_text(
        PROGRAM.format(message="doing stuff, well")
    )
    rebuilt = _step(env, cwd, f'fetch push --build "--pkg {PKG}"')
    assert rebuilt.returncode == 0, rebuilt.stdout + rebuilt.stderr
    assert f"catkin_make --pkg {PKG} (on freight0)" in rebuilt.stderr

    ran = _step(env, cwd, 'fetch run "do_stuff"')
    assert ran.returncode == 0, ran.stdout + ran.stderr
    assert ran.stdout.strip().splitlines()[-1] == "doing stuff, well"
