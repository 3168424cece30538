"""Building a workspace after a sync, and installing its dependencies, as fetch_tools did.

``push --build`` builds on the robot, ``pull --build`` here. What runs is
decided by pure functions: :func:`detect_tool` picks the build tool from what
the workspace holds, :func:`plan` turns a :class:`BuildRequest` into
:class:`Step` s (each a bash script: ``cd`` to the workspace, source its ROS
environment, run one command). A runner executes the steps, over a transport
(:class:`TransportRunner`) or here (:class:`LocalRunner`), streaming the
output; the first that fails raises :class:`BuildError` with its exit status.
"""

from __future__ import annotations

import logging
import os
import re
import shlex
import subprocess
import sys
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from fetchsync.errors import FetchsyncError
from fetchsync.remote import ros_environment, script, shell_path

if TYPE_CHECKING:
    from fetchsync.config import Target
    from fetchsync.transport import Transport

log = logging.getLogger(__name__)

BUILD_TYPES = ("Debug", "Release", "RelWithDebInfo", "MinSizeRel", "default")
"""fetch_tools' ``--build-type`` choices; ``default`` passes none."""

CATKIN_MAKE, CATKIN_TOOLS, COLCON = "catkin_make", "catkin", "colcon"
TOOLS = ("auto", CATKIN_MAKE, CATKIN_TOOLS, COLCON)
"""``--build-tool`` choices; ``catkin`` is catkin_tools' ``catkin build``."""

MARKERS = (
    ".catkin_tools",
    "build/COLCON_IGNORE",
    "install/COLCON_IGNORE",
    "log/COLCON_IGNORE",
    "colcon.meta",
    "src/CMakeLists.txt",
    "build/catkin_make.cache",
    "devel/.catkin",
)
"""Paths, relative to a workspace, whose presence tells how it is built."""

_IGNORE_FILES = ("CATKIN_IGNORE", "COLCON_IGNORE", "AMENT_IGNORE")
_AMENT = re.compile(r"<(buildtool_depend|build_type)>\s*ament_")
_CMAKE_ARGS = re.compile(r"(?:^|(?<=\s))--cmake-args(?=\s|$)")


class BuildError(FetchsyncError):
    """A build or dependency step failed; ``exit_code`` is that step's exit status."""

    def __init__(self, message: str, *, exit_code: int, hint: str | None = None) -> None:
        super().__init__(message, hint=hint)
        self.exit_code = exit_code


@dataclass(frozen=True)
class BuildRequest:
    """What ``--build``, ``--build-type``, ``--build-tool`` and ``--install-deps`` ask for."""

    builds: tuple[str, ...] = ()
    """Arguments of each build, in order; ``""`` is a build without arguments."""
    build_type: str = "default"
    tool: str = "auto"
    install_deps: bool = False

    def __post_init__(self) -> None:
        if self.build_type not in BUILD_TYPES:
            raise ValueError(f"unknown build type {self.build_type!r}")
        if self.tool not in TOOLS:
            raise ValueError(f"unknown build tool {self.tool!r}")

    def __bool__(self) -> bool:
        return bool(self.builds) or self.install_deps


@dataclass(frozen=True)
class Step:
    """One command run in the workspace, with the ROS environment sourced first."""

    what: str
    """The command as shown to the user (``catkin_make -j4``)."""
    script: str
    """The bash script that runs it."""
    program: str
    """The program it runs (for messages)."""


# --------------------------------------------------------------------------- detection
def detect_tool(markers: Collection[str], manifests: Iterable[str] = ()) -> str:
    """The build tool for a workspace with these ``markers`` and package manifests.

    A workspace configured for catkin_tools (``.catkin_tools/``) uses
    ``catkin build``; one colcon built before (its ``COLCON_IGNORE`` files)
    colcon; one catkin_make built or set up before (the toplevel
    ``src/CMakeLists.txt``, its caches) catkin_make. Else the packages decide:
    ament ones (ROS 2) mean colcon, catkin ones catkin_make, which is also the
    default, as in fetch_tools.
    """
    found = set(markers)
    if ".catkin_tools" in found:
        return CATKIN_TOOLS
    if found & {"build/COLCON_IGNORE", "install/COLCON_IGNORE", "log/COLCON_IGNORE", "colcon.meta"}:
        return COLCON
    if found & {"src/CMakeLists.txt", "build/catkin_make.cache", "devel/.catkin"}:
        return CATKIN_MAKE
    if any(_AMENT.search(text) for text in manifests):
        return COLCON
    return CATKIN_MAKE


