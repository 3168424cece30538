"""The workspace's repositories: what git says about each, and whether the robot's copy matches.

Finding repositories and asking git about them touch only the local disk
(git runs without taking ``index.lock``, so an editor's git is never
blocked). The robot column compares the local tree with the robot's through
the last-synced state and one read-only listing request: the robot's
workspace is opened with ``create: False``, so a workspace never pushed is
reported, not created, and nothing under its ``src/`` is written.

A path that differs is counted for the innermost repository holding it, as
git does: a nested repository's files are its own, not its parent's.
"""

from __future__ import annotations

import logging
import os
import subprocess
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable

from fetchsync.config import ROBOT_VARS, Target, resolve_robot, resolve_target
from fetchsync.environ import inheritable
from fetchsync.errors import (
    ConfigError,
    FetchsyncError,
    RemoteError,
    TransportError,
    UsageError,
)

if TYPE_CHECKING:
    from fetchsync.link.client import Listing
    from fetchsync.protocol import messages as M
    from fetchsync.protocol.ignore import IgnoreRules

log = logging.getLogger(__name__)

DEFAULT_TIMEOUT = 5.0  # seconds for the robot to answer before it is called unreachable
LISTING_TIMEOUT = 120.0  # a first full listing hashes the robot's whole tree: be patient
GIT_TIMEOUT = 60.0
GIT_JOBS = 8

# what the robot column can say about a row
IN_SYNC = "in sync"
DIFFERS = "differs"
UNREACHABLE = "unreachable"
NOT_PUSHED = "not pushed yet"
EXCLUDED = "excluded"
FAILED = "error"

_VCS_DIRS = frozenset({".git", ".hg", ".svn", ".bzr"})
# variables that would point every git call at one repository, whatever -C says
# (set by git hooks and by `git submodule foreach`)
_GIT_LOCATION_VARS = (
    "GIT_DIR",
    "GIT_WORK_TREE",
    "GIT_INDEX_FILE",
    "GIT_OBJECT_DIRECTORY",
    "GIT_ALTERNATE_OBJECT_DIRECTORIES",
    "GIT_COMMON_DIR",
    "GIT_NAMESPACE",
    "GIT_PREFIX",
)


# --------------------------------------------------------------------------- rows
@dataclass(frozen=True)
class Found:
    """A directory listed by workspace-status: a git repository, or a top-level untracked one."""

    path: str  # relative to src/, "/"-separated; "." is src/ itself
    is_git: bool


@dataclass(frozen=True)
class GitInfo:
    branch: str | None = None  # None when detached
    detached: bool = False
    sha: str | None = None  # abbreviated; None before the first commit
    dirty: bool = False  # tracked files differ from HEAD (staged or not)
    error: str | None = None  # git failed on this repository (first line of its message)


@dataclass(frozen=True)
class RobotView:
    """The robot column of one row."""

    state: str  # IN_SYNC, DIFFERS, UNREACHABLE, NOT_PUSHED, EXCLUDED or FAILED
    paths: int = 0  # differing paths, for DIFFERS

    def text(self) -> str:
        if self.state == DIFFERS:
            return f"{self.paths} path differs" if self.paths == 1 else f"{self.paths} paths differ"
        return self.state


@dataclass(frozen=True)
class Package:
    """A ROS package in a row's repository: what builds it, ROS 1's or ROS 2's."""

    name: str
    path: str  # its directory, relative to src/
    format: int  # package.xml's format attribute (1 when absent)
    build_type: str  # <export><build_type>, else catkin or ament_* from the buildtool

    @property
    def ros(self) -> int:
        """2 for what only colcon builds (ament_*, plain cmake or python, format 3 without
        catkin), 1 for catkin packages."""
        return 1 if self.build_type == "catkin" else 2

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "path": self.path,
            "format": self.format,
            "build_type": self.build_type,
            "ros": self.ros,
        }


