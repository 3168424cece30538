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
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from fetchsync.chores.remote import ros_environment, script, shell_path
from fetchsync.environ import inheritable
from fetchsync.errors import FetchsyncError

if TYPE_CHECKING:
    from fetchsync.config import Target
    from fetchsync.link.transport import Transport

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
    "install/.colcon_install_layout",
    "colcon.meta",
    ".catkin_workspace",
    "src/CMakeLists.txt",
    "build/catkin_make.cache",
    "devel/.catkin",
)
"""Paths, relative to a workspace, whose presence tells how it is built."""

_CATKIN_TOOLS_MARKERS = (".catkin_tools",)
_COLCON_MARKERS = (
    "build/COLCON_IGNORE",
    "install/COLCON_IGNORE",
    "log/COLCON_IGNORE",
    "install/.colcon_install_layout",
    "colcon.meta",
)
_CATKIN_MAKE_MARKERS = (
    ".catkin_workspace",
    "src/CMakeLists.txt",
    "build/catkin_make.cache",
    "devel/.catkin",
)

ROS1, ROS2 = "ros1", "ros2"
"""Prefixes of the probe's lines naming a distribution under /opt/ros (``ros2:humble``)."""

_IGNORE_FILES = ("CATKIN_IGNORE", "COLCON_IGNORE", "AMENT_IGNORE")
_AMENT = re.compile(r"<(buildtool_depend|build_type)>\s*ament_")
_BUILD_TYPE = re.compile(r"<build_type>\s*([A-Za-z0-9_]+)\s*</build_type>")
_CATKIN_BUILDTOOL = re.compile(r"<buildtool_depend>\s*catkin\s*</buildtool_depend>")
_FORMAT = re.compile(r"<package\b[^>]*\bformat\s*=\s*[\"']?(\d+)")
_PKG_NAME = re.compile(r"<name>\s*([^<\s]+)\s*</name>")
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
    password: str | None = field(default=None, repr=False)
    """A password the script's ``sudo -S`` reads: sent as the first line of its stdin."""


# --------------------------------------------------------------------------- detection
@dataclass(frozen=True)
class Choice:
    """The build tool :func:`choose_tool` picked, and why (for the one line that says so)."""

    tool: str
    reason: str


def ros2_reason(text: str) -> str | None:
    """Why the package in ``text`` needs colcon (ament or plain build types, format 3 without
    catkin), or None when catkin builds it."""
    m = _BUILD_TYPE.search(text)
    if m and m.group(1) != "catkin":
        return f"build type {m.group(1)}"
    if _AMENT.search(text):
        return "ament buildtool"
    f = _FORMAT.search(text)
    if f and int(f.group(1)) >= 3 and not _CATKIN_BUILDTOOL.search(text):
        return "package.xml format 3 without catkin"
    return None


def choose_tool(
    markers: Collection[str], manifests: Iterable[str] = (), distros: Collection[str] = ()
) -> Choice:
    """The build tool for a workspace with these ``markers``, package manifests and ROS.

    A workspace configured for catkin_tools (``.catkin_tools/``) uses
    ``catkin build``; one colcon built before (its ``COLCON_IGNORE`` files,
    ``install/.colcon_install_layout``) colcon; one catkin_make built or set
    up before (``.catkin_workspace``, the toplevel ``src/CMakeLists.txt``, its
    caches) catkin_make. A workspace never built is known by its packages:
    ROS 2 ones (``ament_*`` or other non-catkin build types, format 3 without
    catkin) mean colcon, catkin ones catkin_make, as in fetch_tools. With no
    package to tell, the robot's ROS does (``distros``: ``ros2:humble``, ...
    from :func:`marker_probe`): ROS 2 only means colcon; else catkin_make.
    """
    found = set(markers)
    for tool, names in (
        (CATKIN_TOOLS, _CATKIN_TOOLS_MARKERS),
        (COLCON, _COLCON_MARKERS),
        (CATKIN_MAKE, _CATKIN_MAKE_MARKERS),
    ):
        hit = next((m for m in names if m in found), None)
        if hit is not None:
            return Choice(tool, f"the workspace has {hit}")
    catkin_pkg = None
    for text in manifests:
        why = ros2_reason(text)
        name = _PKG_NAME.search(text)
        label = name.group(1) if name else "a package"
        if why is not None:
            return Choice(COLCON, f"{label} is a ROS 2 package ({why})")
        catkin_pkg = catkin_pkg or label
    if catkin_pkg is not None:
        return Choice(CATKIN_MAKE, f"never built, and {catkin_pkg} is a catkin package")
    kinds = {d.split(":", 1)[0] for d in distros}
    if kinds == {ROS2}:
        ros2 = ", ".join(sorted(d.split(":", 1)[1] for d in distros))
        return Choice(COLCON, f"no packages yet, and the robot has ROS 2 only ({ros2})")
    return Choice(CATKIN_MAKE, "nothing tells: catkin_make, as fetch_tools")


