"""The SSH transport: run commands on a robot over paramiko, the way ``ssh`` would.

:class:`SSHTransport` implements :class:`fetchsync.link.transport.Transport`. It
honours ``~/.ssh/config`` (HostName, Port, User, IdentityFile, IdentitiesOnly,
ProxyCommand, ProxyJump, UserKnownHostsFile, GlobalKnownHostsFile,
HostKeyAlias, HashKnownHosts), the ssh-agent and known_hosts, so that a robot
``ssh NAME`` reaches is reached by ``fetchsync`` too.

Host keys: a key known_hosts does not list is refused with its SHA256
fingerprint, unless the caller passes that very fingerprint (the user saw it
and accepts it); it is then recorded. A key that differs from the one listed
is always refused.

paramiko, socket and OS exceptions are mapped here to
:class:`~fetchsync.errors.ConnectError` (and its :class:`HostKeyError`) while
connecting, and to :class:`~fetchsync.errors.LinkLostError` once connected.
Passwords and passphrases come from a callback and are never logged.
"""

# ruff: noqa: E402  (paramiko is imported through import_paramiko, before the modules that use it)
from __future__ import annotations

import contextlib
import errno
import hmac
import logging
import os
import re
import select
import shlex
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from fetchsync.config import allow_match_exec, import_paramiko

import_paramiko()  # without invoke: only an ssh config's Match exec needs it (allow_match_exec)

import paramiko
from paramiko.auth_handler import AuthHandler
from paramiko.message import Message
from paramiko.pkey import UnknownKeyType
from paramiko.ssh_exception import (
    AuthenticationException,
    BadAuthenticationType,
    ChannelException,
    IncompatiblePeer,
    ProxyCommandFailure,
    SSHException,
)

from fetchsync.environ import inheritable
from fetchsync.errors import ConfigError, ConnectError, HostKeyError, LinkLostError, TransportError
from fetchsync.link import early as early_route
from fetchsync.link.channels import (
    Packetizer,
    SessionSlots,
    send_data,
    send_eof,
    send_exec,
    send_window_change,
)
from fetchsync.link.transport import Capabilities, Channel
from fetchsync.protocol.wire import widen_pipe
from fetchsync.trace import mark

mark("ssh: paramiko imported")
log = logging.getLogger(__name__)
# paramiko logs a dropped link as an ERROR ("Socket exception: ...") before we
# report it as a LinkLostError; with no handler configured Python would print
# it raw to stderr as a second line. -v still shows it through the root logger.
logging.getLogger("paramiko").addHandler(logging.NullHandler())

PasswordCallback = Callable[[str], "str | None"]
"""Asked for a password or a key's passphrase; gets the prompt, returns None to skip."""

SSH_PORT = 22
DEFAULT_IDENTITIES = ("id_ed25519", "id_ecdsa", "id_rsa")
DEFAULT_KNOWN_HOSTS = "~/.ssh/known_hosts"
DEFAULT_GLOBAL_KNOWN_HOSTS = ("/etc/ssh/ssh_known_hosts", "/etc/ssh/ssh_known_hosts2")
KEEPALIVE_REQUEST = "keepalive@openssh.com"
_MAX_HOPS = 8
_PASSWORD_TRIES = 3
_ENV_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


@dataclass(frozen=True)
class HostSettings:
    """What the ssh config says about one host, with our overrides applied."""

    alias: str
    """The name asked for (``robot``); config sections match on it."""
    hostname: str
    port: int
    user: str
    identity_files: tuple[str, ...]
    """From IdentityFile, ``~`` and %-tokens expanded; empty when the config names none."""
    identities_only: bool
    proxy_command: str | None
    proxy_jump: str | None
    known_hosts_files: tuple[str, ...]
    global_known_hosts_files: tuple[str, ...]
    host_key_alias: str | None
    hash_known_hosts: bool

    @property
    def known_hosts_name(self) -> str:
        """The name known_hosts lists this host under (``[host]:port`` off port 22)."""
        if self.host_key_alias:
            return self.host_key_alias
        name = self.hostname.lower()
        return name if self.port == SSH_PORT else f"[{name}]:{self.port}"

    @property
    def display(self) -> str:
        """``robot`` or ``robot (10.0.0.7:2222)`` for messages."""
        if self.alias == self.hostname and self.port == SSH_PORT:
            return self.alias
        return f"{self.alias} ({_host_port(self.hostname, self.port)})"


def load_ssh_config(path: str | os.PathLike[str] | None = None) -> paramiko.SSHConfig:
    """Parse ``path``, by default ``~/.ssh/config`` when it exists (else an empty config).

    A file parsed before in this process, still the same file (device, inode, size,
    mtime and ctime, and at least _SETTLED old when it was read: a write since moves
    its ctime), is not parsed again: a fleet push connects to each of its robots
    through the same config, whose Host blocks name them all (issue 27: 1.8 ms a
    robot for 20 robots' blocks, growing with the fleet). Nothing changes a parsed
    config: paramiko's lookups copy what they return."""
    if path is None:
        default = Path(os.path.expanduser("~/.ssh/config"))
        if not default.is_file():
            return paramiko.SSHConfig()
        path = default
    name = os.fspath(path)
    try:
        before = os.stat(name)
        with _PARSED_LOCK:
            kept = _PARSED.get(name)
        if kept is not None and kept[0] == _identity(before):
            return kept[1]
        config = allow_match_exec(paramiko.SSHConfig.from_path(name))
        after = os.stat(name)
    except OSError as exc:
        raise ConfigError(f"cannot read the ssh config {name}: {exc.strerror}") from exc
    except SSHException as exc:
        raise ConfigError(f"cannot parse the ssh config {name}: {exc}") from exc
    settled = time.time_ns() - max(after.st_mtime_ns, after.st_ctime_ns) >= _SETTLED
    if settled and _identity(after) == _identity(before):
        with _PARSED_LOCK:
            _PARSED[name] = (_identity(after), config)
    return config


_SETTLED = 2_000_000_000  # ns: a file's stamps this old when read are past any write then
_PARSED: dict[str, tuple[tuple[int, ...], paramiko.SSHConfig]] = {}
_PARSED_LOCK = threading.Lock()


