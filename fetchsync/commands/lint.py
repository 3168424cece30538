"""``fetchsync lint``: the click layer over :mod:`fetchsync.lint` (parse, lint, print)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import click

from fetchsync.lint import DEFAULT_MAX_LINE_LENGTH, TOOLS, lint

log = logging.getLogger(__name__)


@click.command("lint")
@click.argument("target", metavar="FILE|DIRECTORY|PACKAGE")
@click.option("--workspace", type=click.Path(file_okay=False),
              help="Workspace whose src/ holds the packages (to find PACKAGE, and for "
              "catkin_lint). Default: $FETCHSYNC_WORKSPACE, $FETCH_WORKSPACE, ~/$ROS_DISTRO.")
@click.option("--tool", "tools", multiple=True, type=click.Choice(TOOLS),
              help="Run only this tool; repeatable. Default: all of them.")
@click.option("--max-line-length", type=click.IntRange(min=1), default=DEFAULT_MAX_LINE_LENGTH,
              show_default=True, help="Longest line allowed (pycodestyle and cpplint).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of text.")
@click.pass_context
def command(ctx: click.Context, target: str, workspace: str | None, tools: tuple[str, ...],
            max_line_length: int, as_json: bool) -> None:
    """Lint a file, a directory or a workspace package the way roslint does.

    pycodestyle on Python files, cpplint with roslint's filters on C/C++ files,
    catkin_lint on packages (with the workspace as its package path). Exits 1
    when anything is found.
    """
    report = lint(target, workspace=workspace, tools=tools or TOOLS,
                  max_line_length=max_line_length)
    base = Path.cwd()
    if as_json:
        click.echo(json.dumps(report.to_json(base=base), sort_keys=True))
    else:
        for line in report.lines(base=base):
            click.echo(line)
    log.debug("lint %s: %d findings", target, report.total)
    ctx.exit(1 if report.total else 0)
