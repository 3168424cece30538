"""``fetchsync create-account``: make (or repair) a user's account on a robot.

Thin: parse the options, gather the passwords, key and skeleton, let
:mod:`fetchsync.chores.account` do the work through the admin login, print.

``--user`` names the new account here, as it did in fetch_tools; the login
goes through ``--admin-user`` (default ``fetch``).
"""

from __future__ import annotations

import json
import os
import sys
import threading
from pathlib import Path
from typing import Any, Callable

import click

from fetchsync.cli.common import _robots as robots_option  # --robot's values as a,b
from fetchsync.cli.common import complete_robot
from fetchsync.cli.fleet import fleet_options

NEW_PASSWORD_VAR = "FETCHSYNC_NEW_PASSWORD"
ADMIN_PASSWORD_VAR = "FETCHSYNC_ADMIN_PASSWORD"


def _refuse_password_option(ctx: click.Context, param: click.Parameter, value: Any) -> None:
    # fetch_tools took passwords as options, which shows them to every `ps` on the laptop.
    if value is not None:
        from fetchsync.errors import UsageError

        raise UsageError(
            f"{param.opts[0]} is not supported: a password on the command line is "
            "visible to every user of this machine",
            hint=f"type it when asked, or set {NEW_PASSWORD_VAR} / "
            f"{ADMIN_PASSWORD_VAR} for scripts",
        )


class _Secret:
    """A password from a variable, else asked once on the terminal; kept for reuse."""

    def __init__(self, variable: str, prompt: str, *, confirm: bool) -> None:
        self.variable = variable
        self.prompt = prompt
        self.confirm = confirm
        self._value: str | None = None
        # Taken out of the environment at once: no process this one starts inherits it.
        self._given = os.environ.pop(variable, None)
        self._asked = False  # a fleet asked before its robots were worked on: never again
        self._lock = threading.Lock()

    def ask_first(self, *, optional: str = "") -> None:
        """Ask now (a fleet, before its parallel phase), unless a variable gives it or there
        is no terminal; ``optional``: the prompt's note that Enter means none."""
        from fetchsync.chores.account import check_password

        with self._lock:
            self._asked = True
            if self._given or not sys.stdin.isatty():
                return
            value = click.prompt(
                self.prompt + (f" ({optional})" if optional else ""),
                hide_input=True,
                confirmation_prompt=self.confirm,
                err=True,
                default="" if optional else None,
                show_default=False,
            )
            if value:
                self._value = check_password(value, what=self.prompt.lower())

    def get(self) -> str:
        from fetchsync.chores.account import check_password
        from fetchsync.errors import UsageError

        with self._lock:  # a fleet's robots ask from their threads
            if self._value is None:
                value = self._given
                if not value:
                    if not sys.stdin.isatty():
                        raise UsageError(
                            f"{self.prompt.lower()} is needed and there is no terminal to ask it on",
                            hint=f"set {self.variable}",
                        )
                    if self._asked:
                        raise UsageError(
                            f"{self.prompt.lower()} is needed and none was given",
                            hint="run again and type it when asked",
                        )
                    value = click.prompt(
                        self.prompt, hide_input=True, confirmation_prompt=self.confirm, err=True
                    )
                self._value = check_password(value, what=self.prompt.lower())
            return self._value


def _login_callback(admin_password: _Secret) -> Callable[[str], str | None]:
    def answer(prompt: str) -> str | None:
        if prompt.startswith("Enter passphrase"):
            if not sys.stdin.isatty():
                return None
            return (
                str(
                    click.prompt(
                        prompt.rstrip(": "),
                        hide_input=True,
                        default="",
                        show_default=False,
                        err=True,
                    )
                )
                or None
            )
        return admin_password.get()

    return answer


def _account_user(option: str | None) -> str:
    """The account to create: ``--user``, else ``$FETCHSYNC_USER``, ``$FETCH_USER``, ``$USER``
    (fetch_tools' order, with fetchsync's own variable first, as every verb)."""
    import getpass

    from fetchsync.config import USER_VARS

    for value in (option, *(os.environ.get(name) for name in (*USER_VARS, "USER"))):
        if value and value.strip():
            return value.strip()
    return getpass.getuser()