def local_markers(workspace: Path) -> set[str]:
    """Which :data:`MARKERS` exist in a local workspace."""
    return {m for m in MARKERS if os.path.lexists(workspace / m)}


def marker_probe(workspace: str) -> str:
    """A shell command that prints which :data:`MARKERS` exist in ``workspace``, one a line."""
    names = " ".join(shlex.quote(m) for m in MARKERS)
    return (f"cd {shell_path(workspace)} 2>/dev/null || exit 0; for m in {names}; do "
            'if [ -e "$m" ] || [ -L "$m" ]; then printf "%s\\n" "$m"; fi; done')


def manifests(src: Path) -> Iterator[str]:
    """The text of every package.xml under ``src``, skipping ignored and hidden directories."""
    for dirpath, dirs, files in os.walk(src):
        if any(name in files for name in _IGNORE_FILES):
            dirs[:] = []
            continue
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        if "package.xml" in files:
            dirs[:] = []  # packages do not nest
            try:
                yield (Path(dirpath) / "package.xml").read_text(encoding="utf-8", errors="replace")
            except OSError:
                continue


# --------------------------------------------------------------------------- commands
def build_command(tool: str, args: str = "", build_type: str = "default") -> str:
    """The command line of one build; ``args`` is shell text, passed on as typed."""
    words = {CATKIN_MAKE: "catkin_make", CATKIN_TOOLS: "catkin build", COLCON: "colcon build"}[tool]
    line = f"{words} {args.strip()}".rstrip()
    if build_type == "default":
        return line
    define = f"-DCMAKE_BUILD_TYPE={build_type}"
    if tool == CATKIN_MAKE:
        return f"{line} {define}"
    # catkin build and colcon take CMake's arguments after --cmake-args; colcon
    # keeps only the last such option, so join an existing one
    last = None
    for last in _CMAKE_ARGS.finditer(line):
        pass
    if last is not None:
        return f"{line[:last.end()]} {define}{line[last.end():]}"
    return f"{line} --cmake-args {define}"


def deps_commands() -> list[str]:
    """fetch_tools' rosdep calls: refresh the index, then install what ``src`` needs."""
    return ["rosdep update", "rosdep install --from-paths src --ignore-src -y"]


def plan(request: BuildRequest, *, workspace: str, tool: str) -> list[Step]:
    """The steps ``request`` takes in ``workspace`` (``~`` for the home there), built with ``tool``.

    Dependencies come first and see the environment ``run`` gives (the
    workspace's own setup first). catkin builds see the workspace's devel
    space when there is one (it chains to what it was built on); colcon
    builds only the distribution, as sourcing a workspace's own install
    before building it is a mistake with colcon.
    """
    steps = []
    if request.install_deps:
        env = ros_environment(workspace)
        for line in deps_commands():
            steps.append(Step(what=line, script=script(line, environment=env, directory=workspace),
                              program="rosdep"))
    spaces: tuple[str, ...] = () if tool == COLCON else ("devel",)
    env = ros_environment(workspace, spaces=spaces)
    for args in request.builds:
        line = build_command(tool, args, request.build_type)
        steps.append(Step(what=line, script=script(line, environment=env, directory=workspace),
                          program=line.split()[0]))
    return steps


# --------------------------------------------------------------------------- running
class Runner(Protocol):
    where: str
    """Where steps run, for messages (``fetch7``, ``this machine``)."""

    def run(self, step: Step) -> int:
        """Run ``step`` to its end, streaming its output; its exit status."""


@dataclass
class LocalRunner:
    """Runs steps here, with our terminal and streams."""

    stdout: int = 1
    where: str = "this machine"

    def run(self, step: Step) -> int:
        proc = subprocess.Popen(["bash", "-c", step.script], stdout=self.stdout)
        try:
            return proc.wait()
        except KeyboardInterrupt:
            # the terminal sent SIGINT to the build too; let it stop, then stop
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            raise


