"""Lint ROS sources the way ROS's own tools do, for ``fetchsync lint``.

Two styles, chosen per package (``--style auto``) from its package.xml:

- ``roslint``, fetch_tools' rules exactly, for catkin (ROS 1) packages and
  files outside any package: ``pycodestyle`` (in process; pep8 at its 79
  columns, ignoring only E266 as fetch_tools' ``--ignore`` did, which also
  dropped pep8's default ignores; W504, which pep8 did not have and which
  contradicts W503, is off); ``cpplint`` through roslint's wrapper
  (:mod:`fetchsync.chores.roslint_cpplint`: ROS's braces, header guards, 120
  columns) with fetch_tools' ``--filter=+,-runtime/references,-runtime/
  threadsafe_fn``; ``catkin_lint -W2`` (offline) on the packages, with the
  workspace's ``src/`` as its package path.
- ``ament``, for ROS 2 packages (package.xml format 3 without catkin, or an
  ``ament_*``/``cmake`` build type), what ``ament_lint_common`` runs:
  ``ament_cpplint`` and ``ament_pep257`` (the ament packages of PyPI), and
  ``flake8`` with ament_flake8's settings (99 columns, its ignore list):
  ament_flake8 itself does not run with the flake8 this project needs, so
  flake8 runs with its configuration, and the output's first line says so.
  Never catkin_lint.

What is linted comes from one argument (:func:`resolve_targets`): an existing
file, a directory (walked with fetchsync's exclude rules), or the name of a
package found by its ``package.xml`` under the workspace's ``src/``.
:func:`lint` runs the tools and returns a :class:`LintReport`; findings are
data, a missing tool or a bad argument is a :class:`~fetchsync.errors.FetchsyncError`.
"""

from __future__ import annotations

import difflib
import importlib.util
import json
import logging
import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fetchsync.config import resolve_workspace
from fetchsync.environ import inheritable
from fetchsync.errors import ConfigError, UsageError
from fetchsync.protocol.ignore import IgnoreRules, read_ignore_file

log = logging.getLogger(__name__)

PYCODESTYLE = "pycodestyle"
CPPLINT = "cpplint"
CATKIN_LINT = "catkin_lint"
FLAKE8 = "flake8"
AMENT_PEP257 = "ament_pep257"
AMENT_CPPLINT = "ament_cpplint"
ROSLINT_TOOLS: tuple[str, ...] = (PYCODESTYLE, CPPLINT, CATKIN_LINT)
AMENT_TOOLS: tuple[str, ...] = (FLAKE8, AMENT_PEP257, AMENT_CPPLINT)
TOOLS: tuple[str, ...] = ROSLINT_TOOLS + AMENT_TOOLS

AUTO, ROSLINT, AMENT = "auto", "roslint", "ament"
STYLES: tuple[str, ...] = (AUTO, ROSLINT, AMENT)
STYLE_TOOLS = {ROSLINT: ROSLINT_TOOLS, AMENT: AMENT_TOOLS}
STYLE_NOTES = {
    ROSLINT: "fetch_tools' rules: pep8 at 79 columns, roslint's cpplint, catkin_lint -W2",
    AMENT: "ament_lint_common's rules: ament_cpplint, ament_pep257, and flake8 with "
    "ament_flake8's settings (ament_flake8 itself needs an older flake8)",
}

# Lines: pep8's default (fetch_tools passed none), roslint's cpplint wrapper,
# ament_flake8's configuration, ament_cpplint's default.
PEP8_MAX_LINE_LENGTH = 79
ROSLINT_CPP_MAX_LINE_LENGTH = 120
AMENT_FLAKE8_MAX_LINE_LENGTH = 99
AMENT_CPPLINT_MAX_LINE_LENGTH = 100
DEFAULT_MAX_LINE_LENGTH = PEP8_MAX_LINE_LENGTH  # the default style's Python limit