def _account_workspace(
    robot: str | None, user: str, workspace: str | None, remote_workspace: str | None
) -> str | None:
    """The account's workspace on the robot, resolved by the very call ``push`` makes, so
    the two agree; None when no workspace resolves (the robot's initialize.sh chooses)."""
    from fetchsync.cli.common import resolve
    from fetchsync.config import REMOTE_WORKSPACE_VARS, resolve_remote_workspace
    from fetchsync.errors import ConfigError

    try:
        return str(resolve(robot, user, workspace, remote_workspace).remote_workspace)
    except ConfigError:
        if workspace is not None or remote_workspace is not None:
            raise
    # No local workspace (ROS not sourced, none given): a remote one from a variable still counts.
    if any(os.environ.get(name, "").strip() for name in REMOTE_WORKSPACE_VARS):
        return resolve_remote_workspace(None, workspace=Path.home())
    return None


def _say_where(robot: str, user: str, workspace: str | None) -> None:
    """``create-account alice@freight0:~/noetic`` on stderr: the account and its workspace."""
    from fetchsync.cli.common import say_where
    from fetchsync.config import Target

    place = Target(
        robot=robot,
        host=robot,
        user=user,
        workspace=Path.home(),
        remote_workspace=workspace or "",
        is_local=False,
    )
    say_where("create-account", place, remote=workspace)


def _report_lines(report: Any, *, key_path: Path | None, skeleton: Any) -> list[str]:
    """What was done on the robot, one line each."""
    lines: list[str] = []
    if report.created:
        lines.append(
            f"create-account: created {report.user} on {report.robot} (home {report.home})"
        )
    else:
        lines.append(
            f"create-account: {report.user} already existed on {report.robot}; "
            f"checked and repaired (home {report.home})"
        )
    lines.append(f"  password: {'set' if report.password_set else 'unchanged'}")
    groups = f"added {', '.join(report.groups_added)}" if report.groups_added else "all present"
    if report.groups_absent:
        groups += f"; not on the robot: {', '.join(report.groups_absent)}"
    lines.append(f"  groups: {groups}")
    where = f" ({key_path})" if key_path else ""
    lines.append(f"  key: {_KEY_WORDS.get(report.key, report.key)}{where}")
    added = len(report.skeleton_added)
    lines.append(f"  skeleton: {skeleton.source}: {added} file{'s' if added != 1 else ''} added")
    lines.append(f"  initialize.sh: {_INIT_WORDS.get(report.initialize, report.initialize)}")
    if report.workspace:
        how = _WORKSPACE_WORDS.get(report.workspace_record, report.workspace_record)
        was = f"; was {report.workspace_was}" if report.workspace_was else ""
        where = f" in ~/{report.workspace_file}" if report.workspace_file else ""
        lines.append(f"  workspace: {report.workspace} ({how}{where}{was})")
    elif report.workspace_record == "unresolved":
        lines.append(
            "  workspace: none resolved here (source ROS or pass --workspace, then run "
            "create-account again to record it)"
        )
    return lines


_KEY_WORDS = {"added": "added", "present": "already there", "none": "none installed"}
_WORKSPACE_WORDS = {
    "written": "recorded",
    "updated": "recorded",
    "kept": "already recorded",
    "yours": "your own file, left as it is",
    "initialize.sh": "chosen by initialize.sh",
}
_INIT_WORDS = {
    "ran": "ran",
    "already": "had already run",
    "failed": "FAILED",
    "none": "not in the skeleton",
}


