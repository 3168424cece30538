"""``fetchsync shell-init``: print the shell code for fetch_tools' helpers and completion."""

from __future__ import annotations

import click
from click.shell_completion import CompletionItem

from fetchsync.chores.shell import DEFAULT_PREFIX, DEFAULT_PREFIX_R, SHELLS, init_script


def _complete_shell(
    ctx: click.Context, param: click.Parameter, incomplete: str
) -> list[CompletionItem]:
    return [CompletionItem(name) for name in SHELLS if name.startswith(incomplete)]


@click.command("shell-init")
@click.argument("shell", required=False, metavar="bash|zsh", shell_complete=_complete_shell)
@click.option(
    "--prefix",
    default=DEFAULT_PREFIX,
    show_default=True,
    metavar="NAME",
    help="Default robot name prefix of uf, sf and kf "
    "($FETCHSYNC_ROBOT_PREFIX overrides it when they run).",
)
@click.option(
    "--prefix-r",
    default=DEFAULT_PREFIX_R,
    show_default=True,
    metavar="NAME",
    help="Default robot name prefix of ufr, sfr and kfr "
    "($FETCHSYNC_ROBOT_PREFIX_R overrides it when they run).",
)
@click.option(
    "--fetch/--no-fetch",
    "fetch",
    default=True,
    show_default=True,
    help="Define fetch_tools' `fetch` command (a shell function running fetchsync).",
)
@click.pass_context
def command(ctx: click.Context, shell: str | None, prefix: str, prefix_r: str, fetch: bool) -> None:
    """Print shell code defining fetch_tools' fetch command, helpers and tab completion.

    \b
    Add to ~/.bashrc:                  eval "$(fetchsync shell-init bash)"
    or to ~/.zshrc, after compinit:    eval "$(fetchsync shell-init zsh)"

    \b
    fetch VERB ...  fetchsync VERB ...: fetch_tools' command lines, as typed
    uf N, ufr N     export and print ROS_MASTER_URI=http://fetchN:11311 (freightN)
    ul [PORT]       the same for localhost (port 11311 by default)
    sf N, sfr N     ssh to fetchN / freightN as $FETCHSYNC_USER or $FETCH_USER
    kf N, kfr N     ssh-copy-id to the same
    N is a number or suffix such as 7 or 7.local.
    """
    click.echo(
        init_script(shell, ctx.find_root().command, prefix=prefix, prefix_r=prefix_r, fetch=fetch),
        nl=False,
    )
