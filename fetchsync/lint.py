"""Lint ROS sources the way ROS's roslint does, for ``fetchsync lint``.

Three tools, each on what it understands:

- ``pycodestyle`` (in process) on Python files: ``.py`` and extensionless
  scripts with a python shebang; lines up to 120 characters (roslint's
  ``roslint_python``), pycodestyle's default ignores plus E266 (``##``
  Doxygen comments, as fetch_tools allowed).
- ``cpplint`` (a subprocess, ``python -m cpplint``) on C/C++ files with
  roslint's settings: lines up to 120 characters, the category filters of
  ``roslint_cpp`` and of roslint's cpplint wrapper (ROS's brace placement,
  include order, streams and access specifiers differ from Google's), and
  ROS's header guards (``PKG_PATH_FILE_H`` from the package or ``include/``
  directory), checked here in place of cpplint's own.
- ``catkin_lint`` (a subprocess, offline) on packages, with the workspace's
  ``src/`` as its package path, so a dependency on a sibling workspace package
  that ``package.xml`` does not declare is reported.

What is linted comes from one argument (:func:`resolve_targets`): an existing
file, a directory (walked with fetchsync's exclude rules; every package in it
is linted by catkin_lint too), or the name of a package found by its
``package.xml`` under the workspace's ``src/``. :func:`lint` runs the tools
and returns a :class:`LintReport`; findings are data, a missing tool or a bad
argument is a :class:`~fetchsync.errors.FetchsyncError`.
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
from fetchsync.errors import ConfigError, UsageError
from fetchsync.protocol.ignore import IgnoreRules, read_ignore_file

log = logging.getLogger(__name__)

PYCODESTYLE = "pycodestyle"
CPPLINT = "cpplint"
CATKIN_LINT = "catkin_lint"
TOOLS: tuple[str, ...] = (PYCODESTYLE, CPPLINT, CATKIN_LINT)

# The ROS style guides' line length (roslint_python, roslint's cpplint wrapper).
DEFAULT_MAX_LINE_LENGTH = 120

CPP_SUFFIXES = frozenset({".c", ".cc", ".cpp", ".cxx", ".h", ".hh", ".hpp", ".hxx"})
HEADER_SUFFIXES = frozenset({".h", ".hh", ".hpp", ".hxx"})

# pycodestyle's own defaults stay ignored; E266 lets `## ` Doxygen comments be.
PYCODESTYLE_EXTRA_IGNORE = ("E266",)

# roslint_cpp's default (-runtime/references), fetch_tools' (-runtime/threadsafe_fn),
# and what roslint's cpplint wrapper suppresses because ROS style differs from
# Google's: include order and streams are free, braces go on their own line.
# Header guards are checked by check_header_guard() with ROS's names instead.
CPPLINT_FILTERS = (
    "-runtime/references",
    "-runtime/threadsafe_fn",
    "-build/include_order",
    "-build/include_alpha",
    "-readability/streams",
    "-readability/braces",
    "-whitespace/braces",
    "-build/header_guard",
)
# Messages roslint drops by text: ROS puts access specifiers at the class's
# indentation and `else` on its own line after `}`.
CPPLINT_SUPPRESSED_MESSAGES = (
    re.compile(r".*should be indented \+1 space inside"),
    re.compile(r"An else should appear on the same line as the preceding \}"),
)

# Directories catkin (and colcon) skip: linting them would report packages
# that are never built.
SKIP_MARKERS = ("CATKIN_IGNORE", "COLCON_IGNORE")

_CPPLINT_LINE = re.compile(
    r"^(?P<path>.+?):(?P<line>\d+):  (?P<message>.*)  \[(?P<code>[^\]]+)\] \[\d\]$"
)
_PY_SHEBANG = re.compile(rb"^#!.*\bpython[0-9.]*\b")
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
    """The findings of every tool that was asked for, in a stable order."""

    tools: dict[str, ToolResult]

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
                    {"path": display_path(f.path, base), "line": f.line, "code": f.code,
                     "message": f.message}
                    for f in sorted(result.findings, key=Finding.sort_key)
                ],
            }
        return {"tools": tools, "total": self.total}

    def lines(self, *, base: Path | None = None) -> list[str]:
        """``path:line: [tool] code message`` per finding, then one summary line per tool."""
        out = []
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


def lint(target: str, *, workspace: str | os.PathLike[str] | None = None,
         tools: Iterable[str] = TOOLS, max_line_length: int = DEFAULT_MAX_LINE_LENGTH,
         environ: Mapping[str, str] = os.environ) -> LintReport:
    """Lint a file, a directory or a workspace package with the chosen tools."""
    wanted = set(tools)
    chosen = [t for t in TOOLS if t in wanted]
    unknown = wanted - set(TOOLS)
    if unknown:
        raise UsageError(f"unknown tool {min(unknown)!r}; choose from {', '.join(TOOLS)}")
    found = resolve_targets(target, workspace=workspace, environ=environ)
    results: dict[str, ToolResult] = {}
    for tool in chosen:
        if tool == PYCODESTYLE:
            results[tool] = run_pycodestyle(found.python_files, max_line_length=max_line_length)
        elif tool == CPPLINT:
            results[tool] = run_cpplint(found.cpp_files, max_line_length=max_line_length)
        else:
            results[tool] = run_catkin_lint(found.packages, search_path=found.search_path)
    return LintReport(results)


def resolve_targets(target: str, *, workspace: str | os.PathLike[str] | None = None,
                    environ: Mapping[str, str] = os.environ) -> Targets:
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
            raise UsageError(f"cannot lint {target}: not a Python or C/C++ file, nor a package.xml "
                             "or CMakeLists.txt of a package")
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
        raise UsageError(f"cannot lint {name}: no such file or directory, and no workspace "
                         f"sources at {src} to find a package by that name",
                         hint="pass --workspace DIR")
    packages = workspace_packages(src)
    dirs = packages.get(name)
    if not dirs:
        close = difflib.get_close_matches(name, sorted(packages), n=5, cutoff=0.6)
        hint = f"did you mean {', '.join(close)}?" if close else None
        raise UsageError(f"cannot lint {name}: no such file or directory, nor a package "
                         f"of that name in {src}", hint=hint)
    if len(dirs) > 1:
        raise UsageError(f"package {name} is defined twice: {', '.join(sorted(map(str, dirs)))}")
    return dirs[0]


def _workspace_src(target: str, workspace: str | os.PathLike[str] | None,
                   environ: Mapping[str, str]) -> Path:
    try:
        return resolve_workspace(workspace, environ=environ) / "src"
    except ConfigError as exc:
        raise ConfigError(f"{target} is not a file or directory, so it names a package, "
                          f"but {exc.message}", hint=exc.hint) from exc


def _search_path(path: Path, workspace: str | os.PathLike[str] | None,
                 environ: Mapping[str, str]) -> list[Path]:
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
    env = dict(os.environ)
    # Paths come back as we passed them, undecodable bytes included.
    env["PYTHONIOENCODING"] = "utf-8:surrogateescape"
    log.debug("running %s", " ".join(args[:6]))
    try:
        return subprocess.run(list(args), stdin=subprocess.DEVNULL, capture_output=True,
                              env=env, encoding="utf-8", errors="surrogateescape", check=False)
    except OSError as exc:
        raise ConfigError(f"cannot run {args[0]}: {exc}") from exc


def run_pycodestyle(files: Sequence[Path], *,
                    max_line_length: int = DEFAULT_MAX_LINE_LENGTH) -> ToolResult:
    """pycodestyle on ``files``, with roslint's line length."""
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
                findings.append(Finding(self.filename, line_number, PYCODESTYLE, code,
                                        text[5:].strip()))
            return code

    ignore = [*pycodestyle.DEFAULT_IGNORE.split(","), *PYCODESTYLE_EXTRA_IGNORE]
    guide = pycodestyle.StyleGuide(max_line_length=max_line_length, ignore=ignore,
                                   reporter=_Collect, quiet=True)
    for path in files:
        guide.input_file(str(path))
    return result