def _identity(st: os.stat_result) -> tuple[int, ...]:
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def resolve_host(
    alias: str,
    *,
    config: paramiko.SSHConfig,
    user: str | None = None,
    port: int | None = None,
) -> HostSettings:
    """Look ``alias`` up in ``config``; ``user`` and ``port`` win over it when given."""
    found = config.lookup(alias)
    try:
        config_port = int(found.get("port", SSH_PORT))
    except ValueError as exc:
        raise ConfigError(
            f"invalid Port {found.get('port')!r} for {alias} in the ssh config"
        ) from exc
    hostname = str(found.get("hostname", alias))
    login = user or found.get("user") or _local_user()
    known = _split_files(found.get("userknownhostsfile"), default=(DEFAULT_KNOWN_HOSTS,))
    global_known = _split_files(
        found.get("globalknownhostsfile"), default=DEFAULT_GLOBAL_KNOWN_HOSTS
    )
    tokens = {"%d": os.path.expanduser("~"), "%u": _local_user(), "%h": hostname, "%k": alias}
    proxy_jump = found.get("proxyjump")
    proxy_command = found.get("proxycommand")
    return HostSettings(
        alias=alias,
        hostname=hostname,
        port=port or config_port,
        user=str(login),
        identity_files=tuple(os.path.expanduser(p) for p in found.get("identityfile", [])),
        identities_only=_yes(found.get("identitiesonly")),
        proxy_command=None
        if not proxy_command or proxy_command.lower() == "none"
        else proxy_command,
        proxy_jump=None if not proxy_jump or proxy_jump.lower() == "none" else proxy_jump,
        known_hosts_files=tuple(_expand_tokens(p, tokens) for p in known),
        global_known_hosts_files=tuple(_expand_tokens(p, tokens) for p in global_known),
        host_key_alias=found.get("hostkeyalias"),
        hash_known_hosts=_yes(found.get("hashknownhosts")),
    )


class SSHChannel:
    """A command running on the robot, over one SSH session channel (a :class:`Channel`)."""

    def __init__(self, chan: paramiko.Channel, transport: paramiko.Transport, *, name: str) -> None:
        self._chan = chan
        self._transport = transport
        self._name = name

    def send_all(self, data: bytes | memoryview) -> None:
        # paramiko's sendall re-slices what is left after every 32 KiB packet,
        # copying it again each time; a memoryview's slices copy nothing
        view = memoryview(data)
        try:
            while view:
                view = view[send_data(self._chan, view) :]  # never after our CLOSE
        except (OSError, EOFError, SSHException) as exc:
            raise self._lost("while sending") from exc

    def resize_pty(self, *, width: int, height: int) -> None:
        """The robot's PTY to the terminal's new size (never after our CLOSE: channels)."""
        send_window_change(self._chan, width=width, height=height)

    def recv(self, n: int) -> bytes:
        try:
            data: bytes = self._chan.recv(n)
        except (OSError, EOFError, SSHException) as exc:
            raise self._lost("while receiving") from exc
        if not data and self._link_died():
            raise self._lost("before the command finished")
        return data

    def ready(self) -> bool:
        return bool(self._chan.recv_ready() or self._chan.eof_received or self._chan.closed)

    def recv_stderr(self, n: int) -> bytes:
        # The stdout side reports a lost link; a stderr drain just ends.
        try:
            return bytes(self._chan.recv_stderr(n))
        except (OSError, EOFError, SSHException):
            return b""

    def shutdown_write(self) -> None:
        try:
            send_eof(self._chan)  # never after our CLOSE: sshd would drop the connection
        except (OSError, EOFError, SSHException):
            pass

    def exit_status(self, timeout: float | None = None) -> int | None:
        """The command's exit status; -1 when it ended without one (killed by a signal)."""
        if not self._chan.status_event.wait(timeout):
            return None
        if self._link_died():
            raise self._lost("before the command exited")
        return int(self._chan.exit_status)

    def close(self) -> None:
        try:
            self._chan.close()
        except (OSError, EOFError, SSHException):
            pass

    def _link_died(self) -> bool:
        # Channels of a dead transport are closed without an exit status, which
        # would otherwise look like a command that ended normally.
        return not self._transport.is_active() and self._chan.exit_status == -1

    def _lost(self, when: str) -> LinkLostError:
        why = self._transport.get_exception()
        detail = f": {why}" if why else ""
        return LinkLostError(f"the link to {self._name} was lost {when}{detail}")

    def __repr__(self) -> str:
        return f"SSHChannel({self._name!r}, chan={self._chan.get_id()})"


