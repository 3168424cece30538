"""roslint's cpplint wrapper over the cpplint of PyPI: ``python -m fetchsync.chores.roslint_cpplint``.

fetch_tools' ``lint`` ran ``/opt/ros/$DISTRO/lib/roslint/cpplint`` with
``--filter=+,-runtime/references,-runtime/threadsafe_fn``: roslint's copy of
cpplint, patched by ``roslint/cpplint_wrapper.py`` to ROS's C++ style. This
module applies the same patches, function for function, to the cpplint
installed from PyPI (its checks are a newer cpplint's), then runs its
``main()`` with the arguments given:

- lines up to 120 characters;
- ``CheckBraces`` replaced: ``{`` that opens a scope goes on a line of its
  own, and ``}`` too (one-line bodies and initialisers excepted);
- include order, ``include_alpha`` and streams not reported by
  ``CheckIncludeLine``; brace placement not reported by ``CheckSpacing``;
- access specifiers need not be indented by one space;
- header guards named from the package or ``include/`` directory
  (``PKG_THING_H``);
- ``do { } while (x);`` accepted by ``CheckEmptyBlockBody``.

Laptop side only (it imports cpplint).
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Callable, Iterable
from typing import Any

import cpplint

Error = Callable[[str, int, str, int, str], None]

_original: dict[str, Callable[..., Any]] = {}


def _patch(func: Callable[..., Any]) -> Callable[..., Any]:
    """Put ``func`` in cpplint's namespace in place of its namesake, kept in ``_original``."""
    _original[func.__name__] = getattr(cpplint, func.__name__)
    setattr(cpplint, func.__name__, func)
    return func


def _suppressing(
    error: Error, categories: Iterable[str] = (), messages: Iterable[str] = ()
) -> Error:
    """``error`` without these categories and without messages matching these patterns."""
    categories, messages = list(categories), list(messages)

    def report(filename: str, linenum: int, category: str, confidence: int, message: str) -> None:
        if category in categories or any(re.match(m, message) for m in messages):
            return
        error(filename, linenum, category, confidence, message)

    return report


def GetHeaderGuardCPPVariable(filename: str) -> str:  # noqa: N802 (cpplint's name)
    """The guard of ROS style: the path from the package or ``include`` directory."""
    parts: list[str] = []
    head = filename
    while head:
        head, tail = os.path.split(head)
        parts.insert(0, tail)
        if (
            head.endswith("include")
            or os.path.exists(os.path.join(head, "package.xml"))
            or tail == ""
        ):
            break
    return re.sub(r"[-./\s]", "_", "_".join(parts)).upper()


def CheckBraces(filename: str, clean_lines: Any, linenum: int, error: Error) -> None:  # noqa: N802
    """ROS's brace rules in place of Google's: braces that open or close a scope stand alone."""
    line = clean_lines.elided[linenum]
    if re.match(r"^(.*){(.*)}.*$", line):
        return  # both on one line: a one-line body or an initialiser row
    m = re.match(r"^(.*){(.*)$", line)
    if m and not cpplint.IsBlankLine(m.group(1)):
        if not ("=" in line and re.match(r"\)( *){$", line)):
            error(
                filename,
                linenum,
                "whitespace/braces",
                4,
                "when starting a new scope, { should be on a line by itself",
            )
    m = re.match(r"^(.*)}(.*)$", line)
    if m and (not cpplint.IsBlankLine(m.group(1)) or not cpplint.IsBlankLine(m.group(2))):
        if m.group(2) != ";":
            error(filename, linenum, "whitespace/braces", 4, "} should be on a line by itself")


def CheckIncludeLine(
    filename: str,
    clean_lines: Any,
    linenum: int,
    include_state: Any,  # noqa: N802
    error: Error,
) -> None:
    _original["CheckIncludeLine"](
        filename,
        clean_lines,
        linenum,
        include_state,
        _suppressing(error, ["build/include_order", "build/include_alpha", "readability/streams"]),
    )


def CheckSpacing(
    filename: str,
    clean_lines: Any,
    linenum: int,
    nesting_state: Any,  # noqa: N802
    error: Error,
) -> None:
    _original["CheckSpacing"](
        filename,
        clean_lines,
        linenum,
        nesting_state,
        _suppressing(error, ["readability/braces", "whitespace/braces"]),
    )


def ProcessLine(
    filename: str,
    file_extension: str,
    clean_lines: Any,
    line: int,  # noqa: N802
    include_state: Any,
    function_state: Any,
    nesting_state: Any,
    error: Error,
    extra_check_functions: Any = None,
    cppvar: Any = None,
) -> None:
    _original["ProcessLine"](
        filename,
        file_extension,
        clean_lines,
        line,
        include_state,
        function_state,
        nesting_state,
        _suppressing(error, (), [r"(.*)should be indented \+1 space inside(.*)"]),
        [],
        cppvar,
    )


def CheckEmptyBlockBody(
    filename: str,
    clean_lines: Any,
    linenum: int,  # noqa: N802
    error: Error,
) -> None:
    """Empty loop and conditional bodies, but a ROS-style ``} while (x);`` is fine."""
    line = clean_lines.elided[linenum]
    matched = re.match(r"\s*(for|while|if)\s*\(", line)
    if not matched:
        return
    end_line, end_linenum, end_pos = cpplint.CloseExpression(clean_lines, linenum, line.find("("))
    if end_pos >= 0 and re.match(r";", end_line[end_pos:]):
        if matched.group(1) == "if":
            error(
                filename,
                end_linenum,
                "whitespace/empty_conditional_body",
                5,
                "Empty conditional bodies should use {}",
            )
        elif (
            matched.group(1) == "while" and linenum != 0 and "}" in clean_lines.elided[linenum - 1]
        ):
            return
        else:
            error(
                filename,
                end_linenum,
                "whitespace/empty_loop_body",
                5,
                "Empty loop bodies should use {} or continue",
            )


def install() -> None:
    """Apply roslint's patches to the imported cpplint (once)."""
    if _original:
        return
    for func in (
        GetHeaderGuardCPPVariable,
        CheckBraces,
        CheckIncludeLine,
        CheckSpacing,
        ProcessLine,
        CheckEmptyBlockBody,
    ):
        _patch(func)
    cpplint._line_length = 120  # type: ignore[attr-defined]


if __name__ == "__main__":
    install()
    # roslint's scripts/cpplint puts its filter first; a later --filter replaces it
    sys.argv.insert(1, "--filter=-runtime/references")
    cpplint.main()
