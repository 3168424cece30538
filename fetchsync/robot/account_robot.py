# Python 3.6 runs this (no `from __future__ import annotations`, no capture_output):
# ruff: noqa: FA100, UP022
"""The robot side of ``fetchsync create-account``: one program, run as root, fed on stdin.

:mod:`fetchsync.chores.account` sends this file's text over the SSH channel and a
short bootstrap in the command line executes it (see ``BOOTSTRAP`` there);
nothing is installed on the robot. It runs on the robot's Python (3.6 and
later: Ubuntu 18.04, Fetch's Melodic image) with the standard library only.

Input: one JSON line on stdin, the request (see :func:`main`). The new
password travels only in it: it reaches ``chpasswd`` on that command's stdin,
never a command line, the environment or a file.

Output: one ``FETCHSYNC-ACCOUNT-RESULT <json>`` line on stdout (a login shell
may print other lines); progress and ``initialize.sh``'s output on stderr.

As root it creates the account, sets the password and adds the groups.
Everything inside the home directory (the SSH key, the skeleton, the run of
``initialize.sh``) is done by a child that has become the user, so a symbolic
link the user planted cannot make root write outside their home, and every
file the user gets is theirs.
"""

import base64
import glob
import grp
import json
import os
import pwd
import re
import shlex
import subprocess
import sys
import tempfile
import time
import traceback
from typing import Any, Dict, List, Optional, Tuple

RESULT_PREFIX = "FETCHSYNC-ACCOUNT-RESULT "
STATE_DIR = ".fetchsync"
INIT_NAME = "initialize.sh"
INIT_MARKER = "initialized"
DEFAULT_UID_MIN = 1000
SAFE_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
WORKSPACE_FILE = ".bashrc.d/30-workspace.sh"
FETCH_TOOLS_FILE = ".bashrc.d/40-ros-setup.sh"
HEADER = "# Written by fetchsync create-account"
OUR_HEADERS = (HEADER, "# Written by initialize.sh")
# fetch_tools' create-account appended such lines, and nothing else, to 40-ros-setup.sh.
_FETCH_TOOLS_LINE = re.compile(r"source \S+/setup\.bash\Z")


class Failure(Exception):
    """A step failed; the message goes back to the laptop as is."""


def main() -> int:
    result: Dict[str, Any] = {}
    try:
        line = sys.stdin.buffer.readline()
        request = json.loads(line.decode("utf-8"))
        del line
        result = apply(request)
        status = 0 if "error" not in result else 1
    except Failure as exc:
        result["error"] = str(exc)
        status = 1
    except Exception as exc:  # noqa: BLE001 - reported to the laptop, never a silent death
        result["error"] = f"unexpected failure on the robot: {exc!r}"
        result["traceback"] = traceback.format_exc()
        status = 1
    sys.stdout.write(RESULT_PREFIX + json.dumps(result, sort_keys=True) + "\n")
    sys.stdout.flush()
    return status


def apply(request: Dict[str, Any]) -> Dict[str, Any]:
    """Create or repair the account described by ``request``; the result as a dict."""
    if os.geteuid() != 0:
        raise Failure("the account program is not running as root")
    name = request["user"]
    result: Dict[str, Any] = {"user": name}
    try:
        entry = pwd.getpwnam(name)
    except KeyError:
        entry = None
    if entry is None:
        if request.get("password") is None:
            raise Failure(f"{name} does not exist and no password was sent")
        create_user(name, request.get("fullname") or name)
        entry = pwd.getpwnam(name)
        result["created"] = True
    else:
        if entry.pw_uid < uid_min():
            raise Failure(f"{name} is a system account (uid {entry.pw_uid}); refusing to change it")
        result["created"] = False
    result["uid"] = entry.pw_uid
    result["home"] = entry.pw_dir
    # Out of the request from here on: only chpasswd and initialize.sh's sudo get it.
    password = request.pop("password", None)
    if password is not None:
        set_password(name, password)
        result["password_set"] = True
    else:
        result["password_set"] = False
    result["groups_added"], result["groups_absent"] = add_groups(name, entry, request["groups"])
    result["home_created"] = ensure_home(entry)
    result.update(in_home_as(entry, request, overwrite=result["created"], password=password))
    del password
    return result