class SSHTransport:
    """A connection to one robot over SSH (a :class:`fetchsync.link.transport.Transport`)."""

    capabilities = Capabilities(keepalive=True)

    def __init__(
        self,
        transport: paramiko.Transport,
        *,
        settings: HostSettings,
        hops: Sequence[paramiko.Transport] = (),
        keepalive: float = 5.0,
        timeout: float = 10.0,
    ) -> None:
        """Wrap an authenticated paramiko transport; use :meth:`connect` to make one."""
        self.name = settings.alias
        self.settings = settings
        self._transport = transport
        self._hops = list(hops)
        self._keepalive = keepalive
        self._timeout = timeout
        self._probe_lock = threading.Lock()
        self._sessions = SessionSlots(transport)  # within the robot's MaxSessions
        self.on_close: Callable[[], None] | None = None
        """Called once when this connection is closed, just before it goes (say, to leave
        a master behind)."""

    @classmethod
    def connect(
        cls,
        host: str,
        *,
        user: str | None = None,
        port: int | None = None,
        config_path: str | os.PathLike[str] | None = None,
        connect_timeout: float = 10.0,
        keepalive: float = 5.0,
        accept_fingerprint: str | None = None,
        password_callback: PasswordCallback | None = None,
        confirm_callback: PasswordCallback | None = None,
        progress: Callable[[], None] | None = None,
        early: early_route.EarlyLink | None = None,
    ) -> SSHTransport:
        """Connect and authenticate to ``host`` (an ssh config alias, a name or an address).

        ``accept_fingerprint`` (``SHA256:...``) accepts and records an unknown
        host key with that fingerprint. ``confirm_callback(prompt)`` (a terminal's
        answer, echoed) is asked, as ssh asks, whether to accept an unknown one. ``password_callback(prompt)`` is asked
        for key passphrases and, when keys fail, the login password.
        ``progress()`` is called after each step (the socket, the key exchange, the host
        key, the login): a connection master says so to the calls waiting for it.
        ``user`` and ``port`` win over the config's User and Port (a config
        ProxyCommand's ``%p`` still stands for the config's Port).
        ``early``: the route remembered for ``host``, opened before paramiko was imported
        (fetchsync.link.early); used if the config resolves to it now, else closed.
        """
        identity = early_route.config_identity(early_route.config_file(config_path))
        try:
            config = load_ssh_config(config_path)
            settings = resolve_host(host, config=config, user=user, port=port)
        except BaseException:
            if early is not None:
                early.close()
            raise
        opener = _Opener(
            config=config,
            timeout=connect_timeout,
            keepalive=keepalive,
            accept_fingerprint=accept_fingerprint,
            password_callback=password_callback,
            confirm_callback=confirm_callback,
            progress=progress,
            early=early,
        )
        transport = opener.open(settings)
        if not settings.proxy_jump:
            early_route.remember(
                host,
                _route(settings),
                user=user,
                port=port,
                config_path=config_path,
                identity=identity,
                known=early,
            )
        return cls(
            transport,
            settings=settings,
            hops=opener.hops,
            keepalive=keepalive,
            timeout=connect_timeout,
        )

    @property
    def host_key(self) -> paramiko.PKey:
        return self._transport.get_remote_server_key()

    def verify_host_key(self) -> None:
        """Check the robot's host key against known_hosts as it is now (HostKeyError if it
        is no longer listed, or listed differently): for a connection kept open across
        calls, which a new connection would refuse otherwise."""
        _HostKeyCheck(self.settings).verify(self.host_key)

    @property
    def auth_method(self) -> str | None:
        """How this connection logged in (``publickey``, ``password``), None if unknown."""
        return getattr(self._transport, "auth_method", None)

    def exec(
        self, command: str, *, env: dict[str, str] | None = None, pty: bool = False
    ) -> Channel:
        """Start ``command`` through the login shell on the robot.

        ``env`` is set by prefixing ``export NAME=value;`` to the command, as
        sshd rejects most environment requests (AcceptEnv).
        """
        if env:
            command = env_prefix(env) + command
        try:
            chan = self._sessions.open(timeout=self._timeout)
        except (OSError, EOFError, SSHException) as exc:
            raise self._failure("open a session", exc) from exc
        mark("ssh: session open")
        try:
            if pty:
                size = shutil.get_terminal_size()
                chan.get_pty(
                    term=os.environ.get("TERM", "vt100"), width=size.columns, height=size.lines
                )
                chan.exec_command(command)
            else:
                send_exec(chan, command)  # the caller goes on while the robot forks it
        except (OSError, EOFError, SSHException) as exc:
            chan.close()
            raise self._failure("start a command", exc) from exc
        return SSHChannel(chan, self._transport, name=self.name)

    def is_alive(self, timeout: float | None = None) -> bool:
        """Whether the robot still answers: one keepalive round trip within ``timeout``.

        ``timeout`` defaults to three keepalive intervals (at least 5 s);
        ``0`` only checks that the connection has not been closed. A link that
        does not answer in time is closed, so blocked readers wake up with
        :class:`LinkLostError` and the caller can reconnect.
        """
        if not self._transport.is_active():
            return False
        if timeout == 0:
            return True
        wait = timeout if timeout is not None else max(3 * self._keepalive, 5.0)
        with self._probe_lock:
            answered = self.ping()
            if answered is not None and answered.wait(wait) and self._transport.is_active():
                return True
        # the caller reports the lost link; a warning here would be a second line on stderr
        log.info("%s did not answer a keepalive in %.1f s; closing the link", self.name, wait)
        self.close()
        return False

    def ping(self) -> threading.Event | None:
        """Send one keepalive and return at once: the event is set when the robot answers
        (however late), never if it does not; None if the connection has ended.

        Unlike :meth:`is_alive` nothing is closed: a caller that can wait (the watch
        agent, while the link is down) keeps the connection, whose held packets are
        delivered when the link comes back.
        """
        if not self._transport.is_active():
            return None
        answered = threading.Event()

        def probe() -> None:
            try:
                # Any reply, even "request failed", proves the link and the peer alive.
                self._transport.global_request(KEEPALIVE_REQUEST, wait=True)
            except Exception as exc:  # noqa: BLE001 - a dead link is the answer we report
                log.debug("keepalive probe of %s failed: %s", self.name, exc)
            else:
                if self._transport.is_active():  # paramiko returns None once it has closed
                    answered.set()

        threading.Thread(target=probe, name="fetchsync-ssh-probe", daemon=True).start()
        return answered

    def close(self) -> None:
        # on_close first: a process started (by on_close) while a ProxyCommand was
        # ending took ~80 ms to start in 4 of 10 pushes here, ~1 ms otherwise
        on_close, self.on_close = self.on_close, None
        try:
            if on_close is not None:
                on_close()
                mark("ssh: on_close done")
        finally:
            self._transport.close()
            for hop in reversed(self._hops):
                hop.close()

    def __repr__(self) -> str:
        return f"SSHTransport({self.settings.user}@{self.settings.display})"

    def _failure(self, what: str, exc: BaseException) -> TransportError:
        if not self._transport.is_active():
            return LinkLostError(f"the link to {self.name} was lost: cannot {what}")
        if isinstance(exc, ChannelException):
            return TransportError(f"{self.name} refused to {what}: {exc.text}")
        return TransportError(f"cannot {what} on {self.name}: {exc}")


def sshd_answers(
    host: str,
    *,
    user: str | None = None,
    port: int | None = None,
    config_path: str | os.PathLike[str] | None = None,
    timeout: float = 2.0,
) -> bool | None:
    """Whether ``host``'s sshd answers a new connection with its banner, reached the way
    :meth:`SSHTransport.connect` reaches it (ProxyCommand included), within ``timeout``.

    No handshake and no login: next to nothing on either end, nothing in the robot's
    auth log but a closed connection. The watch agent's probe of a robot that stopped
    answering on its connection. None when the route goes through jump hosts (only a
    login to them tells).
    """
    settings = resolve_host(host, config=load_ssh_config(config_path), user=user, port=port)
    if settings.proxy_jump:
        return None
    sock: Any = None
    try:
        if settings.proxy_command:
            sock = _ProxyCommand(settings.proxy_command)
        else:
            sock = socket.create_connection((settings.hostname, settings.port), timeout=timeout)
        sock.settimeout(timeout)
        seen = b""
        while len(seen) < 8192:  # RFC 4253 4.2: lines before the banner are allowed
            piece = sock.recv(1024)
            if not piece:
                return False
            seen += piece
            if seen.startswith(b"SSH-") or b"\nSSH-" in seen:
                return True
        return False
    except (OSError, ConnectError, ProxyCommandFailure):
        return False
    finally:
        if sock is not None:
            sock.close()


def env_prefix(env: dict[str, str]) -> str:
    """``export A='1' B='2'; `` for a POSIX login shell."""
    for name in env:
        if not _ENV_NAME.match(name):
            raise ValueError(f"invalid environment variable name {name!r}")
    pairs = " ".join(f"{name}={shlex.quote(value)}" for name, value in env.items())
    return f"export {pairs}; "


def host_key_fingerprint(key: paramiko.PKey) -> str:
    """``SHA256:...`` as OpenSSH prints it (base64 without padding)."""
    return str(key.fingerprint)