@dataclass(frozen=True)
class Row:
    found: Found
    git: GitInfo = GitInfo()
    robot: RobotView | None = None
    packages: tuple[Package, ...] = ()

    def packages_text(self) -> str:
        """``2 catkin`` or ``1 ament_cmake, 1 ament_python``: how many packages of each type."""
        counts: dict[str, int] = {}
        for p in self.packages:
            counts[p.build_type] = counts.get(p.build_type, 0) + 1
        return ", ".join(f"{n} {t}" for t, n in sorted(counts.items())) or "-"

    @property
    def path(self) -> str:
        return self.found.path

    def branch_text(self) -> str:
        if not self.found.is_git:
            return "-"
        if self.git.error is not None:
            return "?"
        return "(detached)" if self.git.detached else (self.git.branch or "?")

    def sha_text(self) -> str:
        if not self.found.is_git:
            return "untracked"
        if self.git.error is not None:
            return "(git error)"
        if self.git.sha is None:
            return "(no commits)"
        return self.git.sha + ("-dirty" if self.git.dirty else "")

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "path": self.path,
            "git": self.found.is_git,
            "branch": self.git.branch,
            "detached": self.git.detached,
            "sha": self.git.sha,
            "dirty": self.git.dirty,
            "error": self.git.error,
            "packages": [p.to_json() for p in self.packages],
        }
        if self.robot is not None:
            out["robot"] = self.robot.state
            out["differing"] = (
                self.robot.paths
                if self.robot.state == DIFFERS
                else (0 if self.robot.state == IN_SYNC else None)
            )
        return out


@dataclass
class WorkspaceStatus:
    src: Path
    rows: list[Row]
    robot: str | None = None  # "robot:remote/src" when the robot column is shown
    notes: list[str] = field(default_factory=list)  # one line each, for stderr

    def to_json(self) -> list[dict[str, Any]]:
        return [r.to_json() for r in self.rows]

    def lines(self) -> list[str]:
        """A table aligned in columns, which is also a GitHub markdown table (as fetch_tools')."""
        against = f", compared with {self.robot}" if self.robot else ""
        title = f"Status of {self.src}{against}:"
        if not self.rows:
            return [title, "no directories under src/"]
        with_robot = self.robot is not None
        with_packages = any(r.packages for r in self.rows)
        header = (
            ["repository", "branch", "sha"]
            + (["packages"] if with_packages else [])
            + (["robot"] if with_robot else [])
        )
        cells = [
            [r.path, r.branch_text(), r.sha_text()]
            + ([r.packages_text()] if with_packages else [])
            + ([r.robot.text() if r.robot is not None else ""] if with_robot else [])
            for r in self.rows
        ]
        widths = [max(len(c[i]) for c in [header, *cells]) for i in range(len(header))]

        def line(values: list[str]) -> str:
            return " | ".join(v.ljust(w) for v, w in zip(values, widths)).rstrip()

        rule = "|".join(
            "-" * (w + (1 if i in (0, len(widths) - 1) else 2)) for i, w in enumerate(widths)
        )
        return [title, line(header), rule, *(line(c) for c in cells)]


# --------------------------------------------------------------------------- finding
def find_repositories(src: Path) -> list[Found]:
    """Every git repository under ``src`` (nested ones included) and the untracked top level.

    A repository is a directory holding ``.git``, a directory or a file (a
    submodule or a worktree). Top-level directories that are not repositories
    are listed as untracked unless ``src`` itself is one. Symbolic links are
    not followed, except that a top-level link to a directory is listed (the
    robot holds it as a link).
    """
    src_is_repo = os.path.lexists(os.path.join(src, ".git"))
    found = [Found(".", True)] if src_is_repo else []
    stack = [""]
    while stack:
        rel = stack.pop()
        try:
            with os.scandir(os.path.join(src, rel) if rel else src) as it:
                entries = list(it)
        except OSError as exc:
            if not rel:
                raise ConfigError(f"cannot list {src}: {exc.strerror or exc}") from exc
            log.debug("cannot list %s: %s", rel, exc)
            continue
        for de in entries:
            if de.name in _VCS_DIRS:
                continue
            path = f"{rel}/{de.name}" if rel else de.name
            try:
                if de.is_dir(follow_symlinks=False):
                    stack.append(path)
                elif rel or not de.is_dir():  # below the top level, links are not followed
                    continue
            except OSError:
                continue
            if os.path.lexists(os.path.join(de.path, ".git")):
                found.append(Found(path, True))
            elif not rel and not src_is_repo:
                found.append(Found(path, False))
    return sorted(found, key=lambda f: f.path.split("/"))