def detect_tool(
    markers: Collection[str], manifests: Iterable[str] = (), distros: Collection[str] = ()
) -> str:
    """The tool :func:`choose_tool` picks."""
    return choose_tool(markers, manifests, distros).tool


def local_markers(workspace: Path) -> set[str]:
    """Which :data:`MARKERS` exist in a local workspace."""
    return {m for m in MARKERS if os.path.lexists(workspace / m)}


def marker_probe(workspace: str, *, ros_root: str = "/opt/ros") -> str:
    """A shell command that prints which :data:`MARKERS` exist in ``workspace``, one a line,
    then each distribution under ``ros_root`` as ``ros1:NAME`` or ``ros2:NAME`` (ROS 2 ones
    have an ament index)."""
    names = " ".join(shlex.quote(m) for m in MARKERS)
    root = shlex.quote(ros_root)
    return (
        f'for d in {root}/*/; do if [ -f "${{d}}setup.bash" ]; then '
        f'n=$(basename "$d"); if [ -d "${{d}}share/ament_index" ]; then '
        f'printf "{ROS2}:%s\\n" "$n"; else printf "{ROS1}:%s\\n" "$n"; fi; fi; done; '
        f"cd {shell_path(workspace)} 2>/dev/null || exit 0; for m in {names}; do "
        'if [ -e "$m" ] || [ -L "$m" ]; then printf "%s\\n" "$m"; fi; done'
    )


def split_probe(output: str) -> tuple[set[str], set[str]]:
    """:func:`marker_probe`'s output as (markers, distributions)."""
    markers, distros = set(), set()
    for line in output.split("\n"):
        if line.startswith((ROS1 + ":", ROS2 + ":")):
            distros.add(line)
        elif line in MARKERS:
            markers.add(line)
    return markers, distros


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
    matches = list(_CMAKE_ARGS.finditer(line))
    last = matches[-1] if matches else None
    if last is not None:
        return f"{line[: last.end()]} {define}{line[last.end() :]}"
    return f"{line} --cmake-args {define}"


SUDO_PASSWORD_VAR = "FETCHSYNC_SUDO_PASSWORD"
"""Where ``--install-deps`` takes the robot user's sudo password from without a terminal."""

# What rosdep needs of the environment and sudo's env_reset drops (none of them secret).
_ROSDEP_VARS = (
    "PATH",
    "PYTHONPATH",
    "ROS_DISTRO",
    "ROS_VERSION",
    "ROS_PYTHON_VERSION",
    "ROS_PACKAGE_PATH",
    "ROS_HOME",
    "ROS_OS_OVERRIDE",
    "ROSDEP_SOURCE_PATH",
    "ROSDISTRO_INDEX_URL",
    "AMENT_PREFIX_PATH",
    "CMAKE_PREFIX_PATH",
    "APT_CONFIG",
)


def sudo_line(line: str) -> str:
    """bash running ``line`` as root through ``sudo -S``, which reads the password on stdin.

    The command keeps the variables of :data:`_ROSDEP_VARS` that are set, and
    ``ROS_HOME`` defaults to the login user's ``~/.ros``, so rosdep as root
    reads the index the user's ``rosdep update`` wrote. The password is never
    in a command line or the environment: sudo reads it from the channel.
    """
    names = " ".join(_ROSDEP_VARS)
    return (
        'export ROS_HOME="${ROS_HOME:-$HOME/.ros}"\n'
        "__fetchsync_env=()\n"
        f"for __fetchsync_var in {names}; do\n"
        '  if [ -n "${!__fetchsync_var+x}" ]; then '
        '__fetchsync_env+=("$__fetchsync_var=${!__fetchsync_var}"); fi\n'
        "done\n"
        f"exec sudo -S -p '' -- env \"${{__fetchsync_env[@]}}\" {line}"
    )