def run_cpplint(files: Sequence[Path], *,
                max_line_length: int = DEFAULT_MAX_LINE_LENGTH) -> ToolResult:
    """cpplint with roslint's filters on ``files``, plus ROS's header guard check."""
    result = ToolResult(checked=len(files))
    if not files:
        return result
    _require("cpplint", "cpplint")
    base = [sys.executable, "-m", "cpplint", "--output=emacs", "--quiet",
            f"--linelength={max_line_length}", "--filter=" + ",".join(CPPLINT_FILTERS)]
    chunks = [files[i:i + _CPPLINT_CHUNK] for i in range(0, len(files), _CPPLINT_CHUNK)]
    workers = max(1, min(len(chunks), os.cpu_count() or 1, 8))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        procs = list(pool.map(lambda chunk: _run(base + [str(p) for p in chunk]), chunks))
    for proc in procs:
        result.findings.extend(parse_cpplint(proc.stderr))
    for path in files:
        if path.suffix.lower() in HEADER_SUFFIXES:
            result.findings.extend(check_header_guard(path))
    return result


def parse_cpplint(output: str) -> list[Finding]:
    """cpplint's emacs-style lines as findings, without the messages ROS style allows."""
    out = []
    for line in output.splitlines():
        m = _CPPLINT_LINE.match(line)
        if m is None:
            if line.strip():
                log.debug("cpplint: %s", line)
            continue
        message = m.group("message")
        if any(rx.match(message) for rx in CPPLINT_SUPPRESSED_MESSAGES):
            continue
        out.append(Finding(m.group("path"), int(m.group("line")) or None, CPPLINT,
                           m.group("code"), message))
    return out