def uid_min() -> int:
    try:
        with open("/etc/login.defs") as f:
            for line in f:
                parts = line.split()
                if len(parts) >= 2 and parts[0] == "UID_MIN":
                    return int(parts[1])
    except (OSError, ValueError):
        pass
    return DEFAULT_UID_MIN


def run(argv: List[str], *, stdin: Optional[bytes] = None) -> None:
    """Run a system tool; raise Failure with its stderr (never its stdin) when it fails."""
    try:
        proc = subprocess.run(
            argv,
            input=stdin if stdin is not None else b"",
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=_tool_env(),
            check=False,
        )
    except OSError as exc:
        raise Failure(f"cannot run {argv[0]} on the robot: {exc.strerror}") from None
    if proc.returncode != 0:
        detail = (proc.stderr or proc.stdout).decode("utf-8", "replace").strip()
        raise Failure(f"{argv[0]} failed with exit {proc.returncode}: {detail}")


def create_user(name: str, fullname: str) -> None:
    argv = ["useradd", "--create-home", "--shell", "/bin/bash", "--comment", fullname]
    try:
        grp.getgrnam(name)
        argv += ["--gid", name]  # a group of that name already exists: make it the user's
    except KeyError:
        argv += ["--user-group"]
    run(argv + ["--", name])


def set_password(name: str, password: str) -> None:
    # chpasswd reads "name:password" lines on stdin: the secret stays off every command line.
    run(["chpasswd"], stdin=f"{name}:{password}\n".encode())


def add_groups(
    name: str, entry: pwd.struct_passwd, wanted: List[str]
) -> Tuple[List[str], List[str]]:
    """Add ``name`` to those of ``wanted`` that exist; (added, absent)."""
    added, absent = [], []
    for group in wanted:
        try:
            info = grp.getgrnam(group)
        except KeyError:
            absent.append(group)
            continue
        if info.gr_gid != entry.pw_gid and name not in info.gr_mem:
            added.append(group)
    if added:
        run(["usermod", "--append", "--groups", ",".join(added), "--", name])
    return added, absent


def ensure_home(entry: pwd.struct_passwd) -> bool:
    """Create a missing home directory (owned by the user); True when it was missing."""
    home = entry.pw_dir
    if os.path.lexists(home):
        return False
    os.makedirs(os.path.dirname(home) or "/", exist_ok=True)
    os.mkdir(home, 0o750)
    os.chown(home, entry.pw_uid, entry.pw_gid)
    return True


def in_home_as(
    entry: pwd.struct_passwd,
    request: Dict[str, Any],
    *,
    overwrite: bool,
    password: Optional[str] = None,
) -> Dict[str, Any]:
    """Do the home-directory work in a child that has become the user; its result."""
    read_fd, write_fd = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:  # the child
        os.close(read_fd)
        out: Dict[str, Any] = {}
        code = 0
        try:
            become(entry)
            out = furnish(entry, request, overwrite=overwrite, password=password)
        except Failure as exc:
            out["error"] = str(exc)
        except BaseException as exc:  # noqa: BLE001 - the parent must hear of it
            out["error"] = f"unexpected failure as {entry.pw_name}: {exc!r}"
            out["traceback"] = traceback.format_exc()
        try:
            with os.fdopen(write_fd, "w") as f:
                f.write(json.dumps(out))
        except BaseException:  # noqa: BLE001
            code = 1
        os._exit(code)
    os.close(write_fd)
    with os.fdopen(read_fd) as f:
        text = f.read()
    os.waitpid(pid, 0)
    if not text:
        raise Failure(f"the step run as {entry.pw_name} died without a result")
    return dict(json.loads(text))


def become(entry: pwd.struct_passwd) -> None:
    os.initgroups(entry.pw_name, entry.pw_gid)
    os.setgid(entry.pw_gid)
    os.setuid(entry.pw_uid)
    os.umask(0o022)
    os.chdir(entry.pw_dir)