CPP_SUFFIXES = frozenset({".c", ".cc", ".cpp", ".cxx", ".h", ".hh", ".hpp", ".hxx"})

# fetch_tools' --ignore list: its pylint codes mean nothing to pep8, so E266
# (`## ` Doxygen comments) is what it ignored, and pep8's own default ignores
# were dropped with it. W504 did not exist in pep8 and contradicts W503.
PYCODESTYLE_IGNORE = ("E266", "W504")

# fetch_tools' cpplint filter, after roslint's own (-runtime/references)
CPPLINT_FILTER = "+,-runtime/references,-runtime/threadsafe_fn"

# ament_flake8's configuration (ament_flake8/configuration/ament_flake8.ini)
AMENT_FLAKE8_IGNORE = (
    "B902",
    "C816",
    "D100",
    "D101",
    "D102",
    "D103",
    "D104",
    "D105",
    "D106",
    "D107",
    "D203",
    "D212",
    "D404",
    "I202",
)
# ament_cpplint's filters, used when ament_cpplint itself is not installed
AMENT_CPPLINT_FILTERS = (
    "-build/c++11",
    "-runtime/references",
    "-whitespace/braces",
    "-whitespace/indent",
    "-whitespace/parens",
    "-whitespace/semicolon",
)

# Directories catkin (and colcon) skip: linting them would report packages
# that are never built.
SKIP_MARKERS = ("CATKIN_IGNORE", "COLCON_IGNORE")

_CPPLINT_LINE = re.compile(
    r"^(?P<path>.+?):(?P<line>\d+):  (?P<message>.*)  \[(?P<code>[^\]]+)\] \[\d\]$"
)
_PY_SHEBANG = re.compile(rb"^#!.*\bpython[0-9.]*\b")
_FLAKE8_LINE = re.compile(
    r"^(?P<path>.+?):(?P<line>\d+):(?P<col>\d+): (?P<code>[A-Z]+\d+) (?P<message>.*)$"
)
_PEP257_LINE = re.compile(r"^(?P<path>.+?):(?P<line>\d+) .*?: (?P<code>D\d+): (?P<message>.*)$")
_CPPLINT_CHUNK = 50


@dataclass(frozen=True)
class Finding:
    """One problem a tool found. ``path`` is absolute; ``line`` is None for a whole file."""

    path: str
    line: int | None
    tool: str
    code: str
    message: str

    def sort_key(self) -> tuple[str, int, str, str, str]:
        return (self.path, self.line or 0, self.tool, self.code, self.message)


@dataclass
class ToolResult:
    """What one tool checked (files; packages for catkin_lint) and found."""

    checked: int = 0
    findings: list[Finding] = field(default_factory=list)


@dataclass
class Targets:
    """What to lint: files per tool, package directories, and catkin_lint's package path."""

    python_files: list[Path] = field(default_factory=list)
    cpp_files: list[Path] = field(default_factory=list)
    packages: dict[Path, str] = field(default_factory=dict)  # directory -> name
    search_path: list[Path] = field(default_factory=list)


