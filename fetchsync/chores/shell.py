"""Shell start-up code: fetch_tools' robot helpers and fetchsync's tab completion.

``eval "$(fetchsync shell-init bash)"`` (or ``zsh``) defines fetch_tools'
``fetch`` command and the helpers its ``setup.bash`` defined, with the same
meaning::

    fetch VERB ...    fetchsync VERB ...: fetch_tools' command lines run as typed
                      (``fetch push --build "--pkg my_pkg"``, ``fetch run "roslaunch ..."``,
                      ``fetch debug-snapshot``, ``fetch create-account --fullname X``)

    uf N / ufr N      export ROS_MASTER_URI=http://fetchN:11311 (freightN) and print it;
                      alone, print the current ROS_MASTER_URI
    ul [PORT]         export ROS_MASTER_URI=http://localhost:PORT (11311) and print it
    sf N [ARGS...]    ssh [USER@]fetchN [ARGS...]        (sfr: freightN)
    kf [OPTS...] N    ssh-copy-id [OPTS...] [USER@]fetchN (kfr: freightN)

``N`` is a robot number or name suffix (``7``, ``7.local``); USER is
``$FETCHSYNC_USER``, else ``$FETCH_USER``. The prefixes are read when a helper
runs, from ``$FETCHSYNC_ROBOT_PREFIX`` / ``$FETCHSYNC_ROBOT_PREFIX_R``, with
defaults baked in by ``--prefix`` / ``--prefix-r``.

The helpers never ``eval`` what they are given: every argument is validated
(a robot name is ASCII letters, digits, ``.``, ``_`` and ``-`` and starts with
neither ``-`` nor ``.``, so it cannot become an ssh option) and passed quoted.
One body serves bash and zsh; under zsh each function runs in
``emulate -L zsh`` so the user's options cannot change its meaning.

The completion part is click's own script for the shell (the
``_FETCHSYNC_COMPLETE`` protocol), registered for ``fetch`` too, guarded so
that it is only installed where it can work: bash >= 4.4, and zsh once
``compinit`` has defined ``compdef``. ``--robot`` completes from the ssh
config's ``Host`` names, the plain (unhashed) names of ``known_hosts`` and,
as fetch_tools' completer did, ``fetch0``-``fetch9`` / ``freight0``-``freight9``
(``fetch1`` offers ``fetch10``-``fetch19``): :func:`complete_robot`.

``fetch`` is a function, not a program on PATH: it exists only in shells that
ran ``shell-init``, so it never shadows another ``fetch`` elsewhere (scripts,
cron), and ``shell-init --no-fetch`` leaves it out.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Iterator
from pathlib import Path

import click
from click.shell_completion import CompletionItem, get_completion_class

from fetchsync.errors import UsageError

SHELLS = ("bash", "zsh")
PROG_NAME = "fetchsync"
DEFAULT_PREFIX = "fetch"
DEFAULT_PREFIX_R = "freight"
PREFIX_VAR = "FETCHSYNC_ROBOT_PREFIX"
PREFIX_R_VAR = "FETCHSYNC_ROBOT_PREFIX_R"
FETCH_NAME = "fetch"
GLOBAL_KNOWN_HOSTS = "/etc/ssh/ssh_known_hosts"

# The same rule the helpers apply to $FETCHSYNC_ROBOT_PREFIX at call time.
_PREFIX_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")

# Placeholders: str.format and string.Template would both trip over the
# shell's own braces and dollars.
_HELPERS = r"""# fetchsync shell-init: fetch_tools' helpers and tab completion for fetchsync.
#   fetch VERB ...   fetchsync VERB ... (unless shell-init --no-fetch)
#   uf N | ufr N     export and print ROS_MASTER_URI=http://@PREFIX@N:11311 | http://@PREFIX_R@N:11311
#   ul [PORT]        export and print ROS_MASTER_URI=http://localhost:PORT (default 11311)
#   sf N | sfr N     ssh [$FETCHSYNC_USER or $FETCH_USER@]@PREFIX@N | @PREFIX_R@N
#   kf N | kfr N     ssh-copy-id [OPTIONS] to the same
# N is a number or suffix such as 7 or 7.local. The prefixes are read at call
# time from $FETCHSYNC_ROBOT_PREFIX and $FETCHSYNC_ROBOT_PREFIX_R.

