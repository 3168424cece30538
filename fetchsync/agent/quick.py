"""A plain one-shot ``push`` through a warm process: the client side, kept light.

A fresh ``fetchsync push`` spends most of a one-edit push's time before its first
byte: the interpreter, click, the engine's imports, the state's opening (~125 ms
of CPU here, issue 24). The *resident* (:mod:`fetchsync.agent.resident`) is a
background process holding all of that warm, started by a plain push once its own
work is done; the next plain push asks it over the agent's owner-only control
socket and only prints its answer. This module is what such a push needs: the
request (carrying this install's place and version, the resolved target and the
settings that shape a push, so that a resident of another install, checkout or
environment never answers it), the answer's printing (the same lines as a push
made here), the resident's start, and :func:`fast_main`, the console entry's path
for a plain ``push`` that imports neither click nor the engine.

Anything unexpected (no resident, another install's, busy, dead mid-request)
gives None: the caller then pushes the normal way. A push is safe to redo.
"""

from __future__ import annotations

import _socket  # socket.py's selectors, array and enum classes: none needed to ask
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from fetchsync.environ import inheritable, is_secret
from fetchsync.places import MAX_SOCKET_PATH, robot_id, runtime_path

try:  # hashlib loads OpenSSL's libcrypto (~4 ms) for the two digests a fast path makes
    from _sha256 import sha256
except ImportError:  # Python >= 3.12 names it _sha2; a build without it: hashlib's
    try:
        from _sha2 import sha256  # type: ignore[import-not-found,no-redef]
    except ImportError:
        from hashlib import sha256  # type: ignore[assignment]

if TYPE_CHECKING:
    from fetchsync.config import Target

RESIDENT_VAR = "FETCHSYNC_RESIDENT"
DEFAULT_IDLE = 600.0  # seconds a resident waits for its next push before it exits
MAX_ANSWER = 64 << 20  # a report lists every conflict and error: bounded, not small
LOCK_WORDS = "resident pid"  # what a resident's lock file says: a watch may take it over
BUSY_WAIT = 2.0  # seconds a resident waits for the push before this one, then says busy
# the environment that shapes a push (target, state, link, endpoint, logging); a
# resident answers only a push made in the environment it was started in
_ENV_PREFIXES = ("FETCHSYNC_", "FETCH_", "ROS_", "XDG_", "SSH_")
_ENV_NAMES = ("HOME", "USER", "LOGNAME", "PATH", "PYTHONPATH", "TMPDIR")
_ENV_IGNORED = ("FETCHSYNC_TRACE",)  # where trace marks go: not how a push is made


def idle_seconds(environ: Any = os.environ) -> float:
    """How long a resident lives without a push: ``$FETCHSYNC_RESIDENT`` seconds (default
    600, as the connection master); 0 turns residents off. No connection master
    (``FETCHSYNC_PERSIST=0``) means no resident either: it works through the master."""
    from fetchsync.link.mux import persist_seconds

    if persist_seconds() <= 0:
        return 0.0
    value = environ.get(RESIDENT_VAR, "").strip().lower()
    if value in ("", "on", "yes", "true"):
        return DEFAULT_IDLE
    if value in ("off", "no", "false"):
        return 0.0
    try:
        return max(0.0, float(value))
    except ValueError:
        return DEFAULT_IDLE


def identity() -> dict[str, str]:
    """This install: the package's real place and version (a second venv, a checkout of
    another revision: another identity)."""
    import fetchsync

    return {
        "package": os.path.realpath(os.path.dirname(fetchsync.__file__)),
        "version": fetchsync.__version__,
    }


def env_key(environ: Any = os.environ) -> str:
    """A digest of the environment variables that shape a push."""
    names = sorted(
        k
        for k in environ
        if (k.startswith(_ENV_PREFIXES) or k in _ENV_NAMES)
        and k not in _ENV_IGNORED
        and not is_secret(k)  # the resident is not given them (fetchsync.environ)
    )
    text = "\0".join(f"{k}={environ[k]}" for k in names)
    return sha256(text.encode("utf-8", "surrogateescape")).hexdigest()