_IGNORE_MARKERS = ("CATKIN_IGNORE", "COLCON_IGNORE", "AMENT_IGNORE")


def read_package(pkg_dir: Path, rel: str) -> Package | None:
    """The package whose package.xml is in ``pkg_dir`` (None when it is not one)."""
    try:
        root = ET.parse(pkg_dir / "package.xml").getroot()
    except (OSError, ET.ParseError) as exc:
        log.debug("cannot read %s/package.xml: %s", pkg_dir, exc)
        return None
    if root.tag != "package":
        return None
    try:
        fmt = int(root.get("format", "1"))
    except ValueError:
        fmt = 1
    name = (root.findtext("name") or "").strip() or pkg_dir.name
    build_type = (root.findtext("export/build_type") or "").strip()
    if not build_type:
        tools = [(e.text or "").strip() for e in root.findall("buildtool_depend")]
        ament = next((t for t in tools if t.startswith("ament_")), None)
        if "catkin" in tools:
            build_type = "catkin"
        elif ament is not None:
            build_type = ament
        else:
            # format 3 without catkin is a ROS 2 package (colcon's default: ament_cmake)
            build_type = "ament_cmake" if fmt >= 3 else "catkin"
    return Package(name=name, path=rel or ".", format=fmt, build_type=build_type)


def find_packages(src: Path) -> list[Package]:
    """Every package under ``src`` the build tools would see: not inside another package,
    nor under a ``CATKIN_IGNORE``/``COLCON_IGNORE``/``AMENT_IGNORE``, nor hidden."""
    out: list[Package] = []
    for dirpath, dirs, files in os.walk(src):
        rel = os.path.relpath(dirpath, src).replace(os.sep, "/")
        rel = "" if rel == "." else rel
        if rel and any(m in files for m in _IGNORE_MARKERS):
            dirs[:] = []
            continue
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        if "package.xml" in files:
            dirs[:] = []
            pkg = read_package(Path(dirpath), rel)
            if pkg is not None:
                out.append(pkg)
    return out


def packages_by_row(packages: Iterable[Package], rows: Iterable[str]) -> dict[str, list[Package]]:
    """Each package under the innermost row (repository) holding it."""
    ordered = sorted(rows, key=lambda r: -len(r))
    out: dict[str, list[Package]] = {}
    for pkg in packages:
        for row in ordered:
            if row == "." or pkg.path == row or pkg.path.startswith(row + "/"):
                out.setdefault(row, []).append(pkg)
                break
    return out


# --------------------------------------------------------------------------- git
def _git_env() -> dict[str, str]:
    env = {k: v for k, v in inheritable(os.environ).items() if k not in _GIT_LOCATION_VARS}
    # status refreshes the index opportunistically; an editor's git may hold its lock
    env["GIT_OPTIONAL_LOCKS"] = "0"
    return env