@dataclass
class LintReport:
    """The findings of every tool that was asked for, in a stable order, and the styles used
    (style -> the packages linted with it; ``(files)`` for files outside any package)."""

    tools: dict[str, ToolResult]
    styles: dict[str, list[str]] = field(default_factory=dict)

    def style_line(self) -> str:
        """The output's first line: which rules were applied, to what."""
        if not self.styles:
            return "lint: nothing to lint"
        if len(self.styles) == 1:
            style = next(iter(self.styles))
            return f"lint: style {style} ({STYLE_NOTES[style]})"
        parts = [f"{style} for {', '.join(names)}" for style, names in self.styles.items()]
        return (
            "lint: style "
            + "; ".join(parts)
            + " ("
            + "; ".join(f"{style}: {STYLE_NOTES[style]}" for style in self.styles)
            + ")"
        )

    @property
    def total(self) -> int:
        return sum(len(r.findings) for r in self.tools.values())

    def findings(self) -> list[Finding]:
        return sorted((f for r in self.tools.values() for f in r.findings), key=Finding.sort_key)

    def to_json(self, *, base: Path | None = None) -> dict[str, Any]:
        """``{tools: {name: {files, findings: [{path, line, code, message}]}}, total}``."""
        tools: dict[str, Any] = {}
        for name, result in self.tools.items():
            tools[name] = {
                "files": result.checked,
                "findings": [
                    {
                        "path": display_path(f.path, base),
                        "line": f.line,
                        "code": f.code,
                        "message": f.message,
                    }
                    for f in sorted(result.findings, key=Finding.sort_key)
                ],
            }
        return {"tools": tools, "total": self.total, "styles": self.styles}

    def lines(self, *, base: Path | None = None) -> list[str]:
        """``path:line: [tool] code message`` per finding, then one summary line per tool."""
        out = [self.style_line()]
        for f in self.findings():
            where = display_path(f.path, base) + (f":{f.line}" if f.line is not None else "")
            out.append(f"{where}: [{f.tool}] {f.code} {f.message}")
        for name, result in self.tools.items():
            out.append(summary_line(name, result))
        return out


def summary_line(tool: str, result: ToolResult) -> str:
    """``pycodestyle: 3 findings in 2 files (5 checked)``, or what was clean."""
    unit = "package" if tool == CATKIN_LINT else "file"
    if not result.checked:
        return f"{tool}: no {unit}s to check"
    checked = _count(result.checked, unit)
    if not result.findings:
        return f"{tool}: no findings ({checked} checked)"
    where = _count(len({f.path for f in result.findings}), "file")
    return f"{tool}: {_count(len(result.findings), 'finding')} in {where} ({checked} checked)"


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def display_path(path: str, base: Path | None) -> str:
    """``path`` relative to ``base`` when it lies below it, else as it is."""
    if base is None:
        return path
    try:
        return str(Path(path).relative_to(base))
    except ValueError:
        return path


# --------------------------------------------------------------------------- what to lint


def lint(
    target: str,
    *,
    workspace: str | os.PathLike[str] | None = None,
    tools: Iterable[str] | None = None,
    max_line_length: int | None = None,
    style: str = AUTO,
    environ: Mapping[str, str] = os.environ,
) -> LintReport:
    """Lint a file, a directory or a workspace package with the style of each package.

    ``style`` ``auto`` picks per package (:func:`package_style`); ``tools``
    keeps only those tools; ``max_line_length`` overrides every tool's limit.
    """
    if style not in STYLES:
        raise UsageError(f"unknown style {style!r}; choose from {', '.join(STYLES)}")
    wanted = set(TOOLS if tools is None else tools)
    unknown = wanted - set(TOOLS)
    if unknown:
        raise UsageError(f"unknown tool {min(unknown)!r}; choose from {', '.join(TOOLS)}")
    found = resolve_targets(target, workspace=workspace, environ=environ)
    parts = split_by_style(found, style)
    results: dict[str, ToolResult] = {}
    styles: dict[str, list[str]] = {}
    for name, part in parts.items():
        chosen = [t for t in STYLE_TOOLS[name] if t in wanted]
        if not chosen:
            continue
        styles[name] = sorted(set(part.packages.values()))
        if any(_package_of(p) is None for p in part.python_files + part.cpp_files):
            styles[name].append("files outside packages")
        for tool in chosen:
            results[tool] = _run_tool(tool, part, max_line_length)
    if not results:
        # nothing of the chosen tools' style was found: say so per tool
        for tool in [
            t
            for t in TOOLS
            if t in wanted and t in STYLE_TOOLS[AMENT if style == AMENT else ROSLINT]
        ]:
            results[tool] = ToolResult()
    return LintReport(results, styles)


