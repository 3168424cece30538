"""`fetchsync shell-init`: the generated helpers and completion, run in real bash and zsh.

Each case evaluates the generated code in the real shell and checks what it
did: the exported ROS_MASTER_URI, or the argv that fake ``ssh`` /
``ssh-copy-id`` scripts on PATH received (what a helper runs is what is under
test, not OpenSSH). Completion goes through click's environment-variable
protocol, once directly and once through each shell's completion function.
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner
from helpers import clean_env

from fetchsync.cli import cli

REPO = Path(__file__).resolve().parents[1]
SHELLS = ["bash", "zsh"]

# Prints its own name and each argument in brackets, so quoting is visible.
FAKE_TOOL = """#!/bin/sh
printf '%s' "${0##*/}"
for arg in "$@"; do printf ' [%s]' "$arg"; done
echo
"""


def _need(shell: str) -> str:
    path = shutil.which(shell)
    if path is None:
        if os.environ.get("CI"):
            pytest.fail(f"{shell} is not installed (.ci/run installs it)", pytrace=False)
        pytest.skip(f"{shell} not installed (apt-get install {shell})")
    return path


def _generate(*args: str) -> str:
    result = CliRunner().invoke(cli, ["shell-init", *args], prog_name="fetchsync")
    assert result.exit_code == 0, result.output
    return result.output


@pytest.fixture(params=SHELLS)
def shell(request: pytest.FixtureRequest) -> str:
    _need(request.param)
    return str(request.param)


@pytest.fixture
def env(tmp_path: Path) -> dict[str, str]:
    """An environment with fake ssh tools and this checkout's fetchsync first on PATH."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name in ("ssh", "ssh-copy-id"):
        (bin_dir / name).write_text(FAKE_TOOL)
        (bin_dir / name).chmod(0o755)
    # The installed `fetchsync` may be another checkout: run this one.
    wrapper = bin_dir / "fetchsync"
    wrapper.write_text(f'#!/bin/sh\nexec {shlex.quote(sys.executable)} -m fetchsync "$@"\n')
    wrapper.chmod(0o755)
    keep = {k: v for k, v in clean_env().items() if k not in ("BASH_ENV", "ENV", "ZDOTDIR")}
    keep.update(
        PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}",
        PYTHONPATH=str(REPO),
        HOME=str(tmp_path),
    )
    return keep


def run(
    shell: str, code: str, body: str, env: dict[str, str], tmp_path: Path, *, setup: str = ""
) -> subprocess.CompletedProcess[str]:
    """Run ``body`` in a fresh non-interactive ``shell`` after sourcing ``code``."""
    script = tmp_path / f"init.{shell}"
    script.write_text(code)
    argv = [_need(shell), "--norc", "--noprofile"] if shell == "bash" else [_need(shell), "-f"]
    program = f"{setup}\n. {shlex.quote(str(script))}\n{body}\n"
    return subprocess.run(
        [*argv, "-c", program],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )


@pytest.fixture(scope="module")
def generated() -> dict[str, str]:
    return {name: _generate(name) for name in SHELLS}