class _Opener:
    """Opens one authenticated paramiko transport, jump hosts first."""

    def __init__(
        self,
        *,
        config: paramiko.SSHConfig,
        timeout: float,
        keepalive: float,
        accept_fingerprint: str | None,
        password_callback: PasswordCallback | None,
        confirm_callback: PasswordCallback | None = None,
        progress: Callable[[], None] | None = None,
        early: early_route.EarlyLink | None = None,
    ) -> None:
        self.config = config
        self.early = early  # the route opened before the config was parsed (depth 0 only)
        self.timeout = timeout
        self.keepalive = keepalive
        self.accept_fingerprint = accept_fingerprint
        self.password_callback = password_callback
        self.confirm_callback = confirm_callback
        self.progress = progress or (lambda: None)
        self.hops: list[paramiko.Transport] = []

    def open(self, settings: HostSettings, *, depth: int = 0) -> paramiko.Transport:
        """Connect, check the host key and authenticate; on failure close all opened."""
        try:
            return self._open(settings, depth)
        except BaseException:
            if self.early is not None:
                self.early.close()
                self.early = None
            for hop in reversed(self.hops):
                hop.close()
            self.hops.clear()
            raise

    def _open(self, settings: HostSettings, depth: int) -> paramiko.Transport:
        if depth > _MAX_HOPS:
            raise ConfigError(
                f"more than {_MAX_HOPS} ProxyJump hops to reach {settings.alias}: "
                "does the ssh config send a jump host through itself?"
            )
        host_keys = _HostKeyCheck(
            settings, accept_fingerprint=self.accept_fingerprint, confirm=self.confirm_callback
        )
        sock = self._sock(settings, depth)
        mark("ssh: socket made")
        self.progress()
        try:
            transport = _Transport(sock)
        except Exception:
            sock.close()
            raise
        try:
            self._handshake(transport, settings, sock, host_keys.preferred_key_types())
            mark("ssh: key exchange done")
            self.progress()
            host_keys.verify(transport.get_remote_server_key())
            mark("ssh: host key checked")
            self.progress()
            _Auth(transport, settings, password_callback=self.password_callback).run()
            mark("ssh: authenticated")
            self.progress()
        except BaseException:
            transport.close()
            sock.close()
            raise
        if self.keepalive > 0:
            transport.set_keepalive(self.keepalive)
        return transport

    def _sock(self, settings: HostSettings, depth: int) -> Any:
        early, self.early = self.early, None
        if early is not None and (
            depth or settings.proxy_jump or not early.matches(_route(settings))
        ):
            early.close()
            early = None
        if settings.proxy_jump:
            return self._jump(settings, depth)
        if settings.proxy_command:
            started = early.take_process() if early is not None else None
            return _ProxyCommand(settings.proxy_command, started=started)
        if early is not None:
            try:
                sock = early.take_socket(self.timeout)
            except OSError as exc:
                raise _tcp_error(settings, exc, self.timeout) from exc
            return _tune_tcp(sock, self.keepalive)
        return _tcp_connect(settings, timeout=self.timeout, keepalive=self.keepalive)

    def _jump(self, settings: HostSettings, depth: int) -> paramiko.Channel:
        assert settings.proxy_jump is not None
        chain = [hop.strip() for hop in settings.proxy_jump.split(",") if hop.strip()]
        jump_user, jump_host, jump_port = parse_jump(chain[-1])
        jump = resolve_host(jump_host, config=self.config, user=jump_user, port=jump_port)
        if len(chain) > 1:
            # As ``ssh -J a,b``: the earlier hops lead to the last one, whatever
            # the config says about reaching it.
            jump = _replace(jump, proxy_jump=",".join(chain[:-1]), proxy_command=None)
        hop = self._open(jump, depth + 1)
        self.hops.append(hop)
        try:
            return hop.open_channel(
                "direct-tcpip",
                (settings.hostname, settings.port),
                ("127.0.0.1", 0),
                timeout=self.timeout,
            )
        except ChannelException as exc:
            raise ConnectError(
                f"cannot connect to {settings.display} through jump host {jump.display}: {exc.text}"
            ) from exc
        except (OSError, EOFError, SSHException) as exc:
            raise ConnectError(
                f"cannot connect to {settings.display} through jump host {jump.display}: {exc}"
            ) from exc

    def _handshake(
        self, transport: paramiko.Transport, settings: HostSettings, sock: Any, preferred: list[str]
    ) -> None:
        transport.banner_timeout = self.timeout
        transport.handshake_timeout = self.timeout
        transport.auth_timeout = self.timeout
        options = transport.get_security_options()
        # AES-GCM first (paramiko lists it last): one pass of AES-NI and GHASH
        # per packet instead of AES-CTR plus an HMAC computed apart, about a
        # third less CPU per byte on both ends for the same security; it is
        # what OpenSSH prefers after chacha20, which paramiko lacks
        gcm = [c for c in options.ciphers if c.endswith("-gcm@openssh.com")]
        options.ciphers = gcm + [c for c in options.ciphers if c not in gcm]
        if preferred:
            # Ask for the key type known_hosts has, as ssh does, so that a server
            # with several host keys is not taken for one whose key changed.
            known = [k for k in preferred if k in options.key_types]
            options.key_types = known + [k for k in options.key_types if k not in known]
        try:
            transport.start_client(timeout=self.timeout)
        except IncompatiblePeer as exc:
            raise _incompatible(transport, settings, exc) from exc
        except ProxyCommandFailure as exc:
            raise ConnectError(_proxy_message(settings, sock, str(exc))) from exc
        except (SSHException, EOFError, OSError) as exc:
            if isinstance(sock, _ProxyCommand):
                raise ConnectError(_proxy_message(settings, sock, str(exc))) from exc
            if "banner" in str(exc) and isinstance(exc.__context__, TimeoutError):
                raise ConnectError(
                    f"timed out after {self.timeout:g} s waiting for the SSH banner of "
                    f"{settings.display}"
                ) from exc
            if "banner" in str(exc):
                raise ConnectError(
                    f"{settings.display} closed the connection before the SSH handshake "
                    "(is it an SSH server, and does it allow this address?)"
                ) from exc
            raise ConnectError(f"SSH handshake with {settings.display} failed: {exc}") from exc
        if not transport.is_active() or not transport.initial_kex_done:
            raise ConnectError(
                f"timed out after {self.timeout:g} s in the SSH handshake with {settings.display}"
            )


class _Transport(paramiko.Transport):  # type: ignore[misc]  # paramiko ships no types
    """paramiko's Transport, keeping what the peer offered in its KEXINIT for error messages."""

    peer_offer: dict[str, list[str]] | None = None
    auth_method: str | None = None
    """How we logged in: ``publickey``, ``password`` or ``none``."""

    def __init__(self, sock: Any, **kwargs: Any) -> None:
        # channel data in one copy (channels.Packetizer)
        super().__init__(sock, packetizer_class=Packetizer, **kwargs)

    def auth_publickey(self, username: str, key: paramiko.PKey, event: Any = None) -> Any:
        """paramiko's, with the signed request sent behind the service request (see
        _PipelinedAuth)."""
        if not self.active or not self.initial_kex_done:
            raise SSHException("No existing session")
        done = event if event is not None else threading.Event()
        self.auth_handler = _PipelinedAuth(self)
        self.auth_handler.auth_publickey(username, key, done)
        if event is not None:
            return []
        return self.auth_handler.wait_for_response(done)

    def _really_parse_kex_init(self, m: Any, ignore_first_byte: bool = False) -> Any:
        parsed = super()._really_parse_kex_init(m, ignore_first_byte)
        if not ignore_first_byte:  # the peer's message; True re-reads our own
            self.peer_offer = parsed
        return parsed


