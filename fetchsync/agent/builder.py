"""``fetchsync watch --build``: rebuild on the robot what each settled batch changed.

After each push that changed something, the agent hands the touched paths
to :meth:`Builder.submit`. They map to packages (the nearest ``package.xml``
above each path, its ``<name>``); the builder thread builds those packages
with the workspace's build tool, detected once from the remote workspace as
``push --build`` does (:func:`fetchsync.chores.build.detect_tool`) unless chosen:

- catkin_make: ``catkin_make ARGS --pkg a b`` (make in those packages only;
  unlike ``--only-pkg-with-deps`` it leaves no whitelist in the CMake cache);
- catkin build: ``catkin build a b ARGS``;
- colcon: ``colcon build --packages-above a b ARGS`` (and what depends on them).

A batch whose packages cannot be known (a rescan) builds the whole workspace.
Each build runs in one channel of the builder's own connection, under the
reaper of :mod:`fetchsync.chores.remote`, with its output (stdout and stderr
merged) streamed line by line through ``say`` as ``build: ...``. A newer
batch cancels a build in progress: the channel closes, the reaper stops the
build's process group on the robot, and the next build (of the union of the
cancelled packages and the new ones) waits on a lock the old build's
processes hold until the last of them is gone, so two builds never share the
build directory. Packages of a failed build are built again with the next
batch; a lost link keeps them for the next push that gets through.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import shlex
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from fetchsync.chores.build import (
    CATKIN_MAKE,
    CATKIN_TOOLS,
    COLCON,
    build_command,
    choose_tool,
    manifests,
    marker_probe,
    split_probe,
)
from fetchsync.chores.remote import ros_environment, script
from fetchsync.config import Target

log = logging.getLogger(__name__)

_NAME = re.compile(rb"<name>\s*([^<\s]+)\s*</name>")
_IGNORE_FILES = ("CATKIN_IGNORE", "COLCON_IGNORE", "AMENT_IGNORE")
ALL = None
"""What :func:`packages_of` returns for "the whole workspace"."""


# --------------------------------------------------------------------------- packages
def package_name(pkg_dir: Path) -> str:
    """The ``<name>`` of the package in ``pkg_dir`` (its directory name if unreadable)."""
    try:
        m = _NAME.search((pkg_dir / "package.xml").read_bytes())
    except OSError:
        m = None
    return m.group(1).decode("utf-8", "replace") if m else pkg_dir.name


def package_above(src: Path, rel: str) -> str | None:
    """The package holding ``src/rel`` (which may be gone): the nearest ``package.xml`` above it."""
    path = src / rel if rel else src
    d = path if path.is_dir() and not path.is_symlink() else path.parent
    src_abs = os.path.abspath(src)
    while True:
        here = os.path.abspath(d)
        if here == src_abs or not here.startswith(src_abs + os.sep):
            return None
        if (d / "package.xml").is_file():
            return package_name(d)
        d = d.parent


def packages_below(root: Path) -> set[str]:
    """Every package under ``root`` (a directory that appeared whole, e.g. a moved package)."""
    found: set[str] = set()
    for dirpath, dirs, files in os.walk(root):
        if any(name in files for name in _IGNORE_FILES):
            dirs[:] = []
            continue
        dirs[:] = [d for d in dirs if not d.startswith(".")]
        if "package.xml" in files:
            dirs[:] = []
            found.add(package_name(Path(dirpath)))
    return found


def packages_of(src: Path, paths: Iterable[str], dirs: Iterable[str] = ()) -> set[str]:
    """The packages holding these touched paths (relative to ``src``) and subtrees."""
    found: set[str] = set()
    for rel in paths:
        name = package_above(src, rel)
        if name is not None:
            found.add(name)
    for rel in dirs:
        name = package_above(src, rel)
        if name is not None:
            found.add(name)
        elif (src / rel).is_dir():
            found |= packages_below(src / rel)
    return found


def package_command(
    tool: str, packages: Iterable[str] | None, args: str = "", build_type: str = "default"
) -> str:
    """The command line that builds ``packages`` (all when None) with ``tool``."""
    args = args.strip()
    if packages is None:
        return build_command(tool, args, build_type)
    names = " ".join(shlex.quote(p) for p in sorted(packages))
    if tool == CATKIN_MAKE:
        # --pkg takes every word up to the next option: it goes last (the build
        # type's -D after it ends it)
        line = f"{args} --pkg {names}".strip()
    elif tool == CATKIN_TOOLS:
        line = f"{names} {args}".strip()  # --cmake-args in ARGS takes all that follows
    elif tool == COLCON:
        # with what depends on them: a changed header or message is seen by its users
        line = f"--packages-above {names} {args}".strip()
    else:
        raise ValueError(f"unknown build tool {tool!r}")
    return build_command(tool, line, build_type)


def lock_prelude(workspace: str) -> str:
    """bash lines taking a lock (``flock``) held by every process of the build until it ends.

    The lock's descriptor is inherited by all the build's processes: a new
    build starts only when the last process of a cancelled one is gone. The
    lock file lives in the robot user's private directory,
    ``$XDG_RUNTIME_DIR/fetchsync`` or else ``~/.cache/fetchsync``, made 0700
    and used only when it is a real directory owned by the user: in a shared
    ``/tmp``, another user could create the file first and hold its lock,
    blocking every build. Without such a directory (or ``flock``), the build
    runs without the lock and says so.
    """
    key = hashlib.sha256(workspace.encode("utf-8", "surrogateescape")).hexdigest()[:16]
    return "\n".join(
        [
            "__fetchsync_lockdir=",
            'if [ -n "${XDG_RUNTIME_DIR:-}" ] && [ -d "$XDG_RUNTIME_DIR" ] && '
            '[ ! -L "$XDG_RUNTIME_DIR" ] && [ -O "$XDG_RUNTIME_DIR" ]; then',
            '  __fetchsync_lockdir="$XDG_RUNTIME_DIR/fetchsync"',
            "else",
            '  __fetchsync_lockdir="$HOME/.cache/fetchsync"',
            "fi",
            '(umask 077; mkdir -p -- "$__fetchsync_lockdir") 2>/dev/null',
            'if [ -d "$__fetchsync_lockdir" ] && [ ! -L "$__fetchsync_lockdir" ] && '
            '[ -O "$__fetchsync_lockdir" ] && chmod 700 -- "$__fetchsync_lockdir" 2>/dev/null && '
            "command -v flock >/dev/null 2>&1 && "
            f'exec 9>>"$__fetchsync_lockdir/build-{key}.lock"; then',
            "  flock 9",
            "else",
            '  echo "fetchsync: warning: no private directory for the build lock'
            ' ($__fetchsync_lockdir); building without it" >&2',
            "fi",
            "unset __fetchsync_lockdir",
        ]
    )


# --------------------------------------------------------------------------- the thread
class Builder:
    """Builds on the robot, in its own thread and over its own connection."""

    def __init__(
        self,
        target: Target,
        *,
        tool: str = "auto",
        build_type: str = "default",
        args: str = "",
        say: Callable[[str], None] | None = None,
        accept_fingerprint: str | None = None,
    ) -> None:
        self.target = target
        self.tool = tool
        self.build_type = build_type
        self.args = args
        self.say = say or (lambda line: log.info("%s", line))
        self.accept_fingerprint = accept_fingerprint
        self.src = target.workspace / "src"
        self.cond = threading.Condition()
        self.stopping = False
        self.dirty: set[str] = set()  # packages to build
        self.dirty_all = False
        self.carry: set[str] = set()  # packages of a failed build, built with the next batch
        self.carry_all = False
        self.running: set[str] | None = None
        self.running_all = False
        self.cancelled = False
        self._channel: Any = None
        self._transport: Any = None
        self._detected: str | None = None
        self.state = "idle"
        self.last: dict[str, Any] | None = None
        self.builds = 0
        self._thread = threading.Thread(target=self._loop, name="fetchsync-build", daemon=True)

    # ------------------------------------------------------------------ from the agent
    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        with self.cond:
            self.stopping = True
            self.cond.notify_all()
        self._cancel()
        self._thread.join(3.0)
        self._close_transport()

    def submit_paths(
        self, paths: Iterable[str], dirs: Iterable[str] = (), *, whole: bool = False
    ) -> None:
        """A batch reached the robot: build what it touched (``whole``: everything)."""
        if whole:
            self.submit(None)
        else:
            self.submit(packages_of(self.src, paths, dirs))

    def submit(self, packages: set[str] | None) -> None:
        """Build ``packages`` (None: the whole workspace) next, cancelling a build in progress."""
        if packages is not None and not packages:
            return
        with self.cond:
            if packages is None:
                self.dirty_all = True
            else:
                self.dirty |= packages
            busy = self.running is not None or self.running_all
            if busy:
                self.cancelled = True
            self.cond.notify_all()
        if busy:
            self._cancel()

    def status(self) -> dict[str, Any]:
        with self.cond:
            return {
                "state": self.state,
                "tool": self._detected or self.tool,
                "building": None if self.running is None else sorted(self.running),
                "pending": "all"
                if self.dirty_all or self.carry_all
                else sorted(self.dirty | self.carry),
                "builds": self.builds,
                "last": self.last,
            }

    # ------------------------------------------------------------------ the thread
    def _cancel(self) -> None:
        channel = self._channel
        if channel is not None:
            try:
                channel.close()
            except Exception:  # already closed or the link is gone: the reaper does the rest
                pass

    def _close_transport(self) -> None:
        transport, self._transport = self._transport, None
        if transport is not None:
            try:
                transport.close()
            except Exception:  # the link is already gone
                pass

    def _loop(self) -> None:
        while True:
            with self.cond:
                while not (self.dirty or self.dirty_all) and not self.stopping:
                    self.cond.wait()
                if self.stopping:
                    return
                whole = self.dirty_all or self.carry_all
                packages = None if whole else self.dirty | self.carry
                self.dirty, self.dirty_all = set(), False
                self.carry, self.carry_all = set(), False
                self.running, self.running_all = (packages or set()), packages is None
                self.cancelled = False
                self.state = "building"
            try:
                outcome = self._build(packages)
            except Exception as exc:  # a lost link or a robot that cannot run it: keep the packages
                self.say(f"build: error: {exc}")
                self._close_transport()
                outcome = "error"
            with self.cond:
                self.running, self.running_all = None, False
                if outcome == "cancelled":
                    # not built: they go with the build that replaces it
                    if packages is None:
                        self.dirty_all = True
                    else:
                        self.dirty |= packages
                elif outcome != "ok":
                    # built again with the next change, instead of looping on a failure
                    if packages is None:
                        self.carry_all = True
                    else:
                        self.carry |= packages
                self.state = "idle" if outcome in ("ok", "cancelled") else outcome
                self.cond.notify_all()

    def _build(self, packages: set[str] | None) -> str:
        from fetchsync.chores.build import TransportRunner
        from fetchsync.chores.remote import wrap
        from fetchsync.link.connection import remote_python
        from fetchsync.link.session import open_transport

        if self._transport is None:
            self._transport = open_transport(
                self.target, accept_fingerprint=self.accept_fingerprint, persistent=False
            )
        tool = self.tool
        if tool == "auto":
            if self._detected is None:
                runner = TransportRunner(self._transport, where=self.target.robot)
                markers, distros = split_probe(
                    runner.probe(marker_probe(self.target.remote_workspace))
                )
                choice = choose_tool(markers, manifests(self.src), distros)
                self.say(
                    f"build: build tool: {choice.tool} ({choice.reason} on {self.target.robot})"
                )
                self._detected = choice.tool
            tool = self._detected
        line = package_command(tool, packages, self.args, self.build_type)
        workspace = self.target.remote_workspace
        env = ros_environment(workspace, spaces=() if tool == COLCON else ("devel",))
        body = script(line, environment=env, directory=workspace)
        bash = "exec 2>&1\n" + lock_prelude(workspace) + "\n" + body
        what = "everything" if packages is None else " ".join(sorted(packages))
        self.say(f"build: {line} (on {self.target.robot})")
        t0 = time.monotonic()
        channel = self._transport.exec(wrap(bash, tty=False, python=remote_python()))
        with self.cond:
            self._channel = channel
            cancelled = self.cancelled or self.stopping
        if cancelled:
            self._cancel()
        try:
            channel.shutdown_write()
            buf = b""
            while True:
                try:
                    data = channel.recv(65536)
                except Exception:
                    if self.cancelled or self.stopping:
                        data = b""
                    else:
                        raise
                if not data:
                    break
                buf += data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
                *lines, buf = buf.split(b"\n")
                for raw in lines:
                    self.say("build: " + raw.decode("utf-8", "replace"))
            if buf:
                self.say("build: " + buf.decode("utf-8", "replace"))
            with self.cond:
                cancelled = self.cancelled or self.stopping
            status = None if cancelled else channel.exit_status(30)
        finally:
            with self.cond:
                self._channel = None
            try:
                channel.close()
            except Exception:  # already closed by a cancel
                pass
        seconds = time.monotonic() - t0
        with self.cond:
            self.builds += 1
        if cancelled:
            self.say(
                f"build: cancelled ({what}): newer changes arrived"
                if not self.stopping
                else f"build: stopped ({what})"
            )
            self._record(packages, "cancelled", None, seconds)
            return "cancelled"
        if status == 0:
            self.say(f"build: ok: {what} in {seconds:.1f}s")
            self._record(packages, "ok", 0, seconds)
            return "ok"
        self.say(
            f"error: build failed ({what}) with exit status {status}; "
            "it is built again with the next change"
        )
        self._record(packages, "failed", status, seconds)
        return "failed"

    def _record(
        self, packages: set[str] | None, result: str, status: int | None, seconds: float
    ) -> None:
        with self.cond:
            self.last = {
                "packages": "all" if packages is None else sorted(packages),
                "result": result,
                "exit_status": status,
                "seconds": round(seconds, 2),
                "finished": time.time(),
            }