def ros_header_guard(path: Path) -> str:
    """The guard ROS style asks for: the path from the package or ``include/`` dir, upper-cased.

    ``pkg/include/pkg/thing.h`` -> ``PKG_THING_H``; ``pkg/src/util.h`` -> ``SRC_UTIL_H``.
    A header outside any package is named by its file name.
    """
    parts = [path.name]
    for parent in path.parents:
        if parent.name == "include" or (parent / "package.xml").is_file():
            break
        if not parent.name:
            parts = [path.name]
            break
        parts.insert(0, parent.name)
    return re.sub(r"[-./\s]", "_", "_".join(parts)).upper()


def check_header_guard(path: Path) -> list[Finding]:
    """ROS-style header guard findings for one header (``#pragma once`` is fine too)."""
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        return [Finding(str(path), None, CPPLINT, "build/header_guard", f"cannot read: {exc}")]
    if any(re.search(r"//\s*NOLINT\(build/header_guard\)", ln) for ln in lines):
        return []
    if any(re.match(r"\s*#\s*pragma\s+once\b", ln) for ln in lines):
        return []
    expected = ros_header_guard(path)
    ifndef = define = None
    ifndef_line = endif_line = 0
    for number, ln in enumerate(lines, 1):
        words = ln.split()
        if len(words) >= 2 and ifndef is None and words[0] == "#ifndef":
            ifndef, ifndef_line = words[1], number
        if len(words) >= 2 and define is None and words[0] == "#define":
            define = words[1]
        if ln.startswith("#endif"):
            endif_line = number
    code = "build/header_guard"
    if ifndef is None or ifndef != define:
        return [Finding(str(path), 1, CPPLINT, code,
                        f"No #ifndef header guard found, suggested CPP variable is: {expected}")]
    out = []
    if ifndef not in (expected, expected + "_"):
        out.append(Finding(str(path), ifndef_line, CPPLINT, code,
                           f"#ifndef header guard has wrong style, please use: {expected}"))
    endif = lines[endif_line - 1] if endif_line else ""
    if not re.match(r"#endif\s*(//|/\*)\s*" + re.escape(ifndef) + r"\b", endif):
        out.append(Finding(str(path), endif_line or len(lines), CPPLINT, code,
                           f'#endif line should be "#endif  // {ifndef}"'))
    return out


def run_catkin_lint(packages: Mapping[Path, str], *,
                    search_path: Sequence[Path] = ()) -> ToolResult:
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
        why = next((ln for ln in reversed(proc.stderr.splitlines()) if ln.strip()),
                   f"exit status {proc.returncode}")
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
            result.findings.append(Finding(where, int(line) if line else None, CATKIN_LINT,
                                           str(entry.get("id", "")), str(entry.get("text", ""))))
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
    "CATKIN_LINT",
    "CPPLINT",
    "DEFAULT_MAX_LINE_LENGTH",
    "PYCODESTYLE",
    "TOOLS",
    "Finding",
    "LintReport",
    "Targets",
    "ToolResult",
    "check_header_guard",
    "classify",
    "enclosing_src",
    "find_package",
    "lint",
    "parse_cpplint",
    "resolve_targets",
    "ros_header_guard",
    "run_catkin_lint",
    "run_cpplint",
    "run_pycodestyle",
    "workspace_packages",
]