class _PipelinedAuth(AuthHandler):  # type: ignore[misc]  # paramiko ships no types
    """A publickey login in one round trip, not two.

    paramiko asks for the ``ssh-userauth`` service and sends the signed login request
    only once the robot accepted it: a round trip of waiting for an answer that is
    always yes (8 ms on the bench's wifi, 50 ms on weak). The request goes right behind
    the service request instead, built and signed the same way (paramiko's own code
    does it, handed the acceptance it would have waited for): the robot's sshd reads
    them in order, so the login is read once the service is accepted, as before; the
    acceptance, when it comes, is then only noted. Not for RSA keys, whose signature
    algorithm (rsa-sha2-256/512) depends on the robot's server-sig-algs, which come in
    its EXT_INFO and may not have been read yet: they wait for the acceptance as
    before. Nothing else changes: the same key, the same signature, the same checks.
    Measured (bench/firststart.py --link wifi --rclcpp --rounds 6 against the commit
    before, interleaved, load 3.4-4.9): the key exchange to authenticated 22-23 ms
    against 31-35 in the quieter rounds (one round trip: 8 ms).
    """

    _sent_early = False

    def _request_auth(self) -> None:
        key = getattr(self, "private_key", None)
        # decided before the service request goes: its acceptance may be read (on the
        # transport's thread) while the request below is still being signed
        self._sent_early = (
            self.auth_method == "publickey" and key is not None and "rsa" not in key.get_name()
        )
        super()._request_auth()  # the service request
        if self._sent_early:
            accepted = Message()
            accepted.add_string("ssh-userauth")
            accepted.rewind()
            super()._parse_service_accept(accepted)  # builds, signs and sends the request
            mark("ssh: login sent behind the service request")

    def _parse_service_accept(self, m: Any) -> None:
        if not self._sent_early:
            super()._parse_service_accept(m)


# what paramiko names in "no acceptable X" -> (the peer's list, our list, the sshd_config keyword)
_ALGORITHM_KINDS = {
    "kex algorithm": ("kex_algo_list", "preferred_kex", "KexAlgorithms"),
    "host key": ("server_key_algo_list", "preferred_keys", "HostKeyAlgorithms"),
    "client encrypt algorithm": ("server_encrypt_algo_list", "preferred_ciphers", "Ciphers"),
    "server encrypt algorithm": ("server_encrypt_algo_list", "preferred_ciphers", "Ciphers"),
    "client mac algorithm": ("server_mac_algo_list", "preferred_macs", "MACs"),
    "server mac algorithm": ("server_mac_algo_list", "preferred_macs", "MACs"),
    "compression algorithm": ("server_compress_algo_list", "preferred_compression", "Compression"),
}


def _incompatible(
    transport: paramiko.Transport, settings: HostSettings, exc: IncompatiblePeer
) -> ConnectError:
    """No algorithm both ends know: name both lists and the sshd_config keyword that would fix it."""
    found = re.search(r"no acceptable (.*?)\)", str(exc))
    what = found.group(1) if found else str(exc)
    kind = _ALGORITHM_KINDS.get(what)
    offer = getattr(transport, "peer_offer", None)
    if kind is None or not offer:
        return ConnectError(f"cannot agree on algorithms with {settings.display}: {what}")
    theirs_key, ours_attr, keyword = kind
    theirs = [
        a for a in offer.get(theirs_key, []) if not a.startswith(("ext-info-", "kex-strict-"))
    ]
    ours = list(getattr(transport, ours_attr, ()))
    if keyword == "HostKeyAlgorithms":
        hint = "give the robot's sshd a host key of one of our types (HostKey in its sshd_config)"
    else:
        hint = f"add one of ours to {keyword} in the robot's sshd_config"
    return ConnectError(
        f"cannot agree on algorithms with {settings.display}: no acceptable {what}: "
        f"it offers {', '.join(theirs) or 'none'}; fetchsync (paramiko {paramiko.__version__}) "
        f"knows {', '.join(ours)}",
        hint=hint,
    )


def _route(settings: HostSettings) -> early_route.Route:
    """Where a direct connection's socket goes (what fetchsync.link.early remembers)."""
    return (settings.hostname, settings.port, settings.proxy_command)


def _tcp_connect(settings: HostSettings, *, timeout: float, keepalive: float) -> socket.socket:
    try:
        sock = socket.create_connection((settings.hostname, settings.port), timeout=timeout)
    except OSError as exc:
        raise _tcp_error(settings, exc, timeout) from exc
    return _tune_tcp(sock, keepalive)


def _tcp_error(settings: HostSettings, exc: OSError, timeout: float) -> ConnectError:
    where = f"{settings.hostname} port {settings.port}"
    if isinstance(exc, socket.gaierror):
        alias = f" (for {settings.alias})" if settings.alias != settings.hostname else ""
        # fetchsync CLI hint (habits-b): robots are usually NAME.local or an ssh config Host
        zeroconf = (
            "check that the robot is on this network and avahi-daemon (zeroconf) runs here"
            if settings.hostname.endswith(".local")
            else "check the name"
            if "." in settings.hostname
            else f"on its network it may be {settings.hostname}.local (zeroconf)"
        )
        return ConnectError(
            f"cannot resolve host name {settings.hostname!r}{alias}: {exc.strerror}",
            hint=f"{zeroconf}; or give it a 'Host {settings.alias}' entry with its "
            "HostName in ~/.ssh/config",
        )
    if isinstance(exc, ConnectionRefusedError):
        return ConnectError(f"connection refused by {where} ({settings.alias})")
    if isinstance(exc, TimeoutError):  # socket.timeout is TimeoutError since Python 3.10
        return ConnectError(f"timed out after {timeout:g} s connecting to {where}")
    return ConnectError(f"cannot connect to {where}: {exc.strerror or exc}")


def _tune_tcp(sock: socket.socket, keepalive: float) -> socket.socket:
    # Small request/response frames: never wait for Nagle.
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    if keepalive > 0 and hasattr(socket, "TCP_USER_TIMEOUT"):
        # Keepalives keep data in flight on an idle link; when it goes unacked
        # this long the kernel drops the connection and readers see a lost link.
        ms = int(max(3 * keepalive, 15.0) * 1000)
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT, ms)
        except OSError:
            pass
    return sock


