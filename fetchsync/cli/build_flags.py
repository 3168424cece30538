"""The build options of ``push`` and ``pull``: ``--build [ARGS]``, ``--build-type``, ...

``--build`` takes an optional value, as fetch_tools' (argparse ``nargs='?'``,
``action='append'``): ``--build`` alone builds without arguments,
``--build=-j4`` and ``--build "-j4 -DX=1"`` pass arguments, and each
occurrence is one more build. click's own optional values take no value that
starts with ``-`` even after ``=``, so :class:`BuildCommand` rewrites a bare
``--build`` to ``--build=`` before parsing and the option always takes one.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Callable

import click

if TYPE_CHECKING:
    from fetchsync.chores.build import BuildRequest

BUILD = "--build"
# fetchsync.chores.build's BUILD_TYPES and TOOLS (a test checks), without importing it at start-up
BUILD_TYPES = ("Debug", "Release", "RelWithDebInfo", "MinSizeRel", "default")
TOOLS = ("auto", "catkin_make", "catkin", "colcon")


def explicit_build_values(args: Sequence[str]) -> list[str]:
    """``args`` with every bare ``--build`` given its value explicitly.

    As argparse decides: the next argument is the value unless it looks like
    an option (starts with ``-`` and has no space) or there is none.
    """
    out: list[str] = []
    rest = list(args)
    while rest:
        arg = rest.pop(0)
        if arg == "--":
            out.append(arg)
            out.extend(rest)
            break
        if arg == BUILD:
            nxt = rest[0] if rest else None
            if nxt is None or nxt == "--" or (nxt.startswith("-") and " " not in nxt):
                out.append(BUILD + "=")
                continue
        out.append(arg)
    return out


class BuildCommand(click.Command):
    """A command with :func:`build_options` (see the module's docstring)."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        return super().parse_args(ctx, explicit_build_values(args))


def build_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """``--build``, ``--build-type``, ``--build-tool`` and ``--install-deps``."""
    opts = [
        click.option(
            BUILD,
            "builds",
            multiple=True,
            metavar="[ARGS]",
            help="Build after syncing, passing ARGS to the build tool (--build=-j4); "
            "repeatable: one build each.",
        ),
        click.option(
            "--build-type",
            type=click.Choice(BUILD_TYPES),
            default="default",
            help="CMAKE_BUILD_TYPE of the builds ('default' passes none).",
        ),
        click.option(
            "--build-tool",
            type=click.Choice(TOOLS),
            default="auto",
            help="catkin_make, catkin (catkin build) or colcon. Default: what the "
            "workspace is set up for.",
        ),
        click.option(
            "--install-deps",
            is_flag=True,
            help="Install dependencies first: rosdep update, then "
            "rosdep install --from-paths src --ignore-src -y.",
        ),
    ]
    for opt in reversed(opts):
        func = opt(func)
    return func


def build_request(
    builds: Sequence[str], build_type: str, build_tool: str, install_deps: bool
) -> BuildRequest | None:
    """The request these options make; None when they ask for nothing (without importing
    the build module: every push and pull asks this)."""
    if not builds:
        unused = [
            name
            for name, value, default in (
                ("--build-type", build_type, "default"),
                ("--build-tool", build_tool, "auto"),
            )
            if value != default
        ]
        if unused:
            verb = "has" if len(unused) == 1 else "have"
            click.echo(
                f"fetchsync: warning: {' and '.join(unused)} {verb} no effect without --build",
                err=True,
            )
        if not install_deps:
            return None
    from fetchsync.chores.build import BuildRequest

    return BuildRequest(
        builds=tuple(builds), build_type=build_type, tool=build_tool, install_deps=install_deps
    )