def target_fields(target: Target) -> dict[str, Any]:
    return {
        "robot": target.robot,
        "host": target.host,
        "user": target.user,
        "workspace": str(target.workspace),
        "remote_workspace": target.remote_workspace,
        "is_local": target.is_local,
    }


def target_from(fields: dict[str, Any]) -> Target:
    from fetchsync.config import Target

    return Target(
        robot=fields["robot"],
        host=fields["host"],
        user=fields["user"],
        workspace=Path(fields["workspace"]),
        remote_workspace=fields["remote_workspace"],
        is_local=bool(fields["is_local"]),
    )


def request(target: Target) -> dict[str, Any]:
    """A plain push's request, as a resident checks it."""
    return {
        "cmd": "push",
        "client": identity(),
        "target": target_fields(target),
        "env": env_key(),
    }


class Asked:
    """What asking agent sockets found, for the rest of this process: the sockets asked
    already (a fast path that fell back does not ask twice) and those where some process
    answered (then no resident is started there: its lock is taken)."""

    asked: set[str] = set()
    answered: set[str] = set()


def ask(
    sock: Path,
    target: Target,
    *,
    timeout: float = 3600.0,
    leave_offline: bool = False,
    meanwhile: Callable[[], object] | None = None,
) -> dict[str, Any] | None:
    """The answer of the agent or resident at ``sock`` to a plain push of ``target``, or
    None when there is none, or it declined (another install's, busy, gone mid-request).
    ``leave_offline``: the fast path leaves a watch agent whose robot is
    offline to the CLI's push (it asks again, and says so in its order). ``meanwhile``
    runs once the request is sent, while the push is made (the printing's imports)."""
    Asked.asked.add(str(sock))
    try:
        s = _socket.socket(_socket.AF_UNIX, _socket.SOCK_STREAM)
    except OSError:
        return None
    try:
        s.settimeout(5.0)
        s.connect(str(sock))
        if _peer_uid(s) != os.getuid():
            return None  # not ours: never trust, never send to it
        Asked.answered.add(str(sock))
        s.settimeout(timeout + 5)
        payload = dict(request(target), timeout=timeout)
        s.sendall(json.dumps(payload).encode() + b"\n")
        if meanwhile is not None:
            meanwhile()
        data = bytearray()
        while not data.endswith(b"\n") and len(data) < MAX_ANSWER:
            chunk = s.recv(1 << 20)
            if not chunk:
                break
            data += chunk
    except OSError:
        return None
    finally:
        s.close()
    if not data.endswith(b"\n"):
        return None  # it ended without an answer: killed, or not serving this push
    try:
        reply = json.loads(bytes(data))
    except ValueError:
        return None
    if not isinstance(reply, dict):
        return None
    if reply.get("offline") and leave_offline:
        Asked.asked.discard(str(sock))  # the CLI's push asks again and says it in order
        return None
    if reply.get("declined") or reply.get("busy"):
        return None
    if reply.get("fallback"):
        return None
    return reply


def answered_report(reply: dict[str, Any]) -> dict[str, Any] | None:
    """The report (``Report.to_json()``) in an agent's or resident's answer to a push;
    the error it answered raised as a push here raises it; None when a watch agent's
    robot is offline (said on stderr: the caller pushes directly, which reaches the
    robot or fails within the connect timeout)."""
    from fetchsync.errors import SyncError

    if reply.get("resident"):
        if reply.get("note"):
            _out(f"fetchsync: note: {reply['note']}", err=True)
        if not reply.get("ok"):
            raise rebuilt(reply)
        return dict(reply["report"], connection="resident")
    if reply.get("offline"):
        _out(
            f"fetchsync: the watch agent cannot reach its robot ({reply.get('error')}); "
            "pushing directly",
            err=True,
        )
        return None
    if not reply.get("ok"):
        raise SyncError(f"the watch agent could not push: {reply.get('error') or 'unknown error'}")
    return dict(reply.get("report") or {}, connection="agent")