def _run_tool(tool: str, part: Targets, max_line_length: int | None) -> ToolResult:
    if tool == PYCODESTYLE:
        return run_pycodestyle(
            part.python_files, max_line_length=max_line_length or PEP8_MAX_LINE_LENGTH
        )
    if tool == CPPLINT:
        return run_cpplint(
            part.cpp_files, max_line_length=max_line_length or ROSLINT_CPP_MAX_LINE_LENGTH
        )
    if tool == CATKIN_LINT:
        return run_catkin_lint(part.packages, search_path=part.search_path)
    if tool == FLAKE8:
        return run_flake8(
            part.python_files, max_line_length=max_line_length or AMENT_FLAKE8_MAX_LINE_LENGTH
        )
    if tool == AMENT_PEP257:
        return run_pep257(part.python_files)
    return run_ament_cpplint(
        part.cpp_files, max_line_length=max_line_length or AMENT_CPPLINT_MAX_LINE_LENGTH
    )


def package_style(manifest_text: str) -> str:
    """``ament`` for a ROS 2 package (what colcon alone builds), else ``roslint``."""
    from fetchsync.chores.build import ros2_reason

    return AMENT if ros2_reason(manifest_text) is not None else ROSLINT


def _package_of(path: Path) -> Path | None:
    """The package directory holding ``path``: the nearest ancestor with a package.xml."""
    for parent in path.parents:
        if (parent / "package.xml").is_file():
            return parent
    return None


def split_by_style(found: Targets, style: str) -> dict[str, Targets]:
    """``found`` split by the style of the package each file and package belongs to (files
    outside any package: roslint, fetch_tools' default); ``style`` other than auto: all of it."""
    if style != AUTO:
        return {style: found}
    cache: dict[Path | None, str] = {None: ROSLINT}

    def style_of(pkg: Path | None) -> str:
        if pkg not in cache:
            assert pkg is not None
            try:
                text = (pkg / "package.xml").read_text(encoding="utf-8", errors="replace")
            except OSError:
                text = ""
            cache[pkg] = package_style(text)
        return cache[pkg]

    parts: dict[str, Targets] = {}

    def part(name: str) -> Targets:
        if name not in parts:
            parts[name] = Targets(search_path=list(found.search_path))
        return parts[name]

    for pkg, name in found.packages.items():
        part(style_of(pkg)).packages[pkg] = name
    for path in found.python_files:
        part(style_of(_package_of(path))).python_files.append(path)
    for path in found.cpp_files:
        part(style_of(_package_of(path))).cpp_files.append(path)
    return dict(sorted(parts.items(), key=lambda kv: list(STYLE_TOOLS).index(kv[0])))


def resolve_targets(
    target: str,
    *,
    workspace: str | os.PathLike[str] | None = None,
    environ: Mapping[str, str] = os.environ,
) -> Targets:
    """What ``target`` (a file, a directory or a package name) asks to lint."""
    path = Path(target)
    found = Targets()
    if path.is_file():
        path = path.resolve()
        kind = classify(path)
        package = _package_of_manifest(path)
        if package is not None:
            found.packages[package] = _package_name(package / "package.xml") or package.name
        elif kind == PYCODESTYLE:
            found.python_files.append(path)
        elif kind == CPPLINT:
            found.cpp_files.append(path)
        else:
            raise UsageError(
                f"cannot lint {target}: not a Python or C/C++ file, nor a package.xml "
                "or CMakeLists.txt of a package"
            )
    elif path.is_dir():
        path = path.resolve()
        _collect(path, found)
    elif path.exists():
        raise UsageError(f"cannot lint {target}: not a regular file or a directory")
    elif "/" in target or os.sep in target:
        raise UsageError(f"cannot lint {target}: no such file or directory")
    else:
        src = _workspace_src(target, workspace, environ)
        path = find_package(target, src)
        _collect(path, found)
    found.search_path = _search_path(path, workspace, environ)
    return found