function _fetchsync_usage {
    # _fetchsync_usage VERB PREFIX
    case $1 in
        uf|ufr) printf 'usage: %s N   export and print ROS_MASTER_URI=http://%sN:11311 (N like 7 or 7.local); %s alone prints it\n' "$1" "$2" "$1" ;;
        ul) printf 'usage: ul [PORT]   export and print ROS_MASTER_URI=http://localhost:PORT (default 11311)\n' ;;
        sf|sfr) printf 'usage: %s N [COMMAND...]   ssh to %sN (N like 7 or 7.local), as $FETCHSYNC_USER or $FETCH_USER if set\n' "$1" "$2" ;;
        kf|kfr) printf 'usage: %s [SSH-COPY-ID-OPTIONS...] N   ssh-copy-id to %sN (N like 7 or 7.local), as $FETCHSYNC_USER or $FETCH_USER if set\n' "$1" "$2" ;;
    esac >&2
}

function _fetchsync_host {
    # _fetchsync_host VERB PREFIX N: print the robot's host name PREFIX+N, or complain
    if [ -n "${ZSH_VERSION-}" ]; then emulate -L zsh; fi
    case $2 in
        '' | [!A-Za-z0-9]* | *[!A-Za-z0-9._-]*)
            printf '%s: the robot name prefix %s is not a host name prefix (check $FETCHSYNC_ROBOT_PREFIX and $FETCHSYNC_ROBOT_PREFIX_R)\n' "$1" "'$2'" >&2
            return 1 ;;
    esac
    case $3 in
        '' | [.-]* | *[!A-Za-z0-9._-]*)
            printf '%s: %s is not a robot number or name such as 7 or 7.local\n' "$1" "'$3'" >&2
            _fetchsync_usage "$1" "$2"
            return 1 ;;
    esac
    printf '%s%s\n' "$2" "$3"
}

function _fetchsync_login {
    # _fetchsync_login VERB HOST: print [USER@]HOST, USER from $FETCHSYNC_USER or $FETCH_USER
    if [ -n "${ZSH_VERSION-}" ]; then emulate -L zsh; fi
    local user="${FETCHSYNC_USER:-${FETCH_USER:-}}"
    if [ -z "$user" ]; then
        printf '%s\n' "$2"
        return 0
    fi
    case $user in
        -* | *[[:space:][:cntrl:]]*)
            printf '%s: the user %s (from $FETCHSYNC_USER or $FETCH_USER) is not a user name\n' "$1" "'$user'" >&2
            return 1 ;;
    esac
    printf '%s@%s\n' "$user" "$2"
}

function _fetchsync_use {
    # _fetchsync_use VERB PREFIX [N]: export ROS_MASTER_URI=http://PREFIX+N:11311 and print it
    if [ -n "${ZSH_VERSION-}" ]; then emulate -L zsh; fi
    local verb="$1" prefix="$2" host
    shift 2
    if [ "$#" -eq 0 ] && [ -n "${ROS_MASTER_URI:-}" ]; then
        printf '%s\n' "$ROS_MASTER_URI"
        return 0
    fi
    if [ "$#" -ne 1 ]; then
        _fetchsync_usage "$verb" "$prefix"
        return 1
    fi
    host=$(_fetchsync_host "$verb" "$prefix" "$1") || return 1
    export ROS_MASTER_URI="http://$host:11311"
    printf '%s\n' "$ROS_MASTER_URI"
    # fetchsync takes its robot from ROS_MASTER_URI only when neither of these is set.
    if [ -n "${FETCHSYNC_ROBOT:-}" ]; then
        if [ "$FETCHSYNC_ROBOT" != "$host" ]; then
            printf '%s: note: fetchsync still targets FETCHSYNC_ROBOT=%s; unset it to follow ROS_MASTER_URI\n' "$verb" "$FETCHSYNC_ROBOT" >&2
        fi
    elif [ -n "${FETCH_ROBOT:-}" ] && [ "$FETCH_ROBOT" != "$host" ]; then
        printf '%s: note: fetchsync still targets FETCH_ROBOT=%s; unset it to follow ROS_MASTER_URI\n' "$verb" "$FETCH_ROBOT" >&2
    fi
}

function _fetchsync_ssh {
    # _fetchsync_ssh VERB PREFIX N [ARGS...]: ssh [USER@]PREFIX+N [ARGS...]
    if [ -n "${ZSH_VERSION-}" ]; then emulate -L zsh; fi
    local verb="$1" prefix="$2" host login
    shift 2
    if [ "$#" -eq 0 ]; then
        _fetchsync_usage "$verb" "$prefix"
        return 1
    fi
    host=$(_fetchsync_host "$verb" "$prefix" "$1") || return 1
    login=$(_fetchsync_login "$verb" "$host") || return 1
    shift
    ssh "$login" "$@"
}

