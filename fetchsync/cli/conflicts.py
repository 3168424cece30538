"""``fetchsync conflicts``: list, compare and bring back the versions a robot kept.

A push keeps the robot's version of a file edited there since the last sync in
``<remote workspace>/.fetchsync/conflicts/<time>/<path>``, and the files it deletes
in ``.fetchsync/trash/<time>/<path>``; without this verb they could only be found
by logging in. The robot is read through the endpoint, read-only (its ``kept``
request walks ``.fetchsync`` by descriptor, never through a symlink); a restore
writes only the local workspace, keeping the local file it replaces in the local
``.fetchsync/trash/`` first, and the next push sends the restored file as usual.
"""

from __future__ import annotations

import difflib
import errno
import json
import os
import stat
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import click

from fetchsync.cli.common import robot_place, say_where, target_options
from fetchsync.errors import RemoteError, SyncError, UsageError

if TYPE_CHECKING:
    from fetchsync.link.client import Endpoint

PIECE = 4 * 1024 * 1024  # bytes read from the robot per request
MAX_DIFF = 8 * 1024 * 1024  # larger files are said to differ, with their sizes, not diffed
_O_DIR = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)


@dataclass(frozen=True)
class Kept:
    """One file the robot kept: ``.fetchsync/<where>/<time>/<path>``."""

    time: str
    path: str
    size: int
    where: str

    @property
    def shown(self) -> str:
        return f".fetchsync/{self.where}/{self.time}/{self.path}"


def _kept_from_wire(raw: Any, where: str) -> Kept:
    """An entry of the robot's answer, checked as if the robot lied: a wire path, a
    one-component time, a size."""
    from fetchsync.protocol.errors import PathError
    from fetchsync.protocol.paths import validate

    try:
        if not (
            isinstance(raw, list)
            and len(raw) >= 3
            and isinstance(raw[0], str)
            and isinstance(raw[1], str)
            and isinstance(raw[2], int)
            and raw[2] >= 0
        ):
            raise PathError("malformed entry")
        if "/" in validate(raw[0]):
            raise PathError("bad time")
        return Kept(raw[0], validate(raw[1]), raw[2], where)
    except PathError as exc:
        raise RemoteError(f"the robot sent a bad kept entry: {exc}") from None


def _human(n: int) -> str:
    from fetchsync.agent.quick import human

    return human(n)


def list_kept(endpoint: Endpoint, where: str) -> tuple[list[Kept], bool]:
    """The robot's kept files (oldest first), and whether it left some out."""
    listed = endpoint.kept(where)
    return [_kept_from_wire(e, where) for e in listed.entries], listed.more


def read_kept(endpoint: Endpoint, kept: Kept, out: BinaryIO) -> int:
    """Copy the kept file into ``out`` (a binary file), in pieces; its size."""
    offset = 0
    while True:
        piece = endpoint.kept_piece(kept.where, kept.time, kept.path, offset=offset, length=PIECE)
        out.write(piece.data)
        offset += len(piece.data)
        if offset == piece.size:
            return piece.size
        if not piece.data:
            raise RemoteError(f"{kept.shown} changed on the robot while it was read; try again")


def choose(entries: list[Kept], path: str, at: str | None) -> Kept:
    """The version of ``path`` kept at ``at``, or the newest one."""
    from fetchsync.console import printable

    found = [k for k in entries if k.path == path and (at is None or k.time == at)]
    if not found:
        when = f" at {printable(at)}" if at else ""
        raise UsageError(
            f"the robot keeps no version of {printable(path)}{when}",
            hint="fetchsync conflicts list shows what it keeps",
        )
    return max(found, key=lambda k: k.time)


def _wire_path(path: str) -> str:
    from fetchsync.protocol.errors import PathError
    from fetchsync.protocol.paths import validate

    try:
        return validate(path.strip("/"))
    except PathError as exc:
        raise UsageError(
            f"bad path: {exc}", hint="give it relative to src/, as list shows it"
        ) from None


def diff_lines(kept: Kept, robot: bytes, local: bytes | None, *, local_size: int) -> list[str]:
    """A unified diff of the local file (``-``) against the robot's kept version (``+``);
    for binary or large files, one line saying whether they differ and their sizes."""
    local_name = f"local src/{kept.path}"
    robot_name = f"robot {kept.shown}"
    if local is not None and local == robot:
        return [f"{kept.path}: the robot's kept version is the same as the local file"]
    local_text = "absent" if local_size < 0 else f"{local_size} bytes"
    if (
        (local is None and local_size >= 0)
        or b"\0" in robot
        or (local is not None and b"\0" in local)
    ):
        return [
            f"{kept.path}: binary or large files differ: robot {len(robot)} bytes, local {local_text}"
        ]
    try:
        theirs = robot.decode("utf-8").splitlines(keepends=True)
        ours = local.decode("utf-8").splitlines(keepends=True) if local is not None else []
    except UnicodeDecodeError:
        return [f"{kept.path}: binary files differ: robot {len(robot)} bytes, local {local_text}"]
    return [
        line.rstrip("\n")
        for line in difflib.unified_diff(
            ours,
            theirs,
            fromfile=local_name if local is not None else "/dev/null",
            tofile=robot_name,
        )
    ]