@click.command("create-account")
@click.option(
    "--robot",
    multiple=True,
    callback=robots_option,
    shell_complete=complete_robot,
    metavar="NAME",
    help="Robot host name; several (repeated, a,b, or @group of robots.toml) are done in "
    "parallel, the passwords asked once first. "
    "Default: $FETCHSYNC_ROBOT, $FETCH_ROBOT, the host of $ROS_MASTER_URI.",
)
@click.option(
    "--user",
    "user",
    metavar="NAME",
    help="The account to create on the robot (not the login: see --admin-user). "
    "Default: $FETCHSYNC_USER, $FETCH_USER, $USER.",
)
@click.option("--fullname", help="The user's full name. Default: NAME.")
@click.option(
    "--admin-user",
    default="fetch",
    show_default=True,
    envvar="FETCHSYNC_ADMIN_USER",
    help="The account that logs in and creates it: root, or a user with sudo rights.",
)
@click.option(
    "--skeleton",
    type=click.Path(file_okay=False),
    help="Home-directory skeleton to copy. Default: ~/.fetchsync/robot_skeleton, "
    "~/.fetch/robot_skeleton, else the built-in one.",
)
@click.option(
    "--key",
    type=click.Path(dir_okay=False),
    help="Public key to install. Default: ~/.ssh/id_ed25519.pub, id_ecdsa.pub, id_rsa.pub.",
)
@click.option(
    "--workspace",
    type=click.Path(file_okay=False),
    help="Local workspace whose robot counterpart the account uses, as push resolves "
    "it. Default: $FETCHSYNC_WORKSPACE, $FETCH_WORKSPACE, ~/$ROS_DISTRO.",
)
@click.option(
    "--remote-workspace",
    help="The account's workspace on the robot. Default: as push "
    "resolves it, else initialize.sh's choice (~/$ROS_DISTRO of the robot).",
)
@click.option(
    "--reset-password", is_flag=True, help="Set the password of an account that already exists."
)
@click.option(
    "--accept-host-key",
    metavar="SHA256:...",
    help="Accept the robot's host key with this fingerprint (shown when it is unknown).",
)
@click.option("--json", "as_json", is_flag=True, help="Print a JSON report instead of text.")
@fleet_options
@click.option("--password", expose_value=False, hidden=True, callback=_refuse_password_option)
@click.option("--fetch-password", expose_value=False, hidden=True, callback=_refuse_password_option)
def command(
    robot: str | None,
    user: str | None,
    fullname: str | None,
    admin_user: str,
    skeleton: str | None,
    key: str | None,
    workspace: str | None,
    remote_workspace: str | None,
    reset_password: bool,
    accept_host_key: str | None,
    as_json: bool,
    jobs: int,
    fail_fast: bool,
    retry_failed: bool,
) -> None:
    """Create a user's account on the robot, or repair an existing one.

    Through the admin login (root directly, anyone else through sudo): creates
    the user with a password, adds fetch_tools' groups that the robot has
    (adm, audio, cdrom, sudo, dip, plugdev, lpadmin, sambashare), installs your
    public key, copies the skeleton and runs its initialize.sh as the user.

    Passwords are asked on the terminal, or read from FETCHSYNC_NEW_PASSWORD
    and FETCHSYNC_ADMIN_PASSWORD; they never appear on a command line. For an
    existing account only what is missing is added; its password is kept
    unless --reset-password, and its recorded workspace is set to the one push
    uses now (run it again after changing workspaces).

    On several robots (--robot a,b or @group) the passwords are asked once,
    before the robots are worked on in parallel; a table ends it.
    """
    from fetchsync.chores.account import (
        DEFAULT_ADMIN,
        check_user_name,
        find_public_key,
        find_skeleton,
        load_skeleton,
        read_public_key,
    )
    from fetchsync.cli.fleet import robots_for
    from fetchsync.config import resolve_robot
    from fetchsync.errors import UsageError
    from fetchsync.link.transport import LOCAL_ROBOT

    robots = robots_for("create-account", robot, retry_failed=retry_failed)
    name = check_user_name(_account_user(user))
    admin = (admin_user or DEFAULT_ADMIN).strip()
    check_user_name(admin)
    targets = robots if robots is not None else [resolve_robot(robot)]
    if LOCAL_ROBOT in targets:
        raise UsageError(
            "create-account needs a real robot, not the local one", hint="pass --robot NAME"
        )
    skeleton_dir = find_skeleton(skeleton)
    sk = load_skeleton(skeleton_dir)
    key_path = find_public_key(key)
    public_key = read_public_key(key_path) if key_path is not None else None
    if public_key is None:
        click.echo(
            "create-account: warning: no public key found (~/.ssh/id_*.pub); "
            "none is installed, pass --key FILE to add one",
            err=True,
        )
    account = _Account(
        name=name,
        admin=admin,
        fullname=fullname,
        skeleton_dir=skeleton_dir,
        skeleton=sk,
        key=public_key,
        reset_password=reset_password,
        accept_host_key=accept_host_key,
        new_password=_Secret(NEW_PASSWORD_VAR, f"New password for {name}", confirm=True),
        admin_password=_Secret(
            ADMIN_PASSWORD_VAR,
            f"Password of {admin} on {targets[0] if robots is None else 'the robots'}",
            confirm=False,
        ),
    )
    if robots is not None:
        sys.exit(
            _fleet_create(
                robots,
                account,
                workspace=workspace,
                remote_workspace=remote_workspace,
                key_path=key_path,
                as_json=as_json,
                jobs=jobs,
                fail_fast=fail_fast,
            )
        )
    account_ws = _account_workspace(robot, name, workspace, remote_workspace)
    _say_where(targets[0], name, account_ws)
    report = account.create(
        targets[0],
        workspace=account_ws,
        say=lambda line: None if as_json else click.echo(line, err=True),
        on_stderr=_to_stderr,
    )
    if as_json:
        click.echo(json.dumps(report.to_json(), sort_keys=True))
    else:
        for line in _report_lines(report, key_path=key_path, skeleton=sk):
            click.echo(line)
    if report.error:
        from fetchsync.errors import RemoteError

        raise RemoteError(report.error)