def rebuilt(said: dict[str, Any]) -> Exception:
    """The FetchsyncError a resident's push raised, with its message, hint and exit code."""
    from fetchsync.errors import FetchsyncError

    exc = FetchsyncError(
        str(said.get("error") or "the resident's push failed"), hint=said.get("hint")
    )
    exc.exit_code = int(said.get("exit_code") or 1)
    return exc


def _peer_uid(s: _socket.socket) -> int:
    import struct

    creds = s.getsockopt(_socket.SOL_SOCKET, _socket.SO_PEERCRED, struct.calcsize("3i"))
    return int(struct.unpack("3i", creds)[1])


def start_resident(target: Target, sock: Path) -> None:
    """Start a resident for ``target`` in the background, detached: its own session, no
    terminal, stdin/stdout/stderr on /dev/null, so the push that starts it neither waits
    for it nor leaves it holding its output. posix_spawn: ~1 ms, no subprocess import."""
    # this process's own import path (absolute): the resident runs this very code, not
    # a ``fetchsync`` its working directory happens to hold
    path = [os.path.abspath(p) for p in sys.path]
    argv = [
        sys.executable,
        "-c",
        # no descriptor of the caller's beyond stdio (posix_spawn closes none): a harness's
        # pipe, a jobserver's, would wait for the resident's end (tests/test_resident_detach)
        # nothing imported from '' (-c's working directory: where the push was typed)
        "import sys; sys.path[:] = [p for p in sys.path if p]; "
        "import os, json; os.closerange(3, os.sysconf('SC_OPEN_MAX')); "
        "sys.path[:] = json.loads(sys.argv[1]); "
        "from fetchsync.agent.resident import main; sys.exit(main(sys.argv[2:]))",
        json.dumps(path),
        "--socket",
        str(sock),
        "--target",
        json.dumps(target_fields(target)),
        "--client",
        json.dumps(identity()),
    ]
    null = os.devnull
    actions = [
        (os.POSIX_SPAWN_OPEN, 0, null, os.O_RDONLY, 0),
        (os.POSIX_SPAWN_OPEN, 1, null, os.O_WRONLY, 0),
        (os.POSIX_SPAWN_OPEN, 2, null, os.O_WRONLY, 0),
    ]
    try:
        env = inheritable(os.environ)  # no password lingers in it (fetchsync.environ)
        os.posix_spawn(sys.executable, argv, env, file_actions=actions, setsid=True)
    except OSError:
        pass  # no resident: the next push is made the normal way


# What a src/ may hold and still count as empty: catkin's, colcon's and ament's markers
EMPTY_MARKERS = frozenset({"CATKIN_IGNORE", "COLCON_IGNORE", "AMENT_IGNORE"})


def pushable(src: Path, *, force: bool, whose: str) -> Path:
    """``src``, if a push may make the robot's src/ like it: it exists (most often a
    missing one is the wrong workspace) and holds files; with ``force``, made if need be."""
    from fetchsync.errors import ConfigError, SyncError

    if force:
        src.mkdir(parents=True, exist_ok=True)
        return src
    if not src.is_dir():
        raise ConfigError(
            f"{src} does not exist; nothing to push",
            hint="check --workspace; fetchsync config shows where it came from",
        )
    if not holds_files(src):
        raise SyncError(
            f"{src} holds no files (only directories or ignore markers, if "
            f"anything); pushing it would empty {whose} src/",
            hint="pass --force if that is what you want",
        )
    return src


def holds_files(src: Any) -> bool:
    """Whether ``src`` holds a file or link other than package markers (an empty
    directory, or one of empty directories and a CATKIN_IGNORE, is an emptied src/)."""
    from fetchsync.errors import SyncError

    unlisted: list[OSError] = []
    for dirpath, dirnames, filenames in os.walk(src, onerror=unlisted.append):
        if any(name not in EMPTY_MARKERS for name in filenames):
            return True
        # os.walk lists a symlink to a directory among the directories
        if any(os.path.islink(os.path.join(dirpath, d)) for d in dirnames):
            return True
    if unlisted and unlisted[0].filename == str(src):
        exc = unlisted[0]
        raise SyncError(f"cannot list {src}: {exc.strerror or exc}", hint="check its permissions")
    return bool(unlisted)  # a directory it could not list may hold files: the push says