def _git(repo: Path, args: list[str], env: Mapping[str, str]) -> str:
    try:
        proc = subprocess.run(
            ["git", "-C", str(repo), *args],
            capture_output=True,
            check=False,
            env=dict(env),
            timeout=GIT_TIMEOUT,
            stdin=subprocess.DEVNULL,
        )
    except FileNotFoundError as exc:
        raise ConfigError(
            "git is not installed (workspace-status runs it)",
            hint="install git, e.g. apt-get install git",
        ) from exc
    except subprocess.TimeoutExpired as exc:
        raise _GitFailed(f"git {args[0]} took more than {GIT_TIMEOUT:g} s") from exc
    if proc.returncode != 0:
        text = proc.stderr.decode("utf-8", "replace").strip()
        first = text.splitlines()[0] if text else f"git {args[0]} exited {proc.returncode}"
        raise _GitFailed(first)
    return proc.stdout.decode("utf-8", "replace")


class _GitFailed(Exception):
    pass


def inspect_repository(repo: Path, *, env: Mapping[str, str] | None = None) -> GitInfo:
    """Branch, abbreviated commit and dirtiness of the repository at ``repo``.

    Dirty means what ``git describe --dirty`` means (fetch_tools showed that):
    tracked files changed, staged or not. Untracked files do not count, so a
    repository cloned inside another does not make its parent dirty.
    """
    env = _git_env() if env is None else env
    try:
        # one process gives branch, commit and changes (porcelain v2: git >= 2.11)
        out = _git(repo, ["status", "--porcelain=v2", "--branch", "--untracked-files=no"], env)
        oid = head = None
        dirty = False
        for line in out.splitlines():
            if line.startswith("# branch.oid "):
                oid = line[len("# branch.oid ") :]
            elif line.startswith("# branch.head "):
                head = line[len("# branch.head ") :]
            elif line and not line.startswith("#"):
                dirty = True
        detached = head == "(detached)"
        sha = None
        if oid and oid != "(initial)":
            # git's own abbreviation: long enough to be unique in this repository
            sha = _git(repo, ["rev-parse", "--short", "HEAD"], env).strip()
    except _GitFailed as exc:
        return GitInfo(error=str(exc))
    return GitInfo(branch=None if detached else head, detached=detached, sha=sha, dirty=dirty)


def inspect_all(src: Path, found: Iterable[Found], *, jobs: int = GIT_JOBS) -> dict[str, GitInfo]:
    """:func:`inspect_repository` for every repository in ``found``, several at once."""
    repos = [f.path for f in found if f.is_git]
    if not repos:
        return {}
    env = _git_env()
    with ThreadPoolExecutor(
        max_workers=max(1, min(jobs, len(repos))), thread_name_prefix="fetchsync-git"
    ) as pool:
        infos = pool.map(lambda p: inspect_repository(src / p, env=env), repos)
        return dict(zip(repos, infos))


# --------------------------------------------------------------------------- robot
def optional_target(
    *,
    robot: str | None,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    environ: Mapping[str, str] = os.environ,
) -> Target | None:
    """The robot to compare with, or None when none is configured.

    A robot named by ``--robot`` or a variable must resolve (errors are the
    user's to see); one only implied by ``ROS_MASTER_URI`` is dropped silently
    when it is no robot, as with a roscore on this machine (``localhost``).
    """
    named = (robot or "").strip() or any(environ.get(v, "").strip() for v in ROBOT_VARS)
    if not named:
        if not environ.get("ROS_MASTER_URI", "").strip():
            return None
        try:
            resolve_robot(None, environ=environ)
        except ConfigError:
            return None
    return resolve_target(
        robot=robot,
        user=user,
        workspace=workspace,
        remote_workspace=remote_workspace,
        environ=environ,
        defer_ssh_user=True,
    )


@dataclass(frozen=True)
class _Remembered:
    """The last-synced state, read without creating one where none exists."""

    entries: dict[str, Any]
    epoch: str = ""
    gen: int = -1
    algorithm: str = ""


def _remembered(target: Target) -> _Remembered:
    from fetchsync.link.session import robot_id
    from fetchsync.sync.state import State, state_path

    path = state_path(robot_id(target), target.remote_workspace)
    if not path.exists():
        return _Remembered({})
    state = State(path)
    try:
        return _Remembered(state.entries(), state.epoch, state.gen, state.get("algorithm"))
    finally:
        state.close()


