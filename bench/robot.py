"""The robot's account and the robot's side of a bench run: who the bench logs in as, where.

A Fetch runs Ubuntu with a stock ``~/.bashrc`` (it returns at once for a
non-interactive shell, as every ssh command's is) and the system
``/usr/bin/python3``. This machine's root, the robot the bench used to log in
as, runs ``pyenv init`` and ``pyenv virtualenv-init`` from its ``~/.bashrc`` at
every ssh login (rsync's too, ~0.2-0.5 s) and finds ``python3`` as a pyenv shim
(~0.9 s more for every start of fetchsync's endpoint): costs no robot pays, and
that inflated both tools' small pushes. So the bench logs in as a dedicated
account, :data:`ROBOT_USER`, that it creates when it runs as root (``useradd -m
-s /bin/bash``: its home and ``~/.bashrc`` from ``/etc/skel``); ``--robot-user
root`` measures the old robot. Not running as root, the robot is the current
user, as the tests' sshd has it.

The tests' sshd (``tests/sshd.py``) reads one shared ``AuthorizedKeysFile`` in
its work directory, opened as the user logging in: that directory, and every
directory the robot's trees are in, must be reachable by the robot account.
A run's work directory need not be (pytest's are private), so for another
account the robot's side lives in a directory of its own under the account's
home (:class:`RobotSide`): the sshds' work directories (root's, world-readable
but for the private keys) and the robot's trees and caches (owned by the
account, as on a robot).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pwd
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Iterator

ROBOT_USER = "fsrobot"


def default_robot_user() -> str:
    """:data:`ROBOT_USER` when running as root (the bench creates it), else the current user."""
    return ROBOT_USER if os.geteuid() == 0 else pwd.getpwuid(os.getuid()).pw_name


def ensure_account(user: str) -> pwd.struct_passwd:
    """The password entry of ``user``, created first (as root) if it does not exist.

    Only :data:`ROBOT_USER` is created: another name must exist already (a typo
    must not make an account).
    """
    try:
        return pwd.getpwnam(user)
    except KeyError:
        pass
    if user != ROBOT_USER:
        raise SystemExit(f"--robot-user {user}: no such account (only {ROBOT_USER} is created)")
    if os.geteuid() != 0:
        raise SystemExit(f"--robot-user {user}: creating the robot's account needs root")
    proc = subprocess.run(
        ["useradd", "-m", "-s", "/bin/bash", user],
        capture_output=True,
        text=True,
        check=False,
        stdin=subprocess.DEVNULL,
    )
    if proc.returncode not in (0, 9):  # 9: made meanwhile by another run
        raise SystemExit(f"useradd {user} failed: {proc.stderr.strip()}")
    return pwd.getpwnam(user)


def add_robot_user_option(ap: object) -> None:
    """``--robot-user USER`` on a script's argparse parser."""
    ap.add_argument(  # type: ignore[attr-defined]
        "--robot-user",
        default=None,
        metavar="USER",
        help=f"the account the bench logs in to the robot as (default {ROBOT_USER}, created "
        "when running as root: a stock ~/.bashrc and /usr/bin/python3, like a Fetch; root: "
        "this machine's root, whose ~/.bashrc runs pyenv's init)",
    )
    ap.add_argument(  # type: ignore[attr-defined]
        "--robot-fs",
        choices=("ext4", "home"),
        default="ext4",
        help="where the robot's side lives: ext4 (default) = a fresh journaled ext4 made "
        "for the run on a loop device, as a robot's Ubuntu has (needs root); home = the "
        "account's home on this machine's root file system (ext4 WITHOUT a journal: a create "
        "there skips every inode of its group freed in the last 60 s, so the bench's own "
        "deletions made creates 4-15x slower for minutes, at random; the figures before "
        "27 Nov 2026)",
    )


ROBOT_DISK_MB = 4096
"""The robot's loop ext4: sparse, it holds the default tree for every tool and the trash."""


@contextlib.contextmanager
def loop_disk(
    workdir: Path, size_mb: int = ROBOT_DISK_MB, *, mount_in: Path | None = None
) -> Iterator[Path]:
    """A fresh ext4 filesystem (with its journal, as mkfs.ext4 makes it) on a loop
    device, its image in ``workdir``, mounted on a new directory in ``mount_in`` (default
    ``workdir``: sshd's StrictModes wants every directory above a robot account's
    authorized_keys reachable, which a 0700 work directory is not); yields the mount
    point (root's, mode 0755)."""
    image = workdir / "robot-disk.img"
    mnt = Path(tempfile.mkdtemp(prefix="fsbench-disk-", dir=mount_in or workdir))
    with open(image, "wb") as fh:
        fh.truncate(size_mb << 20)
    try:
        # every table written now, so no background initialisation writes during the runs
        subprocess.run(
            ["mkfs.ext4", "-q", "-F", "-E", "lazy_itable_init=0,lazy_journal_init=0", str(image)],
            check=True,
            capture_output=True,
        )
        device = subprocess.run(
            ["losetup", "-f", "--show", str(image)], check=True, capture_output=True, text=True
        ).stdout.strip()
        try:
            subprocess.run(["mount", device, str(mnt)], check=True, capture_output=True)
            try:
                mnt.chmod(0o755)
                yield mnt
            finally:
                if subprocess.run(
                    ["umount", str(mnt)], check=False, capture_output=True
                ).returncode:
                    subprocess.run(["umount", "-l", str(mnt)], check=False, capture_output=True)
        finally:
            subprocess.run(["losetup", "-d", device], check=False, capture_output=True)
    finally:
        image.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            mnt.rmdir()


