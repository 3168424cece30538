"""fetchsync watch --install-service / --uninstall-service (the unit file; systemctl never runs),
and an editor's save hook calling fetchsync flush under a live agent (vim, for real)."""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import fetchsync
from test_watch import Watch, local_env, paths, runtime, wait_for  # noqa: F401 (fixtures)

from fetchsync.agent.unit import exec_quote


def unit_files(env: dict) -> list[Path]:
    return sorted((Path(env["XDG_CONFIG_HOME"]) / "systemd/user").glob("fetchsync-watch-*.service"))


def parse(text: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        if "=" in line and not line.startswith(("#", "[")):
            key, value = line.split("=", 1)
            out.setdefault(key, []).append(value)
    return out


@pytest.fixture
def env(local_env, tmp_path):  # noqa: F811
    return dict(
        local_env,
        XDG_CONFIG_HOME=str(tmp_path / "config"),
        SSH_AUTH_SOCK=f"{local_env['XDG_RUNTIME_DIR']}/keyring/ssh",
    )


def test_install_service_writes_a_unit_that_runs_this_watch(env, tmp_path):
    out = fetchsync(
        "watch",
        "--install-service",
        "--build",
        "--build-args=-j4 -DX=50%",
        "--exclude",
        "*.bag",
        env=env,
    ).stdout.decode()
    [unit] = unit_files(env)
    assert unit.name.startswith("fetchsync-watch-local-ws-")
    assert f"systemctl --user enable --now {unit.name}" in out
    assert f"journalctl --user -u {unit.name}" in out
    keys = parse(unit.read_text())
    assert keys["Restart"] == ["on-failure"]
    assert keys["WantedBy"] == ["default.target"]
    # %t is systemd's runtime directory: the agent socket's path survives the next login
    assert 'SSH_AUTH_SOCK=%t/keyring/ssh"' in "\n".join(keys["Environment"])
    # systemd's quoting is close enough to the shell's for these words, once %% is %
    argv = shlex.split(keys["ExecStart"][0].replace("%%", "%"))
    assert os.path.isabs(argv[0]) and os.access(argv[0], os.X_OK)
    i = argv.index("watch")
    assert argv[i:] == [
        "watch",
        "--robot",
        "local",
        "--workspace",
        str(tmp_path / "ws"),
        "--remote-workspace",
        "~/robot_ws",
        "--exclude",
        "*.bag",
        "--build=-j4 -DX=50%",
    ]
    # the unit's command line runs: its --help
    help_out = subprocess.run(
        [*argv[:i], "watch", "--help"], capture_output=True, env=env, check=False
    )
    assert help_out.returncode == 0 and b"--install-service" in help_out.stdout
    analyze = shutil.which("systemd-analyze")
    if analyze:
        check = subprocess.run(
            [analyze, "verify", str(unit)], capture_output=True, text=True, check=False
        )
        assert check.returncode == 0, check.stderr
        assert unit.name not in check.stderr, check.stderr  # no warning about the unit itself
    # installing again rewrites the same unit; another workspace gets its own
    fetchsync("watch", "--install-service", env=env)
    assert unit_files(env) == [unit] and "--build" not in unit.read_text()
    other = tmp_path / "other_ws"
    (other / "src").mkdir(parents=True)
    fetchsync("watch", "--install-service", "--workspace", str(other), env=env)
    assert len(unit_files(env)) == 2


def test_uninstall_service_removes_the_unit_and_its_enablement(env):
    fetchsync("watch", "--install-service", env=env)
    [unit] = unit_files(env)
    wants = unit.parent / "default.target.wants"
    wants.mkdir()
    (wants / unit.name).symlink_to(unit)  # what systemctl --user enable makes
    out = fetchsync("watch", "--uninstall-service", env=env).stdout.decode()
    assert f"systemctl --user stop {unit.name}" in out
    assert not unit.exists() and not (wants / unit.name).is_symlink()
    again = fetchsync("watch", "--uninstall-service", env=env).stdout.decode()
    assert again.startswith("no unit")


def test_exec_quote_keeps_specifiers_and_variables_literal():
    assert exec_quote("/usr/bin/fetchsync") == "/usr/bin/fetchsync"
    assert exec_quote("~/robot ws") == '"~/robot ws"'
    assert exec_quote("50%") == "50%%"
    assert exec_quote("$HOME") == '"$$HOME"'
    assert exec_quote('a"b\\c') == '"a\\"b\\\\c"'


@pytest.mark.skipif(shutil.which("vim") is None, reason="vim not installed")
def test_vim_save_hook_flushes_before_the_write_returns(local_env, tmp_path):  # noqa: F811
    # `fetchsync` on PATH runs this checkout
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    wrapper = bin_dir / "fetchsync"
    calls = tmp_path / "calls.log"
    wrapper.write_text(
        f'#!/bin/sh\necho "$*" >> {calls}\nexec {shlex.quote(sys.executable)} -m fetchsync "$@"\n'
    )
    wrapper.chmod(0o755)
    env = dict(
        local_env,
        PATH=f"{bin_dir}:{local_env['PATH']}",
        PYTHONPATH=str(Path(__file__).resolve().parent.parent),
    )
    w = Watch(env, tmp_path / "watch.log")
    try:
        wait_for(lambda: w.status().get("state") == "live", what="the agent to be live")
        src, robot = paths(env)
        edited = src / "my_pkg/src/node.cpp"
        # the README's hook, with the workspace's src/ as the pattern
        hook = f"autocmd BufWritePost {src}/* silent !fetchsync flush %:p"
        vim = subprocess.run(
            [
                "vim",
                "-N",
                "-u",
                "NONE",
                "-i",
                "NONE",
                "-es",
                "--cmd",
                hook,
                "-c",
                "call setline(1, 'int main() { return 7; }')",
                "-c",
                "wq",
                str(edited),
            ],
            env=env,
            capture_output=True,
            timeout=30,
            check=False,
        )
        assert vim.returncode == 0, vim
        assert calls.read_text() == f"flush {edited}\n"  # the hook ran, with the saved file
        # no waiting: flush returned only once the saved file was on the robot
        assert (robot / "my_pkg/src/node.cpp").read_text() == "int main() { return 7; }\n"
    finally:
        w.stop()