def agent_paths(target: Target) -> tuple[Path, Path]:
    """The lock file and the control socket of the agent (or resident) for this target,
    in the private runtime directory (made, and checked to be ours).

    Here, not in service.py or control.py: every one-shot push asks whether an agent
    runs, and this module is the light one (a fast path imports neither logging nor
    the link's connection code)."""
    return runtime_paths("agent", _agent_identity(target))


def agent_socket(target: Target) -> Path:
    """Where the agent's (or resident's) socket for this target is, if there is one: the
    path of :func:`agent_paths`, found without making or checking a directory (asking
    trusts an answer only from a process of our uid: :func:`ask`)."""
    return _placed("agent", _agent_identity(target), made=False)[1]


def _agent_identity(target: Target) -> bytes:
    return f"{robot_id(target)}\0{target.remote_workspace}".encode("utf-8", "surrogateescape")


def runtime_paths(kind: str, identity: bytes) -> tuple[Path, Path]:
    """``KIND-KEY.lock`` and ``KIND-KEY.sock`` in the private runtime directory, KEY from
    ``identity``; in the short one when the socket's path would be too long for a socket."""
    return _placed(kind, identity, made=True)


def _placed(kind: str, identity: bytes, *, made: bool) -> tuple[Path, Path]:
    place: Callable[..., Path] = runtime_path
    if made:
        from fetchsync.link.mux import runtime_dir as place
    key = sha256(identity).hexdigest()[:20]
    base = place(short=False)
    sock = base / f"{kind}-{key}.sock"
    if len(os.fsencode(sock)) > MAX_SOCKET_PATH:
        base = place(short=True)
        sock = base / f"{kind}-{key}.sock"
    return base / f"{kind}-{key}.lock", sock