def _open_dirs(top_fd: int, parts: list[str], *, create: bool, mode: int = 0o777) -> int:
    """A descriptor of ``parts`` below ``top_fd``, each component opened O_NOFOLLOW
    (made when ``create``): a symlinked directory is refused, never followed."""
    fd = os.dup(top_fd)
    try:
        for part in parts:
            try:
                sub = os.open(part, _O_DIR, dir_fd=fd)
            except FileNotFoundError:
                if not create:
                    raise
                os.mkdir(part, mode, dir_fd=fd)
                sub = os.open(part, _O_DIR, dir_fd=fd)
            os.close(fd)
            fd = sub
    except OSError as exc:
        os.close(fd)
        if exc.errno in (errno.ELOOP, errno.ENOTDIR):
            raise SyncError(
                f"a directory on the way to {'/'.join(parts)} is a symlink or a "
                "file: nothing restored"
            ) from None
        raise
    return fd


def restore_local(workspace: Path, path: str, data_file: Any) -> str | None:
    """Put the content of ``data_file`` at ``src/path`` of ``workspace``; the local file it
    replaces is hard-linked into ``.fetchsync/trash/<time>-restore/<path>`` first (an
    existing name there is never overwritten). Returns where the replaced file is kept."""
    parts = path.split("/")
    ws_fd = os.open(workspace, os.O_RDONLY | os.O_DIRECTORY)
    try:
        src_fd = _open_dirs(ws_fd, ["src"], create=False)
        try:
            dir_fd = _open_dirs(src_fd, parts[:-1], create=True)
        finally:
            os.close(src_fd)
        name = parts[-1]
        try:
            try:
                old = os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
            except FileNotFoundError:
                old = None
            if old is not None and stat.S_ISDIR(old.st_mode):
                raise SyncError(f"src/{path} is a directory here: nothing restored")
            umask = os.umask(0)
            os.umask(umask)
            mode = (
                stat.S_IMODE(old.st_mode)
                if old is not None and stat.S_ISREG(old.st_mode)
                else 0o666 & ~umask
            )
            tmp = f".fetchsync-restore-{os.getpid()}-{name}"[:255]
            fd = os.open(
                tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600, dir_fd=dir_fd
            )
            try:
                with os.fdopen(fd, "wb") as out:
                    data_file.seek(0)
                    while chunk := data_file.read(1 << 20):
                        out.write(chunk)
                    out.flush()
                    os.fchmod(out.fileno(), mode)
                    os.fsync(out.fileno())
                kept = None
                if old is not None:
                    stamp = time.strftime("%Y%m%d-%H%M%S") + f"-restore-{os.getpid()}"
                    trash_parts = [".fetchsync", "trash", stamp] + parts[:-1]
                    trash_fd = _open_dirs(ws_fd, trash_parts, create=True, mode=0o700)
                    try:
                        os.link(
                            name,
                            name,
                            src_dir_fd=dir_fd,
                            dst_dir_fd=trash_fd,
                            follow_symlinks=False,
                        )
                    finally:
                        os.close(trash_fd)
                    kept = str(workspace / ".fetchsync" / "trash" / stamp / path)
                os.rename(tmp, name, src_dir_fd=dir_fd, dst_dir_fd=dir_fd)
            except BaseException:
                try:
                    os.unlink(tmp, dir_fd=dir_fd)
                except OSError:
                    pass
                raise
            return kept
        finally:
            os.close(dir_fd)
    finally:
        os.close(ws_fd)