def furnish(
    entry: pwd.struct_passwd,
    request: Dict[str, Any],
    *,
    overwrite: bool,
    password: Optional[str] = None,
) -> Dict[str, Any]:
    """As the user: key, skeleton, initialize.sh. Runs in the home directory."""
    out: Dict[str, Any] = {"key": install_key(request.get("key"))}
    out["skeleton_added"] = copy_skeleton(request.get("skeleton") or [], overwrite=overwrite)
    # Before initialize.sh, which reads it: the workspace push uses, fixed on every run.
    out.update(record_workspace(entry, request))
    init = request.get("init")
    if init is None:
        out["initialize"] = "none"
        return out
    script = os.path.join(STATE_DIR, INIT_NAME)
    marker = os.path.join(STATE_DIR, INIT_MARKER)
    os.makedirs(STATE_DIR, mode=0o755, exist_ok=True)
    write_file(script, base64.b64decode(init), 0o755)
    if os.path.exists(marker):
        out["initialize"] = "already"
        return out
    code = run_init(entry, script, request.get("env") or {}, password=password)
    if code != 0:
        out["initialize"] = "failed"
        out["initialize_exit"] = code
        out["error"] = f"~/{script} failed with exit {code} (its output is above)"
        return out
    write_file(marker, time.strftime("%Y-%m-%dT%H:%M:%S%z\n").encode(), 0o644)
    out["initialize"] = "ran"
    if not out.get("workspace"):
        # Nothing resolved on the laptop: say what initialize.sh chose.
        chosen = read_exports(WORKSPACE_FILE).get("FETCH_WORKSPACE")
        if chosen:
            out.update(
                workspace=chosen, workspace_record="initialize.sh", workspace_file=WORKSPACE_FILE
            )
    return out


def record_workspace(entry: pwd.struct_passwd, request: Dict[str, Any]) -> Dict[str, Any]:
    """Write the account's workspace (and ROS distribution) where its shells read them.

    A file fetchsync (or fetch_tools) wrote is rewritten when it says otherwise, so
    running create-account again fixes a wrong workspace; a file of the user's own is
    left alone. The built-in skeleton reads ``30-workspace.sh``; fetch_tools' skeleton
    gets fetch_tools' ``40-ros-setup.sh``, sourcing ROS and the workspace's devel/.
    """
    workspace = request.get("workspace")
    distro = (request.get("env") or {}).get("ROS_DISTRO") or ""
    legacy = request.get("ros_snippet") == "fetch_tools"
    path = FETCH_TOOLS_FILE if legacy else WORKSPACE_FILE
    if os.path.islink(path) or (os.path.lexists(path) and not os.path.isfile(path)):
        # A link or a FIFO is the user's doing (and a FIFO would block the read).
        return {"workspace_record": "yours", "workspace_file": path}
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            old: Optional[str] = f.read()
    except FileNotFoundError:
        old = None
    if old is not None and not is_ours(old):
        return {"workspace_record": "yours", "workspace_file": path}
    if legacy:
        was = _fetch_tools_workspace(old or "")
        distro = distro or _only_distro()
    else:
        exports = read_exports(path) if old is not None else {}
        was = exports.get("FETCH_WORKSPACE", "")
        distro = distro or exports.get("ROS_DISTRO", "")
    if not workspace:
        if legacy and distro:
            workspace = "~/" + distro  # fetch_tools' default, ~/$ROS_DISTRO
        else:
            return {"workspace_record": "unresolved"}
    absolute = expand_home(workspace, entry.pw_dir)
    text = fetch_tools_snippet(distro, absolute) if legacy else workspace_exports(distro, absolute)
    result = {"workspace": workspace, "workspace_file": path}
    if old == text:
        result["workspace_record"] = "kept"
        return result
    os.makedirs(os.path.dirname(path), mode=0o755, exist_ok=True)
    write_file(path, text.encode("utf-8"), 0o644)
    result["workspace_record"] = "written" if old is None else "updated"
    if old is not None and was and was != absolute:
        result["workspace_was"] = was
    return result


def is_ours(text: str) -> bool:
    """Written by fetchsync, by the built-in initialize.sh, or by fetch_tools' create-account."""
    if text.startswith(OUR_HEADERS):
        return True
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return bool(lines) and all(_FETCH_TOOLS_LINE.match(line) for line in lines)