class _ProxyCommand(paramiko.ProxyCommand):  # type: ignore[misc]  # paramiko ships no types
    """paramiko's ProxyCommand, run by ``/bin/sh`` as ssh does, with EOF and stderr kept.

    paramiko splits the command itself (no pipes or redirections) and never
    reports EOF, spinning when the command dies; this reports EOF, so the
    transport ends, and keeps the command's stderr for the error message.
    """

    def __init__(
        self,
        command_line: str,
        *,
        started: tuple[subprocess.Popen[bytes], IO[bytes]] | None = None,
    ) -> None:
        """Run ``command_line``, or take it ``started`` already (its process and the file
        of its stderr: fetchsync.link.early, the same command started the same way)."""
        # not the parent's __init__: the command runs with the shell, as OpenSSH runs it
        self._command_line = command_line
        if started is not None:
            self.process, self._stderr = started
        else:
            self._stderr = tempfile.TemporaryFile()  # noqa: SIM115 - close() closes it
            try:
                self.process = subprocess.Popen(
                    ["/bin/sh", "-c", "exec " + command_line],
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    stderr=self._stderr,
                    bufsize=0,
                    start_new_session=True,
                    env=inheritable(os.environ),  # no password of the call's (fetchsync.environ)
                )
            except OSError as exc:
                self._stderr.close()
                raise ConnectError(
                    f"cannot run ProxyCommand {command_line!r}: {exc.strerror}"
                ) from exc
        for pipe in (self.process.stdin, self.process.stdout):
            if pipe is not None:
                widen_pipe(pipe.fileno())
        self.timeout: float | None = None
        self._closed_here = False
        self._reaping = False
        # paramiko's transport thread closes its socket when the stream ends, and the
        # caller's thread closes it too: one closing a stream while the other flushed
        # it raised "I/O operation on closed file" out of a push that had succeeded
        self._closing = threading.Lock()

    def send(self, content: bytes) -> int:
        assert self.process.stdin is not None
        try:
            written = self.process.stdin.write(content)
        except OSError as exc:
            raise ProxyCommandFailure(self._command_line, exc.strerror) from exc
        return len(content) if written is None else int(written)

    def recv(self, size: int) -> bytes:
        assert self.process.stdout is not None
        try:
            ready, _, _ = select.select([self.process.stdout], [], [], self.timeout)
            if not ready:
                raise socket.timeout()
            return os.read(self.process.stdout.fileno(), size)
        except socket.timeout:
            raise
        except ValueError:
            return b""  # closed under us: end of stream
        except OSError as exc:
            if exc.errno == errno.EBADF:
                return b""
            raise ProxyCommandFailure(self._command_line, exc.strerror) from exc

    def stderr_text(self) -> str:
        try:
            self._stderr.seek(0)
            return self._stderr.read(4096).decode("utf-8", "replace").strip()
        except (OSError, ValueError):
            return ""

    def close(self) -> None:
        """End the command: its input ends and it gets SIGTERM, as ssh sends it SIGHUP
        and goes on. It is reaped by a thread of its own, which kills it if it is still
        there a second later: waiting here made every call that connected through one
        wait for it to exit (~15 ms for the benchmark's, a Python script)."""
        with self._closing:
            self._closed_here = True
            for stream in (self.process.stdin, self.process.stdout, self._stderr):
                if stream is not None:
                    with contextlib.suppress(OSError, ValueError):
                        stream.close()
            if self.process.poll() is None and not self._reaping:
                self._reaping = True
                with contextlib.suppress(OSError):
                    self.process.terminate()
                threading.Thread(
                    target=self._reap, name="fetchsync-proxy-reaper", daemon=True
                ).start()

    def _reap(self) -> None:
        try:
            self.process.wait(1.0)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()

    @property
    def closed(self) -> bool:
        return self._closed_here or self.process.poll() is not None


def _proxy_message(settings: HostSettings, sock: Any, error: str) -> str:
    stderr = sock.stderr_text() if isinstance(sock, _ProxyCommand) else ""
    last = stderr.splitlines()[-1] if stderr else error
    return (
        f"cannot reach {settings.display} through ProxyCommand {settings.proxy_command!r}: {last}"
    )


@dataclass(frozen=True)
class _KnownKey:
    key: paramiko.PKey
    file: str
    line: int
    marker: str | None


# held from finding a host key unknown to accepting or refusing it: a fleet's robots that
# share a host (aliases of one robot) ask about its key once, the others find it recorded
_UNKNOWN_KEYS = threading.Lock()


class _HostKeyCheck:
    """The known_hosts files of one host and the verdict on the key it offers."""

    def __init__(
        self,
        settings: HostSettings,
        *,
        accept_fingerprint: str | None = None,
        confirm: PasswordCallback | None = None,
    ) -> None:
        self.settings = settings
        self.accept_fingerprint = accept_fingerprint
        self.confirm = confirm
        self.name = settings.known_hosts_name
        self._known: list[_KnownKey] | None = None

    def known(self) -> list[_KnownKey]:
        if self._known is None:
            files = self.settings.known_hosts_files + self.settings.global_known_hosts_files
            self._known = [k for path in files for k in _read_known_hosts(path, self.name)]
        return self._known

    def preferred_key_types(self) -> list[str]:
        types: list[str] = []
        for entry in self.known():
            if entry.marker is not None:
                continue
            name = entry.key.get_name()
            names = ["rsa-sha2-512", "rsa-sha2-256"] if name == "ssh-rsa" else [name]
            types.extend(n for n in names if n not in types)
        return types

    def verify(self, key: paramiko.PKey) -> None:
        fingerprint = host_key_fingerprint(key)
        offered = f"{_key_label(key)} key {fingerprint}"
        entries = self.known()
        blob = key.asbytes()
        for entry in entries:
            if entry.marker == "@revoked" and entry.key.asbytes() == blob:
                raise HostKeyError(
                    f"the host key of {self.settings.display} ({offered}) is marked revoked "
                    f"in {_tilde(entry.file)}:{entry.line}; refusing to connect"
                )
        plain = [e for e in entries if e.marker is None]
        if any(e.key.asbytes() == blob for e in plain):
            return
        if plain:
            old = plain[0]
            raise HostKeyError(
                f"REMOTE HOST IDENTIFICATION HAS CHANGED for {self.settings.display}: it offers "
                f"{offered}, but {_tilde(old.file)}:{old.line} lists a different "
                f"{_key_label(old.key)} key; refusing to connect",
                hint=(
                    "if the robot was reinstalled, remove the old key with "
                    f"ssh-keygen -R {shlex.quote(self.name)} -f {shell_path(old.file)}"
                    " and check the new fingerprint"
                ),
            )
        with _UNKNOWN_KEYS:
            # another robot of this process (a fleet's) may have accepted this host's key
            # meanwhile: look again, so that its question is asked once
            self._known = None
            if any(e.marker is None and e.key.asbytes() == blob for e in self.known()):
                return
            wanted = (self.accept_fingerprint or "").strip()
            if wanted and wanted.removeprefix("SHA256:") == fingerprint.removeprefix("SHA256:"):
                self._record(key)
                return
            s = self.settings
            if not wanted and self.confirm is not None and self._confirmed(key, fingerprint):
                self._record(key)
                return
            port = f"-p {s.port} " if s.port != SSH_PORT else ""
            login = shlex.quote(f"{s.user}@{s.alias}")
            how = (
                f"ssh {port}{login} once to accept it, or re-run with --accept-host-key "
                f"{shlex.quote(fingerprint)}"
            )
            if wanted:
                raise HostKeyError(
                    f"the host key of {s.display} is {offered}, not the {wanted} given to accept; "
                    "refusing to connect"
                )
            raise HostKeyError(
                f"the host key of {s.display} is not known: it offers {offered}", hint=how
            )

    def _confirmed(self, key: paramiko.PKey, fingerprint: str) -> bool:
        """Ask on the terminal, as ssh does, whether to accept an unknown host key; a
        "no" is a HostKeyError, no answer (EOF) leaves the usual refusal."""
        assert self.confirm is not None
        prompt = (
            f"The authenticity of host '{self.settings.display}' can't be established.\n"
            f"{_key_label(key)} key fingerprint is {fingerprint}.\n"
            "Are you sure you want to continue connecting (yes/no/[fingerprint])? "
        )
        while True:
            answer = self.confirm(prompt)
            if answer is None:
                return False
            answer = answer.strip()
            if answer.lower() == "yes" or (
                answer.startswith("SHA256:")
                and answer.removeprefix("SHA256:") == fingerprint.removeprefix("SHA256:")
            ):
                return True
            if answer.lower() == "no":
                raise HostKeyError(
                    f"host key verification failed: the host key of "
                    f"{self.settings.display} ({fingerprint}) was not accepted"
                )
            prompt = "Please type 'yes', 'no' or the fingerprint: "

    def _record(self, key: paramiko.PKey) -> None:
        if not self.settings.known_hosts_files:
            return
        path = Path(self.settings.known_hosts_files[0])
        name = self.name
        if self.settings.hash_known_hosts:
            name = paramiko.HostKeys.hash_host(name)
        line = f"{name} {key.get_name()} {key.get_base64()}\n"
        try:
            path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
            with os.fdopen(fd, "ab") as out:
                if out.tell() > 0 and not _ends_with_newline(path):
                    line = "\n" + line
                out.write(line.encode("ascii"))
        except OSError as exc:
            raise ConnectError(f"cannot record the host key in {path}: {exc.strerror}") from exc
        log.info(
            "recorded the host key of %s (%s) in %s", self.name, host_key_fingerprint(key), path
        )