@dataclasses.dataclass
class RobotSide:
    """Where the robot's half of a run lives (sshd work dirs, trees, caches) and its account.

    For the current user (root's old robot, or a non-root run) that is the run's
    work directory, as before; for another account a fresh directory under its
    home, removed by :meth:`close` unless ``keep``.
    """

    user: str
    root: Path
    own: bool
    """``root`` is a directory of this run's outside the work directory."""
    uid: int
    gid: int
    keep: bool = False

    @classmethod
    def make(
        cls, user: str | None, workdir: Path, *, keep: bool = False, parent: Path | None = None
    ) -> RobotSide:
        """``parent``: where the account's directory goes (default its home)."""
        user = user or default_robot_user()
        pw = ensure_account(user)
        if pw.pw_uid == os.geteuid():
            return cls(user, workdir, False, pw.pw_uid, pw.pw_gid, keep)
        root = Path(tempfile.mkdtemp(prefix="fsbench-", dir=parent or pw.pw_dir))
        root.chmod(0o755)
        return cls(user, root, True, pw.pw_uid, pw.pw_gid, keep)

    def sshd_dir(self, name: str = "sshd") -> Path:
        """A work directory for a tests/sshd.py sshd whose shared authorized_keys the
        account can read (tests/sshd.py makes it; this makes it reachable)."""
        path = self.root / name
        if self.own:
            path.mkdir(parents=True, exist_ok=True)
            path.chmod(0o755)
        return path

    def opened(self, sshd_dir: Path) -> None:
        """After the sshd started: its directory (a fresh one it made) reachable, its
        authorized_keys readable by the account."""
        if self.own:
            sshd_dir.chmod(0o755)
            keys = sshd_dir / "authorized_keys"
            if keys.exists():
                keys.chmod(0o644)

    def mkdir(self, path: Path) -> Path:
        """Make ``path`` (and missing parents below :attr:`root`) owned by the account."""
        missing = [p for p in [path, *path.parents] if not p.exists()]
        path.mkdir(parents=True, exist_ok=True)
        if self.own:
            for p in missing:
                os.chown(p, self.uid, self.gid)
        return path

    def probe(self, ssh_argv: list[str]) -> dict[str, object]:
        """What the robot's login is like: the account, its ``python3`` and its version, and
        the wall time of ``ssh robot true`` (median of 5; ``ssh_argv``: the OpenSSH client's
        argv up to the host), for the report."""
        import statistics
        import time

        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            subprocess.run([*ssh_argv, "true"], capture_output=True, check=False)
            times.append(time.perf_counter() - t0)
        out = subprocess.run(
            [
                *ssh_argv,
                "id -un; command -v python3; python3 -c 'import sys; print(sys.version.split()[0])'",
            ],
            capture_output=True,
            text=True,
            check=False,
        ).stdout.split()
        out += ["?"] * (3 - len(out))
        return {
            "user": out[0],  # who the login is, as the robot says
            "python3": out[1],
            "python_version": out[2],
            "ssh_true_seconds": round(statistics.median(times), 4),
        }

    def describe(self, probe: dict[str, object]) -> str:
        """One line for a report."""
        return self.describe_probe(probe)

    @staticmethod
    def describe_probe(probe: dict[str, object]) -> str:
        """One line for a report, from :meth:`probe`'s answer (also as read from JSON)."""
        return (
            f"Robot: account {probe['user']} on the bench's sshd, its python3 "
            f"{probe['python3']} ({probe['python_version']}); `ssh robot true` "
            f"{float(probe['ssh_true_seconds']):.3f} s (median of 5, through the link)."  # type: ignore[arg-type]
        )

    def owners(self, root: Path) -> list[str]:
        """The owners of everything under ``root`` (a robot tree): the robot account's
        name only, when every push wrote as that account."""
        names = set()
        for dirpath, dirnames, filenames in os.walk(root):
            for name in [dirpath, *(os.path.join(dirpath, n) for n in dirnames + filenames)]:
                uid = os.lstat(name).st_uid
                try:
                    names.add(pwd.getpwuid(uid).pw_name)
                except KeyError:
                    names.add(str(uid))
        return sorted(names)

    def close(self) -> None:
        if self.own and not self.keep:
            shutil.rmtree(self.root, ignore_errors=True)