def deps_commands() -> list[str]:
    """fetch_tools' rosdep calls: refresh the index, then install what ``src`` needs."""
    return ["rosdep update", "rosdep install --from-paths src --ignore-src -y"]


def plan(
    request: BuildRequest, *, workspace: str, tool: str, sudo_password: str | None = None
) -> list[Step]:
    """The steps ``request`` takes in ``workspace`` (``~`` for the home there), built with ``tool``.

    With ``sudo_password``, ``rosdep install`` runs as root through ``sudo -S``
    (:func:`sudo_line`) instead of calling sudo itself, which would need a terminal.

    Dependencies come first and see the environment ``run`` gives (the
    workspace's own setup first). catkin builds see the workspace's devel
    space when there is one (it chains to what it was built on); colcon
    builds only the distribution, as sourcing a workspace's own install
    before building it is a mistake with colcon.
    """
    steps = []
    if request.install_deps:
        env = ros_environment(workspace)
        update, install = deps_commands()
        steps.append(
            Step(
                what=update,
                script=script(update, environment=env, directory=workspace),
                program="rosdep",
            )
        )
        if sudo_password is None:
            steps.append(
                Step(
                    what=install,
                    program="rosdep",
                    script=script(install, environment=env, directory=workspace),
                )
            )
        else:
            steps.append(
                Step(
                    what=f"sudo {install}",
                    program="rosdep",
                    password=sudo_password,
                    script=script(sudo_line(install), environment=env, directory=workspace),
                )
            )
    spaces: tuple[str, ...] = () if tool == COLCON else ("devel",)
    env = ros_environment(workspace, spaces=spaces)
    for args in request.builds:
        line = build_command(tool, args, request.build_type)
        steps.append(
            Step(
                what=line,
                script=script(line, environment=env, directory=workspace),
                program=line.split()[0],
            )
        )
    return steps


# --------------------------------------------------------------------------- running
class Runner(Protocol):
    where: str
    """Where steps run, for messages (``fetch7``, ``this machine``)."""

    def run(self, step: Step) -> int:
        """Run ``step`` to its end, streaming its output; its exit status."""


@dataclass
class LocalRunner:
    """Runs steps here, with our terminal and streams, and the call's environment
    without its secrets (a build runs every package's scripts; a local rosdep's sudo asks
    on the terminal)."""

    stdout: int = 1
    where: str = "this machine"

    def run(self, step: Step) -> int:
        proc = subprocess.Popen(
            ["bash", "-c", step.script], stdout=self.stdout, env=inheritable(os.environ)
        )
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
    stderr: int = 2

    def run(self, step: Step) -> int:
        from fetchsync.chores.remote import wrap
        from fetchsync.console import NO_STATUS, attach

        channel = self.transport.exec(
            wrap(step.script, tty=self.pty, python=self.python), pty=self.pty
        )
        try:
            if step.password is not None:
                # sudo -S reads its first line; the command after it sees the end of stdin
                channel.send_all(step.password.encode("utf-8") + b"\n")
            status = attach(
                channel,
                pty=self.pty,
                stdin=0 if self.pty and step.password is None else None,
                stdout=self.stdout,
                stderr=self.stderr,
            )
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


def execute(
    steps: Sequence[Step], runner: Runner, *, announce: Callable[[str], None] | None = None
) -> None:
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
            hint = (
                f"is {step.program} installed on {where}, and ROS under /opt/ros? "
                "--build-tool chooses another tool"
            )
    elif step.what.startswith("rosdep update"):
        hint = f"rosdep update downloads the rosdep sources: is {where} online?"
    elif step.program == "rosdep":
        hint = (
            f"rosdep installs system packages with sudo on {where}, which needs a "
            f"terminal to ask for a password, {SUDO_PASSWORD_VAR}, or a sudoers rule"
        )
    return BuildError(
        f"{step.what} failed on {where} with exit status {status}", exit_code=status, hint=hint
    )


def _announcer(stream: int) -> Callable[[str], None]:
    def announce(text: str) -> None:
        os.write(stream, f"fetchsync: {text}\n".encode())

    return announce