function _fetchsync_copy_id {
    # _fetchsync_copy_id VERB PREFIX [OPTIONS...] N: ssh-copy-id [OPTIONS...] [USER@]PREFIX+N
    if [ -n "${ZSH_VERSION-}" ]; then emulate -L zsh; fi
    local verb="$1" prefix="$2" robot arg host login count i=0
    shift 2
    if [ "$#" -eq 0 ]; then
        _fetchsync_usage "$verb" "$prefix"
        return 1
    fi
    # The robot is the last argument; the ones before it go to ssh-copy-id.
    for robot in "$@"; do :; done
    host=$(_fetchsync_host "$verb" "$prefix" "$robot") || return 1
    login=$(_fetchsync_login "$verb" "$host") || return 1
    count=$#
    for arg in "$@"; do
        i=$((i + 1))
        if [ "$i" -eq 1 ]; then set --; fi
        if [ "$i" -lt "$count" ]; then set -- "$@" "$arg"; fi
    done
    ssh-copy-id "$@" "$login"
}

function uf { _fetchsync_use uf "${FETCHSYNC_ROBOT_PREFIX:-@PREFIX@}" "$@"; }
function ufr { _fetchsync_use ufr "${FETCHSYNC_ROBOT_PREFIX_R:-@PREFIX_R@}" "$@"; }
function sf { _fetchsync_ssh sf "${FETCHSYNC_ROBOT_PREFIX:-@PREFIX@}" "$@"; }
function sfr { _fetchsync_ssh sfr "${FETCHSYNC_ROBOT_PREFIX_R:-@PREFIX_R@}" "$@"; }
function kf { _fetchsync_copy_id kf "${FETCHSYNC_ROBOT_PREFIX:-@PREFIX@}" "$@"; }
function kfr { _fetchsync_copy_id kfr "${FETCHSYNC_ROBOT_PREFIX_R:-@PREFIX_R@}" "$@"; }

