"""``fetchsync watch --install-service``: a systemd user unit that keeps the agent running.

One unit per (robot, remote workspace), as one agent runs per that pair:
``~/.config/systemd/user/fetchsync-watch-<robot>-<workspace>-<hash>.service``.
Its ``ExecStart`` is this very ``fetchsync watch`` with every target option
resolved (the service does not see the shell's ``FETCHSYNC_*`` variables),
``Restart=on-failure``, and the SSH agent socket of the installing shell.
The agent's events go to the journal: ``journalctl --user -u UNIT -f``.
Nothing here runs systemctl: the commands to run are printed.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path

from fetchsync.config import Target


def unit_dir() -> Path:
    base = os.environ.get("XDG_CONFIG_HOME") or os.path.join(os.path.expanduser("~"), ".config")
    return Path(base) / "systemd" / "user"


def unit_name(target: Target) -> str:
    """``fetchsync-watch-<robot>-<workspace>-<hash>.service``, in systemd's unit name alphabet."""
    from fetchsync.link.session import robot_id

    key = hashlib.sha256(
        f"{robot_id(target)}\0{target.remote_workspace}\0{target.workspace}".encode(
            "utf-8", "surrogateescape"
        )
    ).hexdigest()[:8]

    def slug(text: str) -> str:
        return re.sub(r"[^A-Za-z0-9_.]+", "_", text).strip("_.")[:40] or "x"

    return f"fetchsync-watch-{slug(target.robot)}-{slug(target.workspace.name)}-{key}.service"


def fetchsync_argv() -> list[str]:
    """How to run this fetchsync by absolute path: its script, or ``python -m fetchsync``."""
    prog = sys.argv[0] if sys.argv else ""
    if prog and os.path.basename(prog) == "fetchsync" and os.path.isfile(prog):
        return [os.path.abspath(prog)]
    found = shutil.which("fetchsync")
    if found and "/shims/" not in found:  # a pyenv shim needs the shell's pyenv set-up
        return [os.path.abspath(found)]
    # -P (3.11+): the unit runs in the workspace, which -m would put first on the path (a
    # json.py lying there would be imported: tests/test_unit_import_path.py)
    safe = ["-P"] if sys.version_info >= (3, 11) else []
    return [os.path.abspath(sys.executable), *safe, "-m", "fetchsync"]


def exec_quote(arg: str) -> str:
    """``arg`` as one word of a systemd ``ExecStart=`` line (specifiers and variables kept literal)."""
    escaped = arg.replace("%", "%%").replace("$", "$$")
    if escaped and re.fullmatch(r"[A-Za-z0-9_@%+=:,./-]+", escaped):
        return escaped
    return '"' + escaped.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'


def _env_value(value: str) -> str:
    return value.replace("%", "%%").replace("\\", "\\\\").replace('"', '\\"')


def unit_text(
    target: Target, watch_args: Sequence[str], *, environ: dict[str, str] | None = None
) -> str:
    """The unit file running ``fetchsync watch`` for ``target`` with ``watch_args`` after the target."""
    env = os.environ if environ is None else environ
    argv = [*fetchsync_argv(), "watch", "--robot", target.robot]
    if target.user:
        argv += ["--user", target.user]
    argv += ["--workspace", str(target.workspace), "--remote-workspace", target.remote_workspace]
    argv += list(watch_args)
    lines = [
        "# Written by fetchsync watch --install-service; remove with --uninstall-service.",
        "[Unit]",
        f"Description=fetchsync watch: {target.workspace}/src -> {target.robot}:"
        f"{target.remote_workspace}/src".replace("%", "%%"),
        "StartLimitIntervalSec=300",
        "StartLimitBurst=10",
        "",
        "[Service]",
        "Type=simple",
        f"WorkingDirectory={exec_quote(str(target.workspace))}",
        "ExecStart=" + " ".join(exec_quote(a) for a in argv),
        "Restart=on-failure",
        "RestartSec=5",
        "Environment=PYTHONUNBUFFERED=1",
    ]
    for name in ("FETCHSYNC_LOCAL_ROBOT_HOME", "XDG_STATE_HOME"):
        if env.get(name):
            lines.append(f'Environment="{name}={_env_value(env[name])}"')
    sock = env.get("SSH_AUTH_SOCK")
    runtime = env.get("XDG_RUNTIME_DIR")
    if sock:
        if runtime and sock.startswith(runtime.rstrip("/") + "/"):
            # a socket in the runtime directory keeps its path across logins: %t is that directory
            value = "%t/" + _env_value(sock[len(runtime.rstrip("/")) + 1 :])
        else:
            value = _env_value(sock)
        lines.append(f'Environment="SSH_AUTH_SOCK={value}"')
    lines += ["", "[Install]", "WantedBy=default.target", ""]
    return "\n".join(lines)


def install(target: Target, watch_args: Sequence[str]) -> tuple[Path, list[str]]:
    """Write the unit; its path and what to tell the user."""
    name = unit_name(target)
    path = unit_dir() / name
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(unit_text(target, watch_args), encoding="utf-8")
    os.replace(tmp, path)
    notes = [
        f"wrote {path}",
        "start it now and at each login with:",
        f"  systemctl --user daemon-reload && systemctl --user enable --now {name}",
        f"its output: journalctl --user -u {name} -f",
        'to keep it running while logged out: loginctl enable-linger "$USER"',
    ]
    sock = os.environ.get("SSH_AUTH_SOCK", "")
    runtime = os.environ.get("XDG_RUNTIME_DIR", "")
    if sock and not (runtime and sock.startswith(runtime.rstrip("/") + "/")):
        notes.append(
            f"note: SSH_AUTH_SOCK ({sock}) may change at the next login; then run "
            "--install-service again, or use a key without a passphrase"
        )
    return path, notes


def uninstall(target: Target) -> tuple[Path, list[str]]:
    """Remove the unit (if any); its path and what to tell the user."""
    name = unit_name(target)
    path = unit_dir() / name
    wanted = unit_dir() / "default.target.wants" / name  # what enable made
    if not path.exists() and not wanted.is_symlink():
        return path, [f"no unit {path}"]
    for p in (wanted, path):
        if p.is_symlink() or p.exists():
            p.unlink()
    return path, [
        f"removed {path}",
        f"stop it with: systemctl --user stop {name} && systemctl --user daemon-reload",
    ]