def test_eval_of_the_real_command_defines_the_helpers(
    shell: str, env: dict[str, str], tmp_path: Path
) -> None:
    out = run(
        shell,
        "",
        f'eval "$(fetchsync shell-init {shell})"; uf 3; echo "$ROS_MASTER_URI"',
        env,
        tmp_path,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == ["http://fetch3:11311", "http://fetch3:11311"]
    assert out.stderr == ""


@pytest.mark.parametrize(
    ("body", "uri"),
    [
        ("uf 3", "http://fetch3:11311"),
        ("ufr 2", "http://freight2:11311"),
        ("uf 7.local", "http://fetch7.local:11311"),
        ("ufr 0.local", "http://freight0.local:11311"),
        ("ul", "http://localhost:11311"),
        ("ul 11312", "http://localhost:11312"),
    ],
)
def test_ros_master_uri_helpers(
    shell: str, generated: dict[str, str], env: dict[str, str], tmp_path: Path, body: str, uri: str
) -> None:
    out = run(shell, generated[shell], f'{body}; echo "exported $ROS_MASTER_URI"', env, tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [uri, f"exported {uri}"]
    assert out.stderr == ""


def test_fetchsync_follows_the_robot_uf_chose(
    shell: str, generated: dict[str, str], env: dict[str, str], tmp_path: Path
) -> None:
    resolve = (
        f"{shlex.quote(sys.executable)} -c "
        "'from fetchsync.config import resolve_robot; print(resolve_robot())'"
    )
    out = run(shell, generated[shell], f"uf 7.local >/dev/null; {resolve}", env, tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout == "fetch7.local\n"


def test_uf_alone_prints_the_current_uri_like_fetch_tools(
    shell: str, generated: dict[str, str], env: dict[str, str], tmp_path: Path
) -> None:
    out = run(shell, generated[shell], "ufr 4 >/dev/null; uf; uf; echo rc=$?", env, tmp_path)
    assert out.stdout.splitlines() == ["http://freight4:11311"] * 2 + ["rc=0"]
    unset = run(shell, generated[shell], "uf; echo rc=$?", env, tmp_path)
    assert unset.stdout.splitlines() == ["rc=1"]
    assert unset.stderr.startswith("usage: uf N")


def test_ssh_helpers_run_ssh_with_user_and_arguments(
    shell: str, generated: dict[str, str], env: dict[str, str], tmp_path: Path
) -> None:
    body = """
sf 1
FETCH_USER=bob sf 1
FETCHSYNC_USER=al FETCH_USER=bob sf 1
sfr 2.local
sf 5 ls '-la /tmp' 'a b'
kf 4
FETCH_USER=bob kfr 3.local
kf -i ~/'my key.pub' -f 4
"""
    out = run(shell, generated[shell], body, env, tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [
        "ssh [fetch1]",
        "ssh [bob@fetch1]",
        "ssh [al@fetch1]",
        "ssh [freight2.local]",
        "ssh [fetch5] [ls] [-la /tmp] [a b]",
        "ssh-copy-id [fetch4]",
        "ssh-copy-id [bob@freight3.local]",
        f"ssh-copy-id [-i] [{tmp_path}/my key.pub] [-f] [fetch4]",
    ]
    assert out.stderr == ""


@pytest.mark.parametrize(
    "body",
    [
        "uf 1 2",
        "uf ''",
        "uf '1; touch PWNED'",
        "uf '$(touch PWNED)'",
        "uf -h",
        "ufr .local",
        "ul 0",
        "ul 65536",
        "ul 123456",
        "ul port",
        "ul 1 2",
        "sf",
        "kfr",
        "sf '-oProxyCommand=touch PWNED'",
        "kf -i key '1 2'",
        "FETCH_USER='-oProxyCommand=touch PWNED' sf 1",
        "FETCHSYNC_USER='a b' kf 1",
        "FETCHSYNC_ROBOT_PREFIX='-o' sf 1",
        "FETCHSYNC_ROBOT_PREFIX_R='x;y' ufr 1",
    ],
)
def test_bad_input_is_refused_with_a_message(
    shell: str, generated: dict[str, str], env: dict[str, str], tmp_path: Path, body: str
) -> None:
    out = run(
        shell,
        generated[shell],
        f"ul 9999 >/dev/null\n{body}\necho rc=$? $ROS_MASTER_URI",
        env,
        tmp_path,
    )
    # Nothing ran (the fakes print to stdout), nothing changed, nothing was evaluated.
    assert out.stdout.splitlines() == ["rc=1 http://localhost:9999"]
    assert out.stderr.strip(), "a message on stderr"
    assert not (tmp_path / "PWNED").exists()


def test_prefixes_baked_by_options_and_overridden_by_the_environment(
    shell: str, env: dict[str, str], tmp_path: Path
) -> None:
    code = _generate(shell, "--prefix", "robo", "--prefix-r", "base")
    body = """
uf 1
ufr 2.local
sf 3
kfr 4
export FETCHSYNC_ROBOT_PREFIX=tiago FETCHSYNC_ROBOT_PREFIX_R=pmb2
uf 5
sfr 6
"""
    out = run(shell, code, body, env, tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [
        "http://robo1:11311",
        "http://base2.local:11311",
        "ssh [robo3]",
        "ssh-copy-id [base4]",
        "http://tiago5:11311",
        "ssh [pmb26]",
    ]


def test_uf_notes_a_robot_variable_that_still_wins(
    shell: str, generated: dict[str, str], env: dict[str, str], tmp_path: Path
) -> None:
    out = run(
        shell, generated[shell], "FETCH_ROBOT=fetch9 uf 1; FETCH_ROBOT=fetch1 uf 1", env, tmp_path
    )
    assert out.stdout.splitlines() == ["http://fetch1:11311"] * 2
    assert out.stderr.splitlines() == [
        "uf: note: fetchsync still targets FETCH_ROBOT=fetch9; unset it to follow ROS_MASTER_URI"
    ]


@pytest.mark.parametrize(
    ("shell_name", "setup"),
    [
        ("bash", "set -u"),
        ("zsh", "setopt ksh_arrays sh_word_split no_unset no_glob; IFS=."),
    ],
)
def test_helpers_ignore_the_users_shell_options(
    shell_name: str, setup: str, generated: dict[str, str], env: dict[str, str], tmp_path: Path
) -> None:
    _need(shell_name)
    out = run(
        shell_name,
        generated[shell_name],
        "ul; uf 2.local; sf 1 'a b'; kf -i k 3; sf; echo rc=$?",
        env,
        tmp_path,
        setup=setup,
    )
    assert out.stdout.splitlines() == [
        "http://localhost:11311",
        "http://fetch2.local:11311",
        "ssh [fetch1] [a b]",
        "ssh-copy-id [-i] [k] [fetch3]",
        "rc=1",
    ]
    assert out.stderr.startswith("usage: sf N")


def test_bash_completion_of_verbs_and_options(
    generated: dict[str, str], env: dict[str, str], tmp_path: Path
) -> None:
    body = """
complete -p fetchsync
complete_words() { COMPREPLY=(); COMP_WORDS=("$@"); COMP_CWORD=$(($# - 1));
                   _fetchsync_completion fetchsync; echo "${COMPREPLY[*]}"; }
complete_words fetchsync ''
complete_words fetchsync p
complete_words fetchsync push --r
complete_words fetchsync shell-init ''
"""
    out = run("bash", generated["bash"], body, env, tmp_path)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "complete -o nosort -F _fetchsync_completion fetchsync"
    assert {"push", "pull", "shell-init"} <= set(lines[1].split())
    assert lines[2].split() == ["pull", "push"]
    assert "--robot" in lines[3].split() and "--remote-workspace" in lines[3].split()
    assert lines[4].split() == ["bash", "zsh"]


def test_zsh_completion_registers_with_compdef_and_offers_verbs(
    generated: dict[str, str], env: dict[str, str], tmp_path: Path
) -> None:
    _need("zsh")
    # compadd and _describe only work inside a completion widget: stand-ins
    # print what click's zsh function hands them.
    body = """
print -r -- "registered: ${_comps[fetchsync]}"
function _describe { print -rl -- "${(@P)3}"; }
function compadd { print -r -- "compadd $*"; }
words=(fetchsync pu); CURRENT=2; _fetchsync_completion
words=(fetchsync push --r); CURRENT=3; _fetchsync_completion
"""
    out = run(
        "zsh", generated["zsh"], body, env, tmp_path, setup="autoload -Uz compinit; compinit -u -D"
    )
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "registered: _fetchsync_completion"
    names = [line.split(":", 1)[0] for line in lines[1:]]
    assert names[:2] == ["pull", "push"]
    assert "--robot" in names


def test_zsh_without_compinit_loads_the_helpers_quietly(
    generated: dict[str, str], env: dict[str, str], tmp_path: Path
) -> None:
    _need("zsh")
    out = run("zsh", generated["zsh"], "uf 1", env, tmp_path)
    assert (out.returncode, out.stdout, out.stderr) == (0, "http://fetch1:11311\n", "")


@pytest.mark.parametrize(
    ("words", "cword", "expected"),
    [
        ("fetchsync ", 1, {"plain,push", "plain,pull", "plain,shell-init"}),
        ("fetchsync push --r", 2, {"plain,--robot", "plain,--remote-workspace"}),
        ("fetchsync shell-init ", 2, {"plain,bash", "plain,zsh"}),
    ],
)
def test_click_completion_protocol(words: str, cword: int, expected: set[str]) -> None:
    result = CliRunner().invoke(
        cli,
        [],
        prog_name="fetchsync",
        env={"_FETCHSYNC_COMPLETE": "bash_complete", "COMP_WORDS": words, "COMP_CWORD": str(cword)},
    )
    assert result.exit_code == 0
    assert expected <= set(result.output.splitlines())


def test_cli_prints_helpers_and_completion_per_shell(generated: dict[str, str]) -> None:
    for code in generated.values():
        for name in ("uf", "ufr", "ul", "sf", "sfr", "kf", "kfr"):
            assert f"\nfunction {name} " in code
    assert "complete -o nosort -F _fetchsync_completion fetchsync" in generated["bash"]
    assert "compdef _fetchsync_completion fetchsync" in generated["zsh"]
    assert "compdef" not in generated["bash"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["fish"], "fetchsync: error: unsupported shell 'fish'; choose bash or zsh"),
        ([], "fetchsync: error: name the shell to initialise: bash or zsh"),
        (["bash", "--prefix", "-o"], "fetchsync: error: --prefix '-o' is not a host name prefix"),
        (
            ["zsh", "--prefix-r", "a b"],
            "fetchsync: error: --prefix-r 'a b' is not a host name prefix",
        ),
    ],
)
def test_cli_refuses_bad_input_in_one_line(args: list[str], message: str) -> None:
    result = CliRunner().invoke(cli, ["shell-init", *args], prog_name="fetchsync")
    assert result.exit_code == 2
    assert len(result.output.splitlines()) == 1
    assert result.output.startswith(message)


# --- fetch_tools' `fetch` command -----------------------------------------------------------


@pytest.fixture
def fake_fetchsync(env: dict[str, str], tmp_path: Path) -> dict[str, str]:
    """``env`` with a fake ``fetchsync`` first on PATH that prints its argv, bracketed."""
    fake_dir = tmp_path / "fake"
    fake_dir.mkdir()
    (fake_dir / "fetchsync").write_text(FAKE_TOOL)
    (fake_dir / "fetchsync").chmod(0o755)
    return dict(env, PATH=f"{fake_dir}{os.pathsep}{env['PATH']}")


def test_fetch_passes_fetch_tools_command_lines_as_typed(
    shell: str, generated: dict[str, str], fake_fetchsync: dict[str, str], tmp_path: Path
) -> None:
    # The command lines of fetch_tools' README, verbatim.
    body = """
fetch create-account --fullname "Not A. Robot"
fetch push --install-deps --build
fetch run "roslaunch my_awesome_package do_stuff.launch"
fetch push --build "--pkg my_awesome_package"
fetch push --build "--pkg follow_pick -DCMAKE_BUILD_TYPE=RELEASE"
fetch create-account --robot freight0 --user test
fetch pull --no-safety
fetch lint my_pkg
fetch workspace-status
fetch debug-snapshot
fetch run 'echo "$HOME" *'
"""
    out = run(shell, generated[shell], body, fake_fetchsync, tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [
        "fetchsync [create-account] [--fullname] [Not A. Robot]",
        "fetchsync [push] [--install-deps] [--build]",
        "fetchsync [run] [roslaunch my_awesome_package do_stuff.launch]",
        "fetchsync [push] [--build] [--pkg my_awesome_package]",
        "fetchsync [push] [--build] [--pkg follow_pick -DCMAKE_BUILD_TYPE=RELEASE]",
        "fetchsync [create-account] [--robot] [freight0] [--user] [test]",
        "fetchsync [pull] [--no-safety]",
        "fetchsync [lint] [my_pkg]",
        "fetchsync [workspace-status]",
        "fetchsync [debug-snapshot]",
        'fetchsync [run] [echo "$HOME" *]',
    ]


def test_fetch_exits_with_fetchsyncs_status(
    shell: str, generated: dict[str, str], env: dict[str, str], tmp_path: Path
) -> None:
    out = run(
        shell,
        generated[shell],
        "fetch --version; echo rc=$?; fetch nosuchverb; echo rc=$?",
        env,
        tmp_path,
    )
    lines = out.stdout.splitlines()
    assert lines[0].startswith("fetchsync, version ") and lines[1] == "rc=0"
    assert lines[2] == "rc=2" and "No such command 'nosuchverb'" in out.stderr


def test_no_fetch_leaves_the_fetch_command_out(
    shell: str, env: dict[str, str], tmp_path: Path
) -> None:
    code = _generate(shell, "--no-fetch")
    assert "function fetch " not in code and " fetch\n" not in code
    out = run(shell, code, "type fetch >/dev/null 2>&1; echo rc=$?; uf 2", env, tmp_path)
    assert out.stdout.splitlines() == ["rc=1", "http://fetch2:11311"]


def test_bash_completion_of_fetch(
    generated: dict[str, str], env: dict[str, str], tmp_path: Path
) -> None:
    body = """
complete -p fetch
complete_words() { COMPREPLY=(); COMP_WORDS=("$@"); COMP_CWORD=$(($# - 1));
                   _fetchsync_fetch_completion fetch "${COMP_WORDS[COMP_CWORD]}" "$3"; echo "${COMPREPLY[*]}"; }
complete_words fetch p
complete_words fetch push --bu
complete_words fetch de
"""
    out = run("bash", generated["bash"], body, env, tmp_path)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "complete -o nosort -F _fetchsync_fetch_completion fetch"
    assert lines[1].split() == ["pull", "push"]
    assert lines[2].split() == ["--build", "--build-type", "--build-tool"]
    assert lines[3].split() == ["debug-snapshot"]


def test_zsh_completion_of_fetch(
    generated: dict[str, str], env: dict[str, str], tmp_path: Path
) -> None:
    _need("zsh")
    body = """
print -r -- "registered: ${_comps[fetch]}"
function _describe { print -rl -- "${(@P)3}"; }
function compadd { print -r -- "compadd $*"; }
words=(fetch pu); CURRENT=2; _fetchsync_completion
"""
    out = run(
        "zsh", generated["zsh"], body, env, tmp_path, setup="autoload -Uz compinit; compinit -u -D"
    )
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "registered: _fetchsync_completion"
    assert [line.split(":", 1)[0] for line in lines[1:3]] == ["pull", "push"]


# --- --robot completion ---------------------------------------------------------------------


def _robot_home(home: Path) -> Path:
    ssh = home / ".ssh"
    ssh.mkdir(parents=True)
    (ssh / "config").write_text(
        "# my robots\nHost lab-fetch3 freight0\n    HostName 10.0.0.3\n"
        "Host *.corp !bad\n    User me\nhost=tiago1\nMatch host x\n"
    )
    (ssh / "known_hosts").write_text(
        "fetch42,10.1.1.42 ssh-ed25519 AAAA\n"
        "|1|aGFzaGVk|c2FsdA== ssh-ed25519 AAAA\n"
        "[odd-port]:2222 ssh-ed25519 AAAA\n"
        "[port22]:22 ssh-ed25519 AAAA\n"
        "@cert-authority *.corp ssh-ed25519 AAAA\n"
        "@revoked fetch-revoked ssh-ed25519 AAAA\n"
    )
    return home


@pytest.mark.parametrize(
    ("typed", "expected"),
    [
        (
            "",
            ["lab-fetch3", "freight0", "tiago1", "fetch42", "10.1.1.42", "port22"]
            + [f"fetch{i}" for i in range(10)]
            + [f"freight{i}" for i in range(1, 10)],
        ),
        ("fr", ["freight0"] + [f"freight{i}" for i in range(1, 10)]),
        ("fetch", ["fetch42"] + [f"fetch{i}" for i in range(10)]),
        ("fetch4", ["fetch42"] + [f"fetch4{i}" for i in range(10) if i != 2]),
        ("lab", ["lab-fetch3"] + [f"lab{i}" for i in range(10)]),
        ("-o", []),
    ],
)
def test_robot_names_from_ssh_config_known_hosts_and_fetch_tools(
    tmp_path: Path, typed: str, expected: list[str]
) -> None:
    from fetchsync.chores.shell import robot_names

    home = _robot_home(tmp_path)
    assert robot_names(typed, home=home, global_known_hosts=str(tmp_path / "none")) == expected


def test_robot_names_without_ssh_files(tmp_path: Path) -> None:
    from fetchsync.chores.shell import robot_names

    assert robot_names("f", home=tmp_path, global_known_hosts=str(tmp_path / "none")) == (
        [f"fetch{i}" for i in range(10)] + [f"freight{i}" for i in range(10)]
    )


@pytest.mark.parametrize("verb", ["push", "run", "create-account", "snapshot", "debug-snapshot"])
def test_robot_option_completes_in_every_robot_verb(tmp_path: Path, verb: str) -> None:
    home = _robot_home(tmp_path)
    result = CliRunner().invoke(
        cli,
        [],
        prog_name="fetchsync",
        env={
            "_FETCHSYNC_COMPLETE": "bash_complete",
            "COMP_WORDS": f"fetch {verb} --robot la",
            "COMP_CWORD": "3",
            "HOME": str(home),
        },
    )
    assert result.exit_code == 0
    assert result.output.splitlines()[0] == "plain,lab-fetch3"


def test_fetch_robot_completion_through_bash(
    generated: dict[str, str], env: dict[str, str], tmp_path: Path
) -> None:
    _robot_home(tmp_path)  # env's HOME is tmp_path
    body = """
COMP_WORDS=(fetch push --robot frei); COMP_CWORD=3
_fetchsync_fetch_completion fetch frei --robot; echo "${COMPREPLY[*]}"
"""
    out = run("bash", generated["bash"], body, env, tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["freight0"] + [f"freight{i}" for i in range(1, 10)]