class _Account:
    """The account to make, the same on every robot: who, with what, and the passwords
    (each asked at most once, whatever the number of robots)."""

    def __init__(
        self,
        *,
        name: str,
        admin: str,
        fullname: str | None,
        skeleton_dir: Any,
        skeleton: Any,
        key: str | None,
        reset_password: bool,
        accept_host_key: str | None,
        new_password: _Secret,
        admin_password: _Secret,
    ) -> None:
        self.name = name
        self.admin = admin
        self.fullname = fullname
        self.skeleton_dir = skeleton_dir
        self.skeleton = skeleton
        self.key = key
        self.reset_password = reset_password
        self.accept_host_key = accept_host_key
        self.new_password = new_password
        self.admin_password = admin_password

    def create(
        self,
        robot: str,
        *,
        workspace: str | None,
        say: Callable[[str], None],
        on_stderr: Callable[[bytes], None],
    ) -> Any:
        """Create or repair the account on ``robot`` through the admin login: the report."""
        from fetchsync.chores.account import (
            GROUPS,
            AccountRequest,
            AdminSession,
            check_fullname,
            is_legacy_skeleton,
        )
        from fetchsync.link.connection import remote_python
        from fetchsync.link.ssh import SSHTransport  # paramiko is slow to import: only now

        env = {}
        distro = os.environ.get("ROS_DISTRO", "").strip()
        if distro:
            env["ROS_DISTRO"] = distro
        if workspace:
            env["FETCH_WORKSPACE"] = workspace
        transport = SSHTransport.connect(
            robot,
            user=self.admin,
            accept_fingerprint=self.accept_host_key,
            password_callback=_login_callback(self.admin_password),
        )
        try:
            session = AdminSession(transport, admin=self.admin, robot=robot, python=remote_python())
            found = session.probe(self.name)
            if found.exists:
                say(
                    f"create-account: {self.name} already exists on {robot}; adding what is missing"
                )
            password = self.new_password.get() if not found.exists or self.reset_password else None
            sudo_password = None
            if not found.admin_is_root and session.sudo_asks_password():
                sudo_password = self.admin_password.get()
                session.check_sudo(sudo_password)
            request = AccountRequest(
                user=self.name,
                fullname=check_fullname(self.fullname or self.name),
                groups=GROUPS,
                key=self.key,
                skeleton=self.skeleton,
                env=env,
                password=password,
                workspace=workspace,
                ros_snippet="fetch_tools" if is_legacy_skeleton(self.skeleton_dir) else "fetchsync",
            )
            report = session.apply(
                request,
                sudo=not found.admin_is_root,
                sudo_password=sudo_password,
                on_stderr=on_stderr,
            )
        finally:
            transport.close()
        report.skeleton = str(self.skeleton.source)
        return report


def _fleet_create(
    robots: list[str],
    account: _Account,
    *,
    workspace: str | None,
    remote_workspace: str | None,
    key_path: Path | None,
    as_json: bool,
    jobs: int,
    fail_fast: bool,
) -> int:
    """create-account on each robot, in parallel once the passwords are asked (once each,
    here: the new one, and the admin's, which Enter leaves out when the admin logs in with
    a key and sudo asks none); each robot's lines prefixed; the table; the exit status."""
    from fetchsync.cli.fleet import Prefixed, RobotResult, finish, run_all
    from fetchsync.errors import RemoteError

    account.new_password.ask_first()
    account.admin_password.ask_first(optional="Enter: none, it logs in with a key")

    def work(robot: str, out: Prefixed) -> RobotResult:
        account_ws = _account_workspace(robot, account.name, workspace, remote_workspace)
        report = account.create(
            robot,
            workspace=account_ws,
            say=out.line,
            on_stderr=lambda data: _write_all(out.err, data),
        )
        if not as_json:
            for line in _report_lines(report, key_path=key_path, skeleton=account.skeleton):
                out.line(line, err=False)
        error = report.error or ""
        return RobotResult(
            robot,
            result="failed" if error else "ok",
            exit_code=RemoteError.exit_code if error else 0,
            error=error,
            report=report.to_json(),
        )

    results = run_all(robots, work, jobs=jobs, fail_fast=fail_fast)
    return finish("create-account", results, as_json=as_json)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def _to_stderr(data: bytes) -> None:
    """The robot's progress (initialize.sh's output), as it comes."""
    buffer = getattr(sys.stderr, "buffer", None)
    if buffer is not None:
        buffer.write(data)
        buffer.flush()
    else:  # a captured stderr (click's CliRunner) takes text
        sys.stderr.write(data.decode("utf-8", "replace"))
        sys.stderr.flush()