def workspace_exports(distro: str, workspace: str) -> str:
    lines = [HEADER + ": the ROS distribution and the workspace of this account."]
    if distro:
        lines.append("export ROS_DISTRO=" + shlex.quote(distro))
    lines.append("export FETCH_WORKSPACE=" + shlex.quote(workspace))
    return "\n".join(lines) + "\n"


def fetch_tools_snippet(distro: str, workspace: str) -> str:
    lines = [HEADER + ", as fetch_tools did: ROS, then the workspace built over it."]
    setups = ["/opt/ros/" + distro + "/setup.bash"] if distro else []
    setups.append(workspace.rstrip("/") + "/devel/setup.bash")
    for setup in setups:
        q = shlex.quote(setup)
        lines.append("if [ -f " + q + " ]; then source " + q + "; fi")
    return "\n".join(lines) + "\n"


def _fetch_tools_workspace(text: str) -> str:
    for line in text.splitlines():
        for word in shlex.split(line, comments=True) if "source" in line else []:
            if word.endswith("/devel/setup.bash"):
                return word[: -len("/devel/setup.bash")]
    return ""


def read_exports(path: str) -> Dict[str, str]:
    """``export NAME=VALUE`` lines of a shell file, unquoted; {} when unreadable."""
    out: Dict[str, str] = {}
    if not os.path.isfile(path):
        return out
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            lines = f.read().splitlines()
    except OSError:
        return out
    for line in lines:
        try:
            words = shlex.split(line, comments=True)
        except ValueError:
            continue
        if len(words) == 2 and words[0] == "export" and "=" in words[1]:
            name, _, value = words[1].partition("=")
            out[name] = value
    return out


def expand_home(path: str, home: str) -> str:
    if path == "~" or path.startswith("~/"):
        return home.rstrip("/") + path[1:]
    return path


def _only_distro() -> str:
    """The ROS distribution under /opt/ros when there is exactly one."""
    found = glob.glob("/opt/ros/*/setup.bash")
    return os.path.basename(os.path.dirname(found[0])) if len(found) == 1 else ""


def install_key(key: Optional[str]) -> str:
    """Append ``key`` to ~/.ssh/authorized_keys unless it is there; what happened."""
    if not key:
        return "none"
    blob = key.split()[1]
    os.makedirs(".ssh", mode=0o700, exist_ok=True)
    path = os.path.join(".ssh", "authorized_keys")
    try:
        with open(path, "rb") as f:
            existing = f.read().decode("utf-8", "replace")
    except FileNotFoundError:
        existing = ""
    for line in existing.splitlines():
        # A line may start with options; the key's base64 blob identifies it.
        if blob in line.split():
            return "present"
    text = ("" if not existing or existing.endswith("\n") else "\n") + key + "\n"
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    return "added"


def copy_skeleton(entries: List[Dict[str, Any]], *, overwrite: bool) -> List[str]:
    """Create the skeleton's directories and files; existing files are replaced only
    with ``overwrite`` (a new account, whose files came from /etc/skel)."""
    added = []
    for item in sorted(entries, key=lambda e: e["path"]):
        path = check_relative(item["path"])
        mode = int(item["mode"]) & 0o755
        if item["type"] == "dir":
            if not os.path.lexists(path):
                os.mkdir(path, mode | 0o700)
            continue
        if os.path.lexists(path) and not (overwrite and os.path.isfile(path)):
            continue
        write_file(path, base64.b64decode(item["data"]), mode | 0o600)
        added.append(path)
    return added


def check_relative(path: str) -> str:
    parts = path.split("/")
    if not path or path.startswith("/") or "\0" in path or any(p in ("", ".", "..") for p in parts):
        raise Failure(f"refusing the skeleton path {path!r}")
    return path


def write_file(path: str, data: bytes, mode: int) -> None:
    """Write through a temporary beside ``path`` and rename it: never through a link."""
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path) or ".", prefix=".fetchsync-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            os.fchmod(f.fileno(), mode)
        os.replace(tmp, path)
    except BaseException:
        if os.path.lexists(tmp):
            os.unlink(tmp)
        raise