function ul {
    if [ -n "${ZSH_VERSION-}" ]; then emulate -L zsh; fi
    local port="${1:-11311}"
    if [ "$#" -gt 1 ]; then
        _fetchsync_usage ul
        return 1
    fi
    case $port in
        0* | *[!0-9]* | ??????*)
            printf 'ul: %s is not a port number (1 to 65535)\n' "'$port'" >&2
            _fetchsync_usage ul
            return 1 ;;
    esac
    if [ "$port" -gt 65535 ]; then
        printf 'ul: %s is not a port number (1 to 65535)\n' "'$port'" >&2
        return 1
    fi
    export ROS_MASTER_URI="http://localhost:$port"
    printf '%s\n' "$ROS_MASTER_URI"
}
"""

# fetch_tools' verbs and options kept their names in fetchsync (debug-snapshot
# included: fetchsync runs fetch_tools' collection under that name), so the
# command line passes through untouched, quoting and all.
_FETCH = r"""
# fetch_tools' `fetch`: the same command lines, run by fetchsync.
function fetch {
    command fetchsync "$@"
}
"""

# `fetch` completes as `fetchsync`: click's bash function runs the program its
# first argument names, and `fetch` is a function `env` cannot run.
_BASH_FETCH_COMPLETION = """_fetchsync_fetch_completion() {
    _fetchsync_completion fetchsync "$2" "$3"
}
complete -o nosort -F _fetchsync_fetch_completion fetch
"""
_ZSH_FETCH_COMPLETION = "compdef _fetchsync_completion fetch\n"

# bash splits the word being completed at the characters of COMP_WORDBREAKS,
# '@' among them, so `--robot a,@la<Tab>` reaches click's function as the
# words `a,` `@` `la`, and click would complete `la` as a word of its own. This
# one (defined after click's, so it is the one called) hands click the line up
# to the cursor, whose last word is then `a,@la` whole, and gives readline back
# each answer without what precedes the text readline replaces: the word after
# its last break character, '@' and '$' included (its special prefixes), so
# `@lab` for `a,@lab`. Called without COMP_LINE (by hand), it is click's.
_BASH_WORDS_COMPLETION = r"""_fetchsync_completion() {
    local IFS=$'\n'
    local response completion type value pre=""
    if [[ -z ${COMP_LINE-} ]]; then
        response=$(env COMP_WORDS="${COMP_WORDS[*]}" COMP_CWORD=$COMP_CWORD _FETCHSYNC_COMPLETE=bash_complete $1)
    else
        local line="${COMP_LINE:0:$COMP_POINT}" i
        local word="${line##*[[:space:]]}" breaks="${COMP_WORDBREAKS-}"
        for (( i = ${#word} - 1; i >= 0; i-- )); do
            [[ $breaks == *"${word:i:1}"* ]] && break
        done
        if (( i >= 0 )) && [[ ${word:i:1} == [@\$] ]]; then
            pre="${word:0:i}"  # readline keeps its special prefixes ($ @) in the word
        else
            pre="${word:0:i+1}"
        fi
        response=$(env COMP_WORDS="$line''" COMP_CWORD=-1 _FETCHSYNC_COMPLETE=bash_complete $1)
    fi
    for completion in $response; do
        IFS=',' read type value <<< "$completion"
        if [[ $type == 'dir' ]]; then
            COMPREPLY=()
            compopt -o dirnames
        elif [[ $type == 'file' ]]; then
            COMPREPLY=()
            compopt -o default
        elif [[ $type == 'plain' ]]; then
            if [[ -n $pre && $value == "$pre"* ]]; then
                value="${value:${#pre}}"
            fi
            COMPREPLY+=("$value")
        fi
    done
    return 0
}
"""

# click's scripts use `complete -o nosort` and `compopt` (bash 4.4), and
# `compdef`, which exists only after compinit: elsewhere, skip quietly rather
# than print an error at every shell start-up.
_BASH_GUARD = ("if (( BASH_VERSINFO[0] * 100 + BASH_VERSINFO[1] >= 404 )); then\n", "fi\n")
_ZSH_GUARD = ("if (( ${+functions[compdef]} )); then\n", "fi\n")


def check_shell(shell: str | None) -> str:
    """The shell name if fetchsync can initialise it, else a :class:`UsageError`."""
    if shell is None:
        raise UsageError(
            "name the shell to initialise: bash or zsh",
            hint='e.g. eval "$(fetchsync shell-init bash)" in ~/.bashrc',
        )
    if shell not in SHELLS:
        raise UsageError(f"unsupported shell {shell!r}; choose bash or zsh")
    return shell


def check_prefix(prefix: str, *, option: str) -> str:
    """The robot name prefix if it can start a host name, else a :class:`UsageError`."""
    if not _PREFIX_RE.fullmatch(prefix):
        raise UsageError(
            f"{option} {prefix!r} is not a host name prefix "
            "(ASCII letters, digits, '.', '_', '-'; starting with a letter or digit)"
        )
    return prefix


def helpers(*, prefix: str = DEFAULT_PREFIX, prefix_r: str = DEFAULT_PREFIX_R) -> str:
    """The helper functions (uf, ufr, ul, sf, sfr, kf, kfr), for bash and zsh alike."""
    check_prefix(prefix, option="--prefix")
    check_prefix(prefix_r, option="--prefix-r")
    return _HELPERS.replace("@PREFIX_R@", prefix_r).replace("@PREFIX@", prefix)


def completion(
    shell: str, command: click.Command, *, prog_name: str = PROG_NAME, fetch: bool = True
) -> str:
    """click's completion script for ``command`` in ``shell`` (and for ``fetch`` with
    ``fetch``), guarded to where it works."""
    check_shell(shell)
    complete_var = "_{}_COMPLETE".format(prog_name.replace("-", "_").upper())
    comp_cls = get_completion_class(shell)
    assert comp_cls is not None  # click ships bash and zsh
    comp = comp_cls(command, {}, prog_name, complete_var)
    # Not comp.source(): for bash it runs a bash subprocess to check the
    # version on every shell start-up; the guard checks the running shell.
    script = comp.source_template % comp.source_vars()
    opening, closing = _BASH_GUARD if shell == "bash" else _ZSH_GUARD
    if shell == "bash" and prog_name == PROG_NAME:
        script = script.rstrip("\n") + "\n" + _BASH_WORDS_COMPLETION
    if fetch and prog_name == PROG_NAME:
        script = (
            script.rstrip("\n")
            + "\n"
            + (_BASH_FETCH_COMPLETION if shell == "bash" else _ZSH_FETCH_COMPLETION)
        )
    return opening + script.rstrip("\n") + "\n" + closing


def init_script(
    shell: str | None,
    command: click.Command,
    *,
    prefix: str = DEFAULT_PREFIX,
    prefix_r: str = DEFAULT_PREFIX_R,
    prog_name: str = PROG_NAME,
    fetch: bool = True,
) -> str:
    """Everything ``fetchsync shell-init SHELL`` prints: the helpers, ``fetch``, completion."""
    name = check_shell(shell)
    code = helpers(prefix=prefix, prefix_r=prefix_r)
    if fetch:
        code += _FETCH
    return code + "\n" + completion(name, command, prog_name=prog_name, fetch=fetch)


# --- --robot completion ---------------------------------------------------------------------


def complete_robot(
    ctx: click.Context | None, param: click.Parameter | None, incomplete: str
) -> list[CompletionItem]:
    """``--robot`` candidates: ssh config hosts, known_hosts names, then fetch_tools' numbers.

    Read at each completion (a Tab), never cached: a host added to the ssh
    config is offered at the next Tab. Unreadable files are skipped silently;
    completion must never print an error into the user's command line.
    """
    return [CompletionItem(name) for name in robot_names(incomplete)]


def robot_names(
    incomplete: str, *, home: Path | None = None, global_known_hosts: str = GLOBAL_KNOWN_HOSTS
) -> list[str]:
    """The names :func:`complete_robot` offers for ``incomplete``, in order, once each: for
    the last word of a list (``a,fe``), with the words before it kept; ``@`` and a group
    of robots.toml's (``@lab``) for a word that starts with ``@``."""
    head, comma, word = incomplete.rpartition(",")
    before = head + comma
    if word.startswith("@"):
        return [before + "@" + g for g in _group_names(home) if g.startswith(word[1:])]
    return [before + name for name in _host_names(word, home, global_known_hosts)]


def _group_names(home: Path | None) -> list[str]:
    """The groups of robots.toml (none when it cannot be read: completion prints no errors)."""
    from fetchsync.errors import ConfigError
    from fetchsync.robots import groups

    environ = os.environ if home is None else {**os.environ, "HOME": str(home)}
    if home is not None:
        environ.pop("XDG_CONFIG_HOME", None)
    try:
        return list(groups(environ=environ))
    except ConfigError:
        return []


def _host_names(incomplete: str, home: Path | None, global_known_hosts: str) -> list[str]:
    base = home if home is not None else Path(os.path.expanduser("~"))
    ssh_dir = base / ".ssh"
    found = list(ssh_config_hosts(ssh_dir / "config"))
    for path in (ssh_dir / "known_hosts", Path(global_known_hosts)):
        found.extend(known_host_names(path))
    found.extend(fetch_tools_names(incomplete))
    seen: set[str] = set()
    out = []
    for name in found:
        if name.startswith(incomplete) and name not in seen:
            seen.add(name)
            out.append(name)
    return out


def fetch_tools_names(prefix: str) -> list[str]:
    """fetch_tools' ``RobotCompleter``: ``fetch0-9`` / ``freight0-9`` while typing those
    words, else the typed text followed by each digit."""
    options: list[str] = []
    for word in (DEFAULT_PREFIX, DEFAULT_PREFIX_R):
        if word.startswith(prefix) and prefix != word:
            options.extend(f"{word}{i}" for i in range(10))
    if options:
        return options
    if not prefix or not _PREFIX_RE.fullmatch(prefix):
        return []
    return [f"{prefix}{i}" for i in range(10)]


def ssh_config_hosts(path: Path) -> Iterator[str]:
    """The literal names of ``Host`` lines (no patterns: ``*``, ``?``, ``!``)."""
    for line in _lines(path):
        words = line.replace("=", " ", 1).split()
        if len(words) < 2 or words[0].lower() != "host":
            continue
        for name in words[1:]:
            if not any(c in name for c in "*?!") and _is_host_name(name):
                yield name


def known_host_names(path: Path) -> Iterator[str]:
    """The plain names of a known_hosts file: hashed entries, markers (``@revoked``,
    ``@cert-authority``) and hosts on another port than 22 are left out."""
    for line in _lines(path):
        if line.startswith(("|", "@")):
            continue
        for name in line.split(None, 1)[0].split(","):
            if name.startswith("["):
                host, _, port = name[1:].partition("]:")
                if port != "22":
                    continue
                name = host
            if not any(c in name for c in "*?!") and _is_host_name(name):
                yield name


def _is_host_name(name: str) -> bool:
    return bool(name) and not name.startswith("-") and all(c.isalnum() or c in "._-:" for c in name)


def _lines(path: Path) -> Iterable[str]:
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            text = f.read(1 << 20)
    except OSError:
        return []
    return [
        line.strip()
        for line in text.splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]