def classify(path: Path) -> str | None:
    """The tool for a file: by its suffix, or by a python shebang when it has none."""
    suffix = path.suffix.lower()
    if suffix == ".py":
        return PYCODESTYLE
    if suffix in CPP_SUFFIXES:
        return CPPLINT
    if suffix:
        return None
    try:
        with open(path, "rb") as f:
            first = f.readline(256)
    except OSError:
        return None
    return PYCODESTYLE if _PY_SHEBANG.match(first) else None


def _collect(root: Path, found: Targets) -> None:
    """Every lintable file and package under ``root``, with fetchsync's exclude rules."""
    rules = IgnoreRules.build()
    top = _ignore_file(root, "")
    if top is not None:
        rules = rules.with_file("", top)
    stack: list[tuple[str, IgnoreRules]] = [("", rules)]
    while stack:
        rel, rules = stack.pop()
        here = root / rel if rel else root
        try:
            entries = sorted(os.scandir(here), key=lambda e: e.name)
        except OSError as exc:
            log.warning("cannot read %s: %s", here, exc)
            continue
        names = {e.name for e in entries}
        if rel and any(m in names for m in SKIP_MARKERS):
            log.debug("skipping %s: it holds a %s marker", here, "/".join(SKIP_MARKERS))
            continue
        if "package.xml" in names:
            found.packages[here] = _package_name(here / "package.xml") or here.name
        for entry in entries:
            child = f"{rel}/{entry.name}" if rel else entry.name
            if entry.is_symlink():
                continue  # a link may lead out of the tree or lint a file twice
            is_dir = entry.is_dir(follow_symlinks=False)
            if rules.ignored(child, is_dir):
                continue
            if is_dir:
                text = _ignore_file(root, child)
                stack.append((child, rules if text is None else rules.with_file(child, text)))
                continue
            kind = classify(Path(entry.path))
            if kind == PYCODESTYLE:
                found.python_files.append(Path(entry.path))
            elif kind == CPPLINT:
                found.cpp_files.append(Path(entry.path))
    found.python_files.sort()
    found.cpp_files.sort()


def _ignore_file(root: Path, rel: str) -> str | None:
    try:
        return read_ignore_file(str(root), rel)
    except (OSError, ValueError) as exc:
        log.warning("ignoring %s/.fetchsyncignore: %s", root / rel if rel else root, exc)
        return None


def _package_of_manifest(path: Path) -> Path | None:
    """The package directory when ``path`` is its package.xml or top CMakeLists.txt."""
    if path.name in ("package.xml", "CMakeLists.txt") and (path.parent / "package.xml").is_file():
        return path.parent
    return None


def _package_name(manifest: Path) -> str | None:
    """The ``<name>`` of a package.xml, or None when it cannot be read."""
    try:
        root = ET.parse(manifest).getroot()
    except (OSError, ET.ParseError) as exc:
        log.debug("cannot read %s: %s", manifest, exc)
        return None
    name = (root.findtext("name") or "").strip() if root.tag == "package" else ""
    return name or None


def workspace_packages(src: Path) -> dict[str, list[Path]]:
    """Package name -> directories, for every package.xml under ``src`` that catkin would see."""
    out: dict[str, list[Path]] = {}
    rules = IgnoreRules.build()
    stack: list[Path] = [src]
    while stack:
        here = stack.pop()
        try:
            entries = list(os.scandir(here))
        except OSError as exc:
            log.debug("cannot read %s: %s", here, exc)
            continue
        names = {e.name for e in entries}
        if here != src and any(m in names for m in SKIP_MARKERS):
            continue
        if "package.xml" in names:
            name = _package_name(here / "package.xml")
            if name is not None:
                out.setdefault(name, []).append(here)
            continue  # catkin does not look for packages inside a package
        for entry in entries:
            if entry.is_dir(follow_symlinks=False) and not rules.ignored(entry.name, True):
                stack.append(Path(entry.path))
    return out