@dataclass
class TransportRunner:
    """Runs steps on a robot, each in its own channel, reaped when interrupted."""

    transport: Transport
    where: str
    pty: bool = False
    stdout: int = 1
    python: str = "python3"

    def run(self, step: Step) -> int:
        from fetchsync.console import NO_STATUS, attach
        from fetchsync.remote import wrap

        channel = self.transport.exec(wrap(step.script, tty=self.pty, python=self.python),
                                      pty=self.pty)
        try:
            status = attach(channel, pty=self.pty, stdin=0 if self.pty else None,
                            stdout=self.stdout)
        finally:
            channel.close()
        return 255 if status == NO_STATUS else status

    def probe(self, command: str) -> str:
        """The stdout of a short command on the robot (its stderr is dropped)."""
        channel = self.transport.exec(command)
        try:
            channel.shutdown_write()
            chunks = []
            while True:
                data = channel.recv(65536)
                if not data:
                    break
                chunks.append(data)
            channel.exit_status()
        finally:
            channel.close()
        return b"".join(chunks).decode("utf-8", "replace")


def execute(steps: Sequence[Step], runner: Runner, *,
            announce: Callable[[str], None] | None = None) -> None:
    """Run ``steps`` in order; raise :class:`BuildError` at the first that fails."""
    for step in steps:
        if announce is not None:
            announce(f"{step.what} (on {runner.where})")
        status = runner.run(step)
        if status != 0:
            raise _failure(step, status, runner.where)


def _failure(step: Step, status: int, where: str) -> BuildError:
    hint = None
    if status == 127:
        if step.program == "rosdep":
            hint = f"is rosdep installed on {where} (python3-rosdep)?"
        else:
            hint = (f"is {step.program} installed on {where}, and ROS under /opt/ros? "
                    "--build-tool chooses another tool")
    elif step.what.startswith("rosdep update"):
        hint = f"rosdep update downloads the rosdep sources: is {where} online?"
    elif step.program == "rosdep":
        hint = (f"rosdep installs system packages with sudo on {where}, which needs a "
                "terminal to ask for a password or a sudoers rule")
    return BuildError(f"{step.what} failed on {where} with exit status {status}",
                      exit_code=status, hint=hint)


def _announcer(stream: int) -> Callable[[str], None]:
    def announce(text: str) -> None:
        os.write(stream, f"fetchsync: {text}\n".encode())
    return announce


def build_on_robot(target: Target, request: BuildRequest, *, src: Path,
                   accept_fingerprint: str | None = None, quiet_stdout: bool = False) -> None:
    """Run ``request`` in the target's remote workspace, as ``push --build`` does.

    ``src`` is the local ``src/`` just pushed (the robot's is the same): its
    manifests help :func:`detect_tool`. ``quiet_stdout`` sends the build's
    stdout to our stderr (for ``--json``). A terminal on both stdin and stdout
    gives the build a PTY, so sudo (rosdep) can ask for a password.
    """
    from fetchsync.connection import remote_python
    from fetchsync.session import open_transport

    out = 2 if quiet_stdout else 1
    pty = not quiet_stdout and not target.is_local and sys.stdin.isatty() and sys.stdout.isatty()
    transport = open_transport(target, accept_fingerprint=accept_fingerprint, persistent=False)
    try:
        runner = TransportRunner(transport, where=target.robot, pty=pty, stdout=out,
                                 python=remote_python())
        tool = request.tool
        if tool == "auto" and request.builds:
            found = runner.probe(marker_probe(target.remote_workspace)).split("\n")
            tool = detect_tool([m for m in found if m], manifests(src))
        steps = plan(request, workspace=target.remote_workspace, tool=tool)
        execute(steps, runner, announce=_announcer(2))
    finally:
        transport.close()


def build_locally(workspace: Path, request: BuildRequest, *, quiet_stdout: bool = False) -> None:
    """Run ``request`` in the local ``workspace``, as ``pull --build`` does."""
    tool = request.tool
    if tool == "auto" and request.builds:
        tool = detect_tool(local_markers(workspace), manifests(workspace / "src"))
    steps = plan(request, workspace=str(workspace), tool=tool)
    execute(steps, LocalRunner(stdout=2 if quiet_stdout else 1), announce=_announcer(2))