class _Listing(threading.Thread):
    """Reads the robot's copy of ``src/`` in the background: connect, open (never create), list.

    The listing is a drift against the last-synced state when that is still
    current (one round trip with the open, pipelined), else a full one.
    """

    def __init__(
        self,
        target: Target,
        rules: IgnoreRules,
        remembered: _Remembered,
        *,
        accept_fingerprint: str | None,
    ) -> None:
        super().__init__(name="fetchsync-robot-listing", daemon=True)
        self.target = target
        self.rules = rules
        self.remembered = remembered
        self.accept_fingerprint = accept_fingerprint
        self.algorithm = ""
        self.listing: Listing | None = None  # the robot's answer
        self.missing = False  # the remote workspace does not exist
        self.error: BaseException | None = None
        self.connected = threading.Event()  # set once connected, or failed
        self.finished = threading.Event()
        self.abandoned = False

    def run(self) -> None:
        from fetchsync.link.client import Endpoint
        from fetchsync.link.session import connect

        try:
            with connect(self.target, accept_fingerprint=self.accept_fingerprint) as conn:
                self.algorithm = conn.algorithm
                self.connected.set()
                if self.abandoned:
                    return
                r = self.remembered
                fresh = bool(r.entries) and r.epoch != "" and r.algorithm in ("", conn.algorithm)
                endpoint = Endpoint(conn)
                opened = endpoint.send_open(
                    self.target.remote_workspace, rules=self.rules, create=False
                )
                listed = endpoint.send_listing(since=(r.epoch, r.gen) if fresh else None)
                try:
                    opened.wait()
                except RemoteError as exc:
                    if "does not exist" not in str(exc):
                        raise
                    self.missing = True
                    return
                self.listing = listed.wait()
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
            self.error = exc
        finally:
            self.connected.set()
            self.finished.set()


def differing_paths(local: Mapping[str, M.Listed], remote: Mapping[str, M.Listed]) -> list[str]:
    """Paths a push would change on the robot (a deleted directory counts once)."""
    from fetchsync.protocol import messages as M
    from fetchsync.sync.plan import plan

    return [p.op.path for p in plan(local, remote, lambda _path: M.ABSENT, reuse=False)]