def run_init(
    entry: pwd.struct_passwd, script: str, extra: Dict[str, str], *, password: Optional[str] = None
) -> int:
    """Run initialize.sh as the user (we are the user already), its output on our stderr.

    With the account's password known (a new account, --reset-password), its
    ``sudo`` works as fetch_tools' did (which primed sudo with that password):
    a ``sudo`` first on its PATH validates with the password read from an
    inherited descriptor of an anonymous file (:func:`password_fd`), then runs
    the command with that fresh credential. The password is in no argument,
    environment, file name or log; only the user's own processes can read it.
    """
    env = {
        "HOME": entry.pw_dir,
        "USER": entry.pw_name,
        "LOGNAME": entry.pw_name,
        "SHELL": entry.pw_shell or "/bin/bash",
        "PATH": SAFE_PATH,
    }
    for name in ("LANG", "LC_ALL"):
        if os.environ.get(name):
            env[name] = os.environ[name]
    env.update({str(k): str(v) for k, v in extra.items()})
    if env.get("FETCH_WORKSPACE"):
        # fetch_tools handed its initialize.sh an expanded path (`mkdir -p $FETCH_WORKSPACE/src`
        # does no tilde expansion).
        env["FETCH_WORKSPACE"] = expand_home(env["FETCH_WORKSPACE"], entry.pw_dir)
    sys.stderr.write(f"fetchsync: running ~/{script} as {entry.pw_name} on the robot\n")
    sys.stderr.flush()
    real_sudo = _which("sudo")
    fd = password_fd(password) if password is not None and real_sudo else None
    bin_dir = None
    try:
        if fd is not None and real_sudo:
            bin_dir = tempfile.mkdtemp(prefix="sudo-", dir=STATE_DIR)
            write_file(os.path.join(bin_dir, "sudo"), sudo_wrapper(real_sudo, fd).encode(), 0o700)
            env["PATH"] = os.path.abspath(bin_dir) + ":" + env["PATH"]
        # Its output is progress for the user: stderr, so stdout carries only our result.
        proc = subprocess.run(
            ["/bin/bash", script],
            cwd=entry.pw_dir,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=sys.stderr.fileno(),
            stderr=sys.stderr.fileno(),
            check=False,
            pass_fds=(fd,) if fd is not None else (),
        )
    finally:
        if fd is not None:
            os.close(fd)
        if bin_dir is not None:
            for name in os.listdir(bin_dir):
                os.unlink(os.path.join(bin_dir, name))
            os.rmdir(bin_dir)
    return proc.returncode


def password_fd(password: str) -> int:
    """A descriptor of an anonymous file holding ``password`` and a newline.

    Opening ``/proc/self/fd/N`` reopens it from the start, so every sudo can
    read it; it has no name, so nothing else finds it (memfd where the kernel
    and Python have it, else an unlinked temporary file).
    """
    data = (password + "\n").encode("utf-8")
    memfd_create = getattr(os, "memfd_create", None)
    fd = -1
    if memfd_create is not None:
        try:
            fd = memfd_create("fetchsync-sudo", 0)
        except OSError:
            fd = -1
    if fd < 0:
        with tempfile.TemporaryFile(dir=STATE_DIR) as f:
            fd = os.dup(f.fileno())
    os.write(fd, data)
    os.fchmod(fd, 0o600)
    return fd


def sudo_wrapper(real_sudo: str, fd: int) -> str:
    """The ``sudo`` initialize.sh finds first on its PATH (see :func:`run_init`)."""
    sudo = shlex.quote(real_sudo)
    return (
        "#!/bin/sh\n"
        "# fetchsync create-account: sudo for initialize.sh. The account's password is read\n"
        f"# by sudo -S from descriptor {fd} (an anonymous file), to validate; the command then\n"
        "# runs with that credential, its stdin untouched.\n"
        f"{sudo} -S -p '' -v </proc/self/fd/{fd} >/dev/null 2>&1\n"
        f'{sudo} -n "$@"\n'
    )


def _which(name: str) -> Optional[str]:
    for d in SAFE_PATH.split(":"):
        path = os.path.join(d, name)
        if os.path.isfile(path) and os.access(path, os.X_OK):
            return path
    return None


def _tool_env() -> Dict[str, str]:
    env = {"PATH": SAFE_PATH, "LC_ALL": "C"}
    return env


if __name__ == "__main__":
    sys.exit(main())