def _read_local(workspace: Path, path: str) -> tuple[bytes | None, int]:
    """The local ``src/path`` (None when large or absent) and its size (-1: absent)."""
    try:
        fd = os.open(workspace, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return None, -1
    try:
        d = _open_dirs(fd, ["src"] + path.split("/")[:-1], create=False)
    except (OSError, SyncError):
        return None, -1
    finally:
        os.close(fd)
    try:
        f = os.open(path.split("/")[-1], os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK, dir_fd=d)
    except OSError:
        return None, -1
    finally:
        os.close(d)
    with os.fdopen(f, "rb") as fh:
        st = os.fstat(fh.fileno())
        if not stat.S_ISREG(st.st_mode):
            return None, -1
        return (fh.read() if st.st_size <= MAX_DIFF else None), st.st_size


@click.command("conflicts")
@target_options
@click.argument(
    "action", required=False, default="list", type=click.Choice(["list", "diff", "restore"])
)
@click.argument("path", required=False)
@click.option(
    "--at",
    "at",
    metavar="TIME",
    help="The version kept at TIME (as list shows it); default: the newest.",
)
@click.option(
    "--trash",
    is_flag=True,
    help="The robot's trash (files a push deleted) instead of its conflicts.",
)
@click.option("--json", "as_json", is_flag=True, help="list: print a JSON list.")
def command(
    robot: str | None,
    user: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    accept_host_key: str | None,
    action: str,
    path: str | None,
    at: str | None,
    trash: bool,
    as_json: bool,
) -> None:
    """List, diff or restore the robot's kept versions of files.

    A push keeps the robot's version of each file edited there since the last
    sync in <remote workspace>/.fetchsync/conflicts/<time>/<path> (--trash: the
    files it deleted, in .fetchsync/trash/). list (the default) shows them,
    PATH narrowing to one file or directory; diff PATH shows how the newest (or
    --at TIME) differs from the local src/PATH; restore PATH brings it into the
    local src/PATH, keeping the local file it replaces in the local
    .fetchsync/trash/ first. The next push sends it to the robot. Reads the
    robot only.
    """
    import tempfile

    from fetchsync.cli.common import resolve
    from fetchsync.console import printable
    from fetchsync.link.client import Endpoint
    from fetchsync.link.session import connect

    if robot is not None and "," in robot:
        raise UsageError("conflicts reads one robot at a time", hint="give one --robot")
    if action != "list" and not path:
        raise UsageError(f"conflicts {action} needs a PATH (relative to src/)")
    wire = _wire_path(path) if path else None
    where = "trash" if trash else "conflicts"
    target = resolve(robot, user, workspace, remote_workspace)
    kept_dir = f"{target.remote_workspace}/.fetchsync/{where}"
    if action == "list":
        say_where(f"conflicts {action}", target, remote=kept_dir)
    else:
        say_where(
            f"conflicts {action}",
            target,
            local=target.workspace / "src",
            remote=kept_dir,
            direction="from" if action == "restore" else "both",
        )
    with connect(target, accept_fingerprint=accept_host_key) as conn:
        endpoint = Endpoint(conn)
        endpoint.open(target.remote_workspace, create=False, readonly=True)
        entries, more = list_kept(endpoint, where)
        if action == "list":
            if wire is not None:
                entries = [k for k in entries if k.path == wire or k.path.startswith(wire + "/")]
            place = robot_place(target, target.remote_workspace)
            if as_json:
                click.echo(
                    json.dumps(
                        [
                            {
                                "time": k.time,
                                "path": k.path,
                                "size": k.size,
                                "kept": k.shown,
                                "robot": target.robot,
                                "remote_workspace": target.remote_workspace,
                            }
                            for k in entries
                        ],
                        sort_keys=True,
                    )
                )
            elif not entries:
                click.echo(f"no files kept in {printable(place)}/.fetchsync/{where}/")
            else:
                for k in entries:
                    click.echo(printable(f"{k.time}  {_human(k.size):>9}  {k.path}  ({place})"))
            if more:
                click.echo(
                    f"fetchsync: the robot listed only the first {len(entries)} kept files",
                    err=True,
                )
            return
        assert wire is not None
        kept = choose(entries, wire, at)
        with tempfile.TemporaryFile() as data:
            size = read_kept(endpoint, kept, data)
            if action == "diff":
                local, local_size = _read_local(target.workspace, wire)
                data.seek(0)
                robot_bytes = data.read() if size <= MAX_DIFF else b""
                if size > MAX_DIFF:
                    local_text = f"{local_size} bytes" if local_size >= 0 else "absent"
                    lines = [
                        f"{kept.path}: large files differ: robot {size} bytes, local {local_text}"
                    ]
                else:
                    lines = diff_lines(kept, robot_bytes, local, local_size=local_size)
                for line in lines:
                    click.echo(printable(line))
                return
            try:
                replaced = restore_local(target.workspace, wire, data)
            except OSError as exc:
                raise SyncError(
                    printable(f"cannot restore src/{wire}: {exc.strerror or exc}; nothing restored")
                ) from None
    click.echo(printable(f"restored src/{kept.path} from the robot's {kept.shown} ({size} bytes)"))
    if replaced:
        click.echo(printable(f"  the local file it replaced is kept in {replaced}"))
    click.echo("  the next push sends it to the robot")