def _read_known_hosts(path: str, name: str) -> Iterable[_KnownKey]:
    try:
        with open(path, encoding="utf-8", errors="replace") as lines:
            for number, raw in enumerate(lines, 1):
                fields = raw.split()
                if not fields or fields[0].startswith("#"):
                    continue
                marker = None
                if fields[0].startswith("@"):
                    marker, fields = fields[0], fields[1:]
                if len(fields) < 3 or not _host_matches(name, fields[0]):
                    continue
                key = _parse_key(fields[1], fields[2])
                if key is not None:
                    yield _KnownKey(key=key, file=path, line=number, marker=marker)
    except FileNotFoundError:
        return
    except OSError as exc:
        log.warning("cannot read %s: %s", path, exc.strerror)


def _parse_key(key_type: str, data: str) -> paramiko.PKey | None:
    import base64
    import binascii

    try:
        return paramiko.PKey.from_type_string(key_type, base64.b64decode(data))
    except (binascii.Error, ValueError, SSHException, UnknownKeyType):
        return None


def _host_matches(name: str, patterns: str) -> bool:
    """OpenSSH's known_hosts matching: hashed names, ``*``/``?`` patterns, ``!`` negation."""
    if patterns.startswith("|1|"):
        try:
            return hmac.compare_digest(paramiko.HostKeys.hash_host(name, patterns), patterns)
        except Exception:  # noqa: BLE001 - a malformed hashed entry matches nothing
            return False
    matched = False
    for pattern in patterns.lower().split(","):
        negated = pattern.startswith("!")
        if negated:
            pattern = pattern[1:]
        if _glob(pattern).match(name):
            if negated:
                return False
            matched = True
    return matched


def _glob(pattern: str) -> re.Pattern[str]:
    # Only * and ? are special: "[127.0.0.1]:2222" is a literal, not a class.
    parts = (".*" if c == "*" else "." if c == "?" else re.escape(c) for c in pattern)
    return re.compile("".join(parts) + r"\Z")


