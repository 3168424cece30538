"""``fetchsync lint``: the click layer over :mod:`fetchsync.chores.lint` (parse, lint, print)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import click

from fetchsync.chores.lint import AUTO, STYLES, TOOLS, lint

log = logging.getLogger(__name__)


@click.command("lint")
@click.argument("target", metavar="FILE|DIRECTORY|PACKAGE")
@click.option(
    "--workspace",
    type=click.Path(file_okay=False),
    help="Workspace whose src/ holds the packages (to find PACKAGE, and for "
    "catkin_lint). Default: $FETCHSYNC_WORKSPACE, $FETCH_WORKSPACE, ~/$ROS_DISTRO.",
)
@click.option(
    "--style",
    type=click.Choice(STYLES),
    default=AUTO,
    show_default=True,
    help="roslint: fetch_tools' rules (pep8, roslint's cpplint, catkin_lint); ament: "
    "ROS 2's (ament_cpplint, ament_pep257, flake8 with ament's settings); auto: "
    "ament for ROS 2 packages (format 3 without catkin, ament_* build types), "
    "roslint for the rest.",
)
@click.option(
    "--tool",
    "tools",
    multiple=True,
    type=click.Choice(TOOLS),
    help="Run only this tool; repeatable. Default: all of the style's.",
)
@click.option(
    "--max-line-length",
    type=click.IntRange(min=1),
    default=None,
    help="Longest line allowed, for every tool. Default: each style's (pep8 79, "
    "roslint's cpplint 120, flake8 99, ament_cpplint 100).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of text.")
@click.pass_context
def command(
    ctx: click.Context,
    target: str,
    workspace: str | None,
    style: str,
    tools: tuple[str, ...],
    max_line_length: int | None,
    as_json: bool,
) -> None:
    """Lint a file, a directory or a workspace package with ROS's own rules.

    The first line of the output says which style each package got. Exits 1
    when anything is found.
    """
    report = lint(
        target,
        workspace=workspace,
        tools=tools or None,
        max_line_length=max_line_length,
        style=style,
    )
    base = Path.cwd()
    if as_json:
        click.echo(json.dumps(report.to_json(base=base), sort_keys=True))
    else:
        for line in report.lines(base=base):
            click.echo(line)
    log.debug("lint %s: %d findings", target, report.total)
    ctx.exit(1 if report.total else 0)