def find_package(name: str, src: Path) -> Path:
    """The directory of the package called ``name`` under ``src``; UsageError if none or several."""
    if not src.is_dir():
        raise UsageError(
            f"cannot lint {name}: no such file or directory, and no workspace "
            f"sources at {src} to find a package by that name",
            hint="pass --workspace DIR",
        )
    packages = workspace_packages(src)
    dirs = packages.get(name)
    if not dirs:
        close = difflib.get_close_matches(name, sorted(packages), n=5, cutoff=0.6)
        hint = f"did you mean {', '.join(close)}?" if close else None
        raise UsageError(
            f"cannot lint {name}: no such file or directory, nor a package of that name in {src}",
            hint=hint,
        )
    if len(dirs) > 1:
        raise UsageError(f"package {name} is defined twice: {', '.join(sorted(map(str, dirs)))}")
    return dirs[0]


def _workspace_src(
    target: str, workspace: str | os.PathLike[str] | None, environ: Mapping[str, str]
) -> Path:
    try:
        return resolve_workspace(workspace, environ=environ) / "src"
    except ConfigError as exc:
        raise ConfigError(
            f"{target} is not a file or directory, so it names a package, but {exc.message}",
            hint=exc.hint,
        ) from exc


def _search_path(
    path: Path, workspace: str | os.PathLike[str] | None, environ: Mapping[str, str]
) -> list[Path]:
    """Where catkin_lint finds the other packages: the enclosing ``src/`` and the workspace's."""
    found: list[Path] = []
    enclosing = enclosing_src(path)
    if enclosing is not None:
        found.append(enclosing)
    if workspace is not None or enclosing is None:
        try:
            src = resolve_workspace(workspace, environ=environ) / "src"
        except ConfigError:
            src = None
        if src is not None and src.is_dir() and src not in found:
            found.append(src)
    return found


def enclosing_src(path: Path) -> Path | None:
    """The workspace ``src/`` holding ``path``: the nearest ancestor named src outside a package."""
    for parent in [path, *path.parents]:
        if parent.name == "src" and not (parent.parent / "package.xml").is_file():
            return parent
    return None


# --------------------------------------------------------------------------- the tools


def _require(module: str, package: str) -> None:
    if importlib.util.find_spec(module) is None:
        raise ConfigError(f"{package} is not installed", hint=f"pip install {package}")


def _run(args: Sequence[str]) -> subprocess.CompletedProcess[str]:
    env = inheritable(os.environ)  # no password of the call's (fetchsync.environ)
    # Paths come back as we passed them, undecodable bytes included.
    env["PYTHONIOENCODING"] = "utf-8:surrogateescape"
    log.debug("running %s", " ".join(args[:6]))
    try:
        return subprocess.run(
            list(args),
            stdin=subprocess.DEVNULL,
            capture_output=True,
            env=env,
            encoding="utf-8",
            errors="surrogateescape",
            check=False,
        )
    except OSError as exc:
        raise ConfigError(f"cannot run {args[0]}: {exc}") from exc


def run_pycodestyle(
    files: Sequence[Path], *, max_line_length: int = PEP8_MAX_LINE_LENGTH
) -> ToolResult:
    """pycodestyle on ``files`` as fetch_tools ran pep8 (see :data:`PYCODESTYLE_IGNORE`)."""
    result = ToolResult(checked=len(files))
    if not files:
        return result
    _require("pycodestyle", "pycodestyle")
    import pycodestyle

    findings = result.findings

    class _Collect(pycodestyle.BaseReport):
        def error(self, line_number: int, offset: int, text: str, check: Any) -> str | None:
            code: str | None = super().error(line_number, offset, text, check)
            if code:
                findings.append(
                    Finding(self.filename, line_number, PYCODESTYLE, code, text[5:].strip())
                )
            return code

    guide = pycodestyle.StyleGuide(
        max_line_length=max_line_length,
        ignore=list(PYCODESTYLE_IGNORE),
        reporter=_Collect,
        quiet=True,
    )
    for path in files:
        guide.input_file(str(path))
    return result