class _Auth:
    """Authenticate as ssh does: agent, identity files, default keys, then password."""

    def __init__(
        self,
        transport: paramiko.Transport,
        settings: HostSettings,
        *,
        password_callback: PasswordCallback | None,
    ) -> None:
        self.t = transport
        self.s = settings
        self.password_callback = password_callback
        self.tried: list[str] = []
        self.allowed: set[str] | None = None  # methods the server still accepts, once known
        self.offered: set[bytes] = set()
        self.wrong_passwords = 0

    def run(self) -> None:
        try:
            if self._agent() or self._files() or self._password():
                return
            if self.allowed is None:
                self._ask_methods()
        except (SSHException, EOFError, OSError) as exc:
            raise ConnectError(
                f"the connection to {self.s.display} failed while authenticating: {exc}"
            ) from exc
        if self.t.is_authenticated():  # the robot lets this user in without credentials
            self._succeeded("none")
            return
        raise self._denied()

    def _denied(self) -> ConnectError:
        who = f"{self.s.user}@{self.s.display}"
        copy_id = f"ssh-copy-id {shlex.quote(f'{self.s.user}@{self.s.alias}')}"
        tried = ", ".join(self.tried) or "nothing: no agent, no key files, no password prompt"
        # a robot refuses an account it does not have just the same (fetchsync CLI hint, habits-b)
        account = (
            f"; if {self.s.user} has no account there yet, fetchsync create-account "
            f"--robot {shlex.quote(self.s.alias)} --user {shlex.quote(self.s.user)} makes one"
        )
        if self.wrong_passwords:
            tries = "try" if self.wrong_passwords == 1 else "tries"
            return ConnectError(
                f"permission denied for {who}: wrong password ({self.wrong_passwords} {tries}; "
                f"tried: {tried})",
                hint=f"check the password, or install your public key once with {copy_id}{account}",
            )
        wants_password = self.allowed is not None and bool(
            self.allowed & {"password", "keyboard-interactive"}
        )
        if wants_password and self.password_callback is None:
            return ConnectError(
                f"permission denied for {who} (tried: {tried}): the robot asks for a password "
                "and there is no terminal to ask it on",
                hint=f"run fetchsync in a terminal, or install your public key once with {copy_id}{account}",
            )
        return ConnectError(
            f"permission denied for {who} (tried: {tried})",
            hint=f"{copy_id} installs your public key on the robot{account}",
        )

    def _ask_methods(self) -> None:
        """Learn the methods the robot accepts, as ssh does first: a "none" request."""
        try:
            self.t.auth_none(self.s.user)
        except BadAuthenticationType as exc:
            self.allowed = set(exc.allowed_types)
        except AuthenticationException:
            pass

    def _succeeded(self, method: str) -> None:
        if isinstance(self.t, _Transport):
            self.t.auth_method = method

    def _agent(self) -> bool:
        if not os.environ.get("SSH_AUTH_SOCK"):
            return False
        try:
            agent = paramiko.Agent()
        except SSHException as exc:
            log.debug("ssh-agent unusable: %s", exc)
            return False
        try:
            keys = list(agent.get_keys())
            if self.s.identities_only:
                # As ssh: only the agent's copies of the configured identities.
                wanted = self._identity_blobs()
                keys = [k for k in keys if k.asbytes() in wanted]
            if not keys:
                return False
            self.tried.append(f"agent ({len(keys)} key{'s' if len(keys) != 1 else ''})")
            return any(self._offer(key) for key in keys)
        finally:
            agent.close()

    def _files(self) -> bool:
        # As ssh: the default keys only when the config names no IdentityFile.
        files = list(self.s.identity_files) or [
            os.path.expanduser(f"~/.ssh/{name}") for name in DEFAULT_IDENTITIES
        ]
        for path in files:
            if self._publickey_refused():
                return False
            if not os.path.exists(path):
                continue
            key = self._load(path)
            if key is not None and key.asbytes() not in self.offered:
                self.tried.append(_tilde(path))
                if self._offer(key):
                    return True
        return False

    def _password(self) -> bool:
        if self.password_callback is None:
            return False
        if self.allowed is None:
            self._ask_methods()  # no prompt for a robot that takes keys only
        if self.allowed is not None and not self.allowed & {"password", "keyboard-interactive"}:
            return False
        prompt = f"{self.s.user}@{self.s.alias}'s password: "
        self.tried.append("password")
        for attempt in range(_PASSWORD_TRIES):
            again = "Permission denied, please try again.\n" if attempt else ""
            password = self.password_callback(again + prompt)
            if not password:
                return False
            try:
                # fallback: keyboard-interactive answered with the same password.
                remaining = self.t.auth_password(self.s.user, password)
            except BadAuthenticationType as exc:
                self.allowed = set(exc.allowed_types)
                return False
            except AuthenticationException:
                self.wrong_passwords += 1
                continue
            if self.t.is_authenticated():
                self._succeeded("password")
                return True
            self.allowed = set(remaining)
            return False
        return False

    def _offer(self, key: paramiko.PKey) -> bool:
        self.offered.add(key.asbytes())
        if self._publickey_refused():
            return False
        try:
            remaining = self.t.auth_publickey(self.s.user, key)
        except BadAuthenticationType as exc:
            self.allowed = set(exc.allowed_types)
            return False
        except AuthenticationException:
            return False
        if self.t.is_authenticated():
            self._succeeded("publickey")
            return True
        self.allowed = set(remaining)  # partial success: another method must follow
        return False

    def _publickey_refused(self) -> bool:
        return self.allowed is not None and "publickey" not in self.allowed

    def _load(self, path: str) -> paramiko.PKey | None:
        try:
            return paramiko.PKey.from_path(path)
        except TypeError:
            pass  # encrypted: paramiko asks for the passphrase this way
        except (OSError, ValueError, SSHException, UnknownKeyType) as exc:
            log.debug("cannot load key %s: %s", path, exc)
            return None
        if self.password_callback is None:
            self.tried.append(f"{_tilde(path)} (has a passphrase; skipped)")
            return None
        passphrase = self.password_callback(f"Enter passphrase for key '{path}': ")
        if not passphrase:
            return None
        try:
            return paramiko.PKey.from_path(path, password=passphrase.encode("utf-8"))
        except (TypeError, ValueError, SSHException, UnknownKeyType):
            self.tried.append(f"{_tilde(path)} (wrong passphrase)")
            return None

    def _identity_blobs(self) -> set[bytes]:
        blobs: set[bytes] = set()
        for path in self.s.identity_files:
            try:
                blobs.add(paramiko.PublicBlob.from_file(path + ".pub").key_blob)
            except (OSError, ValueError):
                continue
        return blobs


def parse_jump(spec: str) -> tuple[str | None, str, int | None]:
    """``[user@]host[:port]`` or ``ssh://[user@]host[:port]`` -> (user, host, port)."""
    text = spec.removeprefix("ssh://").rstrip("/")
    user = None
    if "@" in text:
        user, text = text.rsplit("@", 1)
    port = None
    if text.startswith("["):
        host, _, rest = text[1:].partition("]")
        if rest.startswith(":"):
            port = rest[1:]
    elif text.count(":") == 1:
        host, port = text.split(":")
    else:
        host = text
    try:
        port_number = int(port) if port else None
    except ValueError as exc:
        raise ConfigError(f"invalid ProxyJump {spec!r}: bad port {port!r}") from exc
    if not host:
        raise ConfigError(f"invalid ProxyJump {spec!r}: no host")
    return user or None, host, port_number


def _replace(settings: HostSettings, **changes: Any) -> HostSettings:
    import dataclasses

    return dataclasses.replace(settings, **changes)


def _split_files(value: Any, *, default: tuple[str, ...]) -> tuple[str, ...]:
    if not value:
        return default
    if isinstance(value, list):
        value = " ".join(value)
    return tuple(shlex.split(str(value)))


def _expand_tokens(path: str, tokens: dict[str, str]) -> str:
    for token, value in tokens.items():
        path = path.replace(token, value)
    return os.path.expanduser(path)


def _yes(value: Any) -> bool:
    return str(value).lower() in ("yes", "true")


def _local_user() -> str:
    import getpass

    return getpass.getuser()


def _host_port(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _key_label(key: paramiko.PKey) -> str:
    name: str = key.get_name()
    if name.startswith("ecdsa-"):
        return "ECDSA"
    return name.removeprefix("ssh-").split("-")[0].upper()


def _tilde(path: str) -> str:
    home = os.path.expanduser("~")
    if home not in ("", "/") and (path == home or path.startswith(home + os.sep)):
        return "~" + path[len(home) :]
    return path


def shell_path(path: str) -> str:
    """``path`` as a user can paste it into a shell: ``~/`` kept unquoted (so the shell
    expands it) and the rest quoted with shlex, so no character of it is run."""
    short = _tilde(path)
    if short == "~":
        return short
    if short.startswith("~/"):
        return "~/" + shlex.quote(short[2:])
    return shlex.quote(path)


def _ends_with_newline(path: Path) -> bool:
    with open(path, "rb") as f:
        f.seek(-1, os.SEEK_END)
        return f.read(1) == b"\n"


__all__ = [
    "HostSettings",
    "PasswordCallback",
    "SSHChannel",
    "SSHTransport",
    "env_prefix",
    "host_key_fingerprint",
    "load_ssh_config",
    "parse_jump",
    "resolve_host",
]