# --------------------------------------------------------------------------- printing
def human(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def _out(line: str, *, err: bool = False) -> None:
    stream = sys.stderr if err else sys.stdout
    stream.write(line + "\n")
    stream.flush()


def print_report(report: dict[str, Any], as_json: bool) -> None:
    """A push's or pull's report (``Report.to_json()``) as the CLI prints it."""
    from fetchsync.console import printable as p_

    if as_json:
        _out(json.dumps(report, indent=None, sort_keys=True))
        return
    dry_run = report["dry_run"]
    verb = "would change" if dry_run else ("pushed" if report["verb"] == "push" else "pulled")
    if dry_run:
        for p in report["planned"]:
            _out(
                f"  {p['op']:<7} {p_(p['path'])}" + (f"  ({p_(p['how'])})" if p.get("how") else "")
            )
    parts = [f"{report['files']} files", f"{report['dirs']} dirs"]
    if report["links"]:
        parts.append(f"{report['links']} links")
    parts.append(f"{report['deleted']} deleted")
    if report["reused"]:
        parts.append(f"{report['reused']} reused")
    if report["deltas"]:
        parts.append(f"{report['deltas']} by delta")
    _out(
        f"{report['verb']}: {verb} {', '.join(parts)}; sent {human(report['bytes_sent'])}, "
        f"received {human(report['bytes_received'])}; {len(report['conflicts'])} conflicts; "
        f"{report['seconds']:.2f}s"
    )
    for c in report["conflicts"]:
        if c.get("refused"):
            _out(f"  conflict: {p_(c['path'])} changed on the robot; left as it is", err=True)
        else:
            side = "on the robot" if report["verb"] == "push" else "locally"
            kept = "would be kept in" if dry_run else "is kept in"
            _out(
                f"  conflict: {p_(c['path'])} was changed {side} since the last sync; "
                f"that version {kept} {p_(c['kept'])}",
                err=True,
            )
    for s in report["skipped"]:
        _out(f"  skipped: {p_(s['path'])}: {p_(s['reason'])}", err=True)
    for e in report["errors"]:
        _out(f"  error: {p_(e['path'])}: {p_(e['error'])}", err=True)


# --------------------------------------------------------------------------- the fast path
def _raise_for(data: dict[str, Any]) -> None:
    from fetchsync.sync.engine import Report, raise_for

    fields = Report.__dataclass_fields__
    raise_for(Report(**{k: v for k, v in data.items() if k in fields}), strict=False)


def plain_push(argv: list[str]) -> dict[str, Any] | None:
    """``argv`` as a plain push this module can make exactly, or None: ``push`` with at
    most ``--robot NAME`` (one robot), ``--workspace DIR`` and ``--json``; anything else
    (another verb, any other option, a list or group of robots) is the CLI's."""
    if not argv or argv[0] != "push":
        return None
    out: dict[str, Any] = {"robot": None, "workspace": None, "as_json": False}
    args = argv[1:]
    i = 0
    while i < len(args):
        arg = args[i]
        name, eq, value = arg.partition("=")
        if arg == "--json":
            if out["as_json"]:
                return None
            out["as_json"] = True
        elif name in ("--robot", "--workspace"):
            if not eq:
                if i + 1 >= len(args):
                    return None
                i += 1
                value = args[i]
            key = name[2:]
            if out[key] is not None or not value or value.startswith("-"):
                return None  # repeated (several robots), or empty: the CLI says what it is
            out[key] = value
        else:
            return None
        i += 1
    from fetchsync.config import ROBOT_VARS

    for value in [out["robot"] or ""] + [os.environ.get(v, "") for v in ROBOT_VARS]:
        if "," in value or value.strip().startswith("@"):
            return None  # a fleet (fetchsync.cli.fleet)
    return out


def _printing() -> None:
    import fetchsync.console  # noqa: F401


def _as_logged_in(target: Target, reply: dict[str, Any]) -> Target:
    """``target`` with the login the resident found for it (it read the ssh config
    for this push, in this push's environment), so that printing it reads nothing."""
    login = reply.get("login")
    if target.user is not None or not isinstance(login, str) or not login:
        return target  # given, the local robot, or an agent that does not say
    from fetchsync.config import Target

    fields = dict(target_fields(target), user=login, workspace=target.workspace)
    return Target(**fields)


def fast_main(argv: list[str]) -> int | None:
    """A plain ``push`` answered by a resident, without click or the engine: the exit
    code, or None (nothing printed) when the CLI must make it (no resident, another
    install's, busy, gone mid-request, a watch agent: it asks that again itself)."""
    from fetchsync.trace import mark

    given = plain_push(argv)
    if given is None:
        return None
    from fetchsync.config import resolve_target
    from fetchsync.errors import FetchsyncError

    try:
        target = resolve_target(
            robot=given["robot"],
            user=None,
            workspace=given["workspace"],
            remote_workspace=None,
            defer_ssh_user=True,
        )
        sock = agent_socket(target)
    except FetchsyncError:
        return None  # the CLI says it in its words
    if not sock.exists():
        return None
    mark("quick: asking the resident")
    try:
        # the printing's imports (~1-2 ms) while the resident pushes, not after
        reply = ask(sock, target, leave_offline=True, meanwhile=_printing)
    except KeyboardInterrupt:
        _out("fetchsync: interrupted", err=True)
        return 130
    mark("quick: answered")
    if reply is None:
        return None
    from fetchsync.console import printable, where_line

    src = target.workspace / "src"
    remote = target.remote_workspace + "/src"
    _out(where_line("push", _as_logged_in(target, reply), local=src, remote=remote), err=True)
    try:
        data = answered_report(reply)
        assert data is not None
        data.update(robot=target.robot, local=str(src), remote=remote)
        print_report(data, given["as_json"])
        if "raise" not in reply:  # a watch agent of an older fetchsync: as the CLI does
            _raise_for(data)
        if reply.get("raise"):
            raise rebuilt(reply["raise"])
    except FetchsyncError as exc:
        _out(f"fetchsync: error: {printable(exc)}", err=True)
        return exc.exit_code
    return 0