def _in_chunks(
    base: Sequence[str], files: Sequence[Path]
) -> list[subprocess.CompletedProcess[str]]:
    """``base + chunk`` for chunks of ``files``, a few at a time."""
    chunks = [files[i : i + _CPPLINT_CHUNK] for i in range(0, len(files), _CPPLINT_CHUNK)]
    workers = max(1, min(len(chunks), os.cpu_count() or 1, 8))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(lambda chunk: _run([*base, *(str(p) for p in chunk)]), chunks))


def run_cpplint(
    files: Sequence[Path], *, max_line_length: int = ROSLINT_CPP_MAX_LINE_LENGTH
) -> ToolResult:
    """roslint's cpplint (:mod:`fetchsync.chores.roslint_cpplint`) with fetch_tools' filter."""
    result = ToolResult(checked=len(files))
    if not files:
        return result
    _require("cpplint", "cpplint")
    base = [
        sys.executable,
        "-m",
        "fetchsync.chores.roslint_cpplint",
        "--output=emacs",
        "--quiet",
        f"--linelength={max_line_length}",
        f"--filter={CPPLINT_FILTER}",
    ]
    for proc in _in_chunks(base, files):
        result.findings.extend(parse_cpplint(proc.stderr, tool=CPPLINT))
    return result


def run_ament_cpplint(
    files: Sequence[Path], *, max_line_length: int = AMENT_CPPLINT_MAX_LINE_LENGTH
) -> ToolResult:
    """ament_cpplint on ``files``; cpplint with its filters where it is not installed."""
    result = ToolResult(checked=len(files))
    if not files:
        return result
    if importlib.util.find_spec("ament_cpplint") is not None:
        base = [
            sys.executable,
            "-m",
            "ament_cpplint.main",
            "--output=emacs",
            f"--linelength={max_line_length}",
        ]
    else:
        _require("cpplint", "cpplint")
        log.info("ament_cpplint is not installed: cpplint with its filters")
        base = [
            sys.executable,
            "-m",
            "cpplint",
            "--output=emacs",
            "--quiet",
            f"--linelength={max_line_length}",
            "--filter=" + ",".join(AMENT_CPPLINT_FILTERS),
        ]
    for proc in _in_chunks(base, files):
        result.findings.extend(parse_cpplint(proc.stderr, tool=AMENT_CPPLINT))
    return result


def run_flake8(
    files: Sequence[Path], *, max_line_length: int = AMENT_FLAKE8_MAX_LINE_LENGTH
) -> ToolResult:
    """flake8 with ament_flake8's settings; its plugins (docstrings, import order, quotes)
    check too where installed."""
    result = ToolResult(checked=len(files))
    if not files:
        return result
    _require("flake8", "flake8")
    base = [
        sys.executable,
        "-m",
        "flake8",
        "--isolated",
        f"--max-line-length={max_line_length}",
        "--extend-ignore=" + ",".join(AMENT_FLAKE8_IGNORE),
        "--format=%(path)s:%(row)d:%(col)d: %(code)s %(text)s",
    ]
    for proc in _in_chunks(base, files):
        for line in proc.stdout.splitlines():
            m = _FLAKE8_LINE.match(line)
            if m is None:
                if line.strip():
                    log.debug("flake8: %s", line)
                continue
            result.findings.append(
                Finding(
                    m.group("path"),
                    int(m.group("line")),
                    FLAKE8,
                    m.group("code"),
                    m.group("message"),
                )
            )
        if proc.returncode not in (0, 1):
            why = next(
                (ln for ln in reversed(proc.stderr.splitlines()) if ln.strip()),
                f"exit status {proc.returncode}",
            )
            result.findings.append(Finding(str(files[0]), None, FLAKE8, "failed", why.strip()))
    return result