def count_by_row(paths: Iterable[str], rows: Iterable[str]) -> dict[str, int]:
    """How many of ``paths`` fall in each row: the innermost row holding a path counts it."""
    known = set(rows)
    counts = dict.fromkeys(known, 0)
    for path in paths:
        parts = path.split("/")
        for i in range(len(parts), 0, -1):
            owner = "/".join(parts[:i])
            if owner in known:
                counts[owner] += 1
                break
        else:
            if "." in known:
                counts["."] += 1
    return counts


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def compare_with_robot(
    src: Path,
    found: list[Found],
    target: Target,
    *,
    excludes: Iterable[str] = (),
    accept_fingerprint: str | None = None,
    timeout: float = DEFAULT_TIMEOUT,
    while_waiting: Callable[[], None] | None = None,
) -> tuple[dict[str, RobotView], list[str]]:
    """The robot column for every row, and notes for stderr.

    ``while_waiting()`` runs while the robot is reached and lists its tree
    (the git work), so both overlap.
    """
    from fetchsync.sync.engine import build_rules, scan_local

    rules = build_rules(excludes)
    remembered = _remembered(target)
    listing = _Listing(target, rules, remembered, accept_fingerprint=accept_fingerprint)
    started = time.monotonic()
    listing.start()
    if while_waiting is not None:
        while_waiting()

    def everywhere(view: RobotView) -> dict[str, RobotView]:
        return {f.path: view for f in found}

    if not listing.connected.wait(max(0.0, started + timeout - time.monotonic())):
        listing.abandoned = True
        return everywhere(RobotView(UNREACHABLE)), [
            f"robot {target.robot} unreachable: no answer within {timeout:g} s"
        ]
    synced = remembered.entries if remembered.algorithm in ("", listing.algorithm) else {}
    local = None
    if listing.error is None:
        # the robot scans its tree meanwhile
        local = scan_local(str(src), rules, synced, listing.algorithm, lazy=True)
    if not listing.finished.wait(LISTING_TIMEOUT):
        listing.abandoned = True
        return everywhere(RobotView(UNREACHABLE)), [
            f"robot {target.robot} unreachable: no listing within {LISTING_TIMEOUT:g} s"
        ]
    exc = listing.error
    if isinstance(exc, (ConfigError, UsageError)):
        raise exc  # the user's to fix, as in every other verb
    if isinstance(exc, TransportError):
        return everywhere(RobotView(UNREACHABLE)), [
            f"robot {target.robot} unreachable: {_one_line(exc)}"
        ]
    if isinstance(exc, FetchsyncError):
        return everywhere(RobotView(FAILED)), [
            f"cannot compare with robot {target.robot}: {_one_line(exc)}"
        ]
    if exc is not None:
        raise exc
    if listing.missing:
        return everywhere(RobotView(NOT_PUSHED)), []
    assert local is not None and listing.listing is not None
    remote = listing.listing.tree(lambda: {p: s.listed(p) for p, s in synced.items()})
    local.hash_where_needed(str(src), remote, listing.algorithm)
    counts = count_by_row(differing_paths(local.items, remote), [f.path for f in found])
    views = {}
    for f in found:
        if f.path != "." and f.path not in local.items:
            views[f.path] = RobotView(EXCLUDED)  # by --exclude or a .fetchsyncignore
        elif counts[f.path]:
            views[f.path] = RobotView(DIFFERS, counts[f.path])
        else:
            views[f.path] = RobotView(IN_SYNC)
    return views, []


# --------------------------------------------------------------------------- together
def workspace_status(
    src: Path,
    *,
    target: Target | None = None,
    excludes: Iterable[str] = (),
    accept_fingerprint: str | None = None,
    timeout: float = DEFAULT_TIMEOUT,
) -> WorkspaceStatus:
    """Every repository under ``src`` with git's view and, with a ``target``, the robot's."""
    if not src.is_dir():
        raise ConfigError(f"{src} is not a directory", hint="check --workspace")
    found = find_repositories(src)
    infos: dict[str, GitInfo] = {}

    def ask_git() -> None:
        infos.update(inspect_all(src, found))

    views: dict[str, RobotView] = {}
    notes: list[str] = []
    if target is None:
        ask_git()
    else:
        views, notes = compare_with_robot(
            src,
            found,
            target,
            excludes=excludes,
            accept_fingerprint=accept_fingerprint,
            timeout=timeout,
            while_waiting=ask_git,
        )
    for path, info in infos.items():
        if info.error is not None:
            notes.append(f"git failed in {src / path}: {info.error}")
    packages = packages_by_row(find_packages(src), [f.path for f in found])
    rows = [
        Row(f, infos.get(f.path, GitInfo()), views.get(f.path), tuple(packages.get(f.path, ())))
        for f in found
    ]
    where = None
    if target is not None:
        where = f"{target.robot}:{target.remote_workspace.rstrip('/')}/src"
    return WorkspaceStatus(src=src, rows=rows, robot=where, notes=notes)


__all__ = [
    "DIFFERS",
    "EXCLUDED",
    "FAILED",
    "IN_SYNC",
    "NOT_PUSHED",
    "UNREACHABLE",
    "Found",
    "GitInfo",
    "Package",
    "RobotView",
    "Row",
    "WorkspaceStatus",
    "compare_with_robot",
    "count_by_row",
    "differing_paths",
    "find_packages",
    "find_repositories",
    "inspect_all",
    "inspect_repository",
    "optional_target",
    "workspace_status",
]