def build_on_robot(
    target: Target,
    request: BuildRequest,
    *,
    src: Path,
    accept_fingerprint: str | None = None,
    quiet_stdout: bool = False,
    stdout: int | None = None,
    stderr: int = 2,
) -> None:
    """Run ``request`` in the target's remote workspace, as ``push --build`` does.

    ``src`` is the local ``src/`` just pushed (the robot's is the same): its
    manifests help :func:`detect_tool`. ``quiet_stdout`` sends the build's
    stdout to our stderr (for ``--json``). A terminal on both stdin and stdout
    gives the build a PTY, so sudo (rosdep) can ask for a password. ``stdout`` and
    ``stderr`` are other descriptors for its output (a fleet's per-robot pipes: no PTY).
    """
    from fetchsync.link.connection import remote_python
    from fetchsync.link.session import open_transport

    out = stdout if stdout is not None else 2 if quiet_stdout else 1
    pty = (
        stdout is None
        and not quiet_stdout
        and not target.is_local
        and sys.stdin.isatty()
        and sys.stdout.isatty()
    )
    transport = open_transport(target, accept_fingerprint=accept_fingerprint, persistent=False)
    try:
        runner = TransportRunner(
            transport,
            where=target.robot,
            pty=pty,
            stdout=out,
            python=remote_python(),
            stderr=stderr,
        )
        tool = request.tool
        announce = _announcer(stderr)
        password = None
        if request.install_deps:
            password = _rosdep_sudo(runner, target.remote_workspace, pty=pty)
        if tool == "auto" and request.builds:
            markers, distros = split_probe(runner.probe(marker_probe(target.remote_workspace)))
            choice = choose_tool(markers, manifests(src), distros)
            announce(f"build tool: {choice.tool} ({choice.reason} on {target.robot})")
            tool = choice.tool
        steps = plan(request, workspace=target.remote_workspace, tool=tool, sudo_password=password)
        execute(steps, runner, announce=announce)
    finally:
        transport.close()


def deps_probe(workspace: str) -> str:
    """A command printing whether rosdep is found in ``workspace``'s ROS environment, the
    user's uid, and whether sudo needs a password (``rosdep=missing``, ``uid=N``, ``sudo=...``)."""
    body = (
        "command -v rosdep >/dev/null 2>&1 || echo rosdep=missing\n"
        'echo "uid=$(id -u)"\n'
        "if ! command -v sudo >/dev/null 2>&1; then echo sudo=missing\n"
        "elif sudo -n true </dev/null >/dev/null 2>&1; then echo sudo=nopasswd\n"
        "else echo sudo=password; fi"
    )
    lines = script(
        body, environment=ros_environment(workspace, announce=False), directory=workspace
    )
    return f"bash -c {shlex.quote(lines)}"


def _rosdep_sudo(runner: TransportRunner, workspace: str, *, pty: bool) -> str | None:
    """The sudo password ``rosdep install`` needs on the robot, None when it needs none or
    can ask on our terminal; a one-line error when rosdep is missing or nothing can answer."""
    facts = dict(
        line.split("=", 1) for line in runner.probe(deps_probe(workspace)).split() if "=" in line
    )
    where = runner.where
    if facts.get("rosdep") == "missing":
        raise BuildError(
            f"rosdep is not installed on {where}",
            exit_code=127,
            hint=f"on {where}: sudo apt install python3-rosdep && sudo rosdep init",
        )
    if facts.get("uid") == "0" or facts.get("sudo") != "password" or pty:
        return None  # root; sudo without a password (or none at all); sudo asks on our terminal
    from fetchsync.chores.account import check_password

    password = os.environ.get(SUDO_PASSWORD_VAR)
    if not password:
        raise BuildError(
            f"rosdep install needs sudo on {where}, which asks for a password, "
            "and there is no terminal to type it on",
            exit_code=2,
            hint=f"run it at a terminal, or set {SUDO_PASSWORD_VAR} (sent to sudo on its stdin)",
        )
    return check_password(password, what="sudo password")


def build_locally(workspace: Path, request: BuildRequest, *, quiet_stdout: bool = False) -> None:
    """Run ``request`` in the local ``workspace``, as ``pull --build`` does."""
    tool = request.tool
    announce = _announcer(2)
    if tool == "auto" and request.builds:
        choice = choose_tool(local_markers(workspace), manifests(workspace / "src"))
        announce(f"build tool: {choice.tool} ({choice.reason} here)")
        tool = choice.tool
    steps = plan(request, workspace=str(workspace), tool=tool)
    execute(steps, LocalRunner(stdout=2 if quiet_stdout else 1), announce=announce)