def run_pep257(files: Sequence[Path]) -> ToolResult:
    """ament_pep257 (pydocstyle with ament's conventions) on ``files``."""
    result = ToolResult(checked=len(files))
    if not files:
        return result
    _require("ament_pep257", "ament-lint-pep257")
    for proc in _in_chunks([sys.executable, "-m", "ament_pep257.main"], files):
        for line in proc.stderr.splitlines():
            m = _PEP257_LINE.match(line)
            if m is None:
                if line.strip():
                    log.debug("ament_pep257: %s", line)
                continue
            result.findings.append(
                Finding(
                    m.group("path"),
                    int(m.group("line")),
                    AMENT_PEP257,
                    m.group("code"),
                    m.group("message"),
                )
            )
    return result


def parse_cpplint(output: str, *, tool: str = CPPLINT) -> list[Finding]:
    """cpplint's emacs-style lines as findings."""
    out = []
    for line in output.splitlines():
        m = _CPPLINT_LINE.match(line)
        if m is None:
            if line.strip():
                log.debug("%s: %s", tool, line)
            continue
        out.append(
            Finding(
                m.group("path"),
                int(m.group("line")) or None,
                tool,
                m.group("code"),
                m.group("message"),
            )
        )
    return out


def run_catkin_lint(
    packages: Mapping[Path, str], *, search_path: Sequence[Path] = ()
) -> ToolResult:
    """catkin_lint on ``packages`` (offline), finding the others in ``search_path``."""
    result = ToolResult(checked=len(packages))
    if not packages:
        return result
    _require("catkin_lint", "catkin-lint")
    args = [sys.executable, "-m", "catkin_lint", "--offline", "--json", "-W2"]
    if search_path:
        args += ["--package-path", os.pathsep.join(str(p) for p in search_path)]
    args += [str(p) for p in sorted(packages)]
    proc = _run(args)
    for line in proc.stderr.splitlines():
        log.debug("catkin_lint: %s", line)
    report = _last_json(proc.stdout)
    first = str(min(packages))
    if report is None:
        why = next(
            (ln for ln in reversed(proc.stderr.splitlines()) if ln.strip()),
            f"exit status {proc.returncode}",
        )
        result.findings.append(Finding(first, None, CATKIN_LINT, "failed", why.strip()))
        return result
    dirs = {name: path for path, name in packages.items()}
    for level in ("errors", "warnings", "notices"):
        for entry in report.get(level, []):
            location = entry.get("location", {})
            package_dir = dirs.get(location.get("package", ""))
            where = str(package_dir) if package_dir is not None else first
            if location.get("file"):
                where = os.path.join(where, location["file"])
            line = location.get("line")
            result.findings.append(
                Finding(
                    where,
                    int(line) if line else None,
                    CATKIN_LINT,
                    str(entry.get("id", "")),
                    str(entry.get("text", "")),
                )
            )
    return result


def _last_json(text: str) -> dict[str, Any] | None:
    for line in reversed(text.splitlines()):
        if line.startswith("{"):
            try:
                value = json.loads(line)
            except ValueError:
                return None
            return value if isinstance(value, dict) else None
    return None


__all__ = [
    "AMENT",
    "AMENT_CPPLINT",
    "AMENT_PEP257",
    "CATKIN_LINT",
    "CPPLINT",
    "DEFAULT_MAX_LINE_LENGTH",
    "FLAKE8",
    "PYCODESTYLE",
    "ROSLINT",
    "STYLES",
    "TOOLS",
    "Finding",
    "LintReport",
    "Targets",
    "ToolResult",
    "classify",
    "enclosing_src",
    "find_package",
    "lint",
    "package_style",
    "parse_cpplint",
    "resolve_targets",
    "run_catkin_lint",
    "run_cpplint",
    "run_ament_cpplint",
    "run_flake8",
    "run_pep257",
    "run_pycodestyle",
    "split_by_style",
    "workspace_packages",
]
