"""The package's rooms and their order (docs/design.md, "Where the code is").

A module imports only from its own package or the packages before it in
``ORDER``; the robot's programs import nothing of fetchsync (they are sent as
source); and no two modules import each other, directly or around a circle.
Imports under ``if TYPE_CHECKING:`` are annotations, not dependencies.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "fetchsync"

ORDER = ["protocol", "base", "link", "sync", "chores", "agent", "cli"]
"""Bottom to top. ``base`` is the package's own modules: errors, config, robots, console."""


def _module(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _room(module: str) -> str:
    parts = module.split(".")
    if len(parts) > 2 or (len(parts) == 2 and (PACKAGE / parts[1]).is_dir()):
        return parts[1]
    return "cli" if module.endswith("__main__") else "base"


def _type_checking_only(tree: ast.AST) -> set[int]:
    """The ids of the import nodes inside ``if TYPE_CHECKING:`` blocks."""
    ids: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            ids.update(id(n) for n in ast.walk(node) if isinstance(n, (ast.Import, ast.ImportFrom)))
    return ids


def _imports() -> dict[str, set[str]]:
    """module -> the fetchsync modules it imports (at any depth of its code)."""
    graph: dict[str, set[str]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        module = _module(path)
        tree = ast.parse(path.read_text(encoding="utf-8"))
        skip = _type_checking_only(tree)
        found: set[str] = set()
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            if isinstance(node, ast.Import):
                found.update(a.name for a in node.names if a.name.split(".")[0] == "fetchsync")
            elif (
                isinstance(node, ast.ImportFrom)
                and node.level == 0
                and node.module
                and node.module.split(".")[0] == "fetchsync"
            ):
                for alias in node.names:
                    sub = f"{node.module}.{alias.name}"
                    as_path = PACKAGE.parent / sub.replace(".", "/")
                    is_module = as_path.with_suffix(".py").is_file() or as_path.is_dir()
                    found.add(sub if is_module else node.module)
        found.discard(module)
        found.discard("fetchsync")  # the package's __init__: only its version
        graph[module] = found
    return graph


def upward_edges(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    return sorted(
        (a, b)
        for a, targets in graph.items()
        for b in targets
        if ORDER.index(_room(b)) > ORDER.index(_room(a))
    )


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_every_module_has_a_room() -> None:
    rooms = {_room(m) for m in _imports()}
    assert rooms <= set(ORDER) | {"robot"}, rooms - set(ORDER)


def test_no_module_imports_from_a_room_above_its_own() -> None:
    graph = {m: t for m, t in _imports().items() if _room(m) != "robot"}
    assert upward_edges(graph) == []


def test_the_robots_programs_import_nothing_of_fetchsync() -> None:
    """They are sent as source and run alone by the robot's Python."""
    graph = _imports()
    assert {m: t for m, t in graph.items() if _room(m) == "robot" and t} == {}


def test_the_protocol_imports_only_the_protocol() -> None:
    """It is what the robot runs: nothing of the laptop's side may come along."""
    graph = _imports()
    assert {
        m: sorted(t)
        for m, t in graph.items()
        if _room(m) == "protocol" and any(_room(x) != "protocol" for x in t)
    } == {}


def test_no_import_cycles() -> None:
    assert cycles(_imports()) == []


def test_the_checks_see_an_upward_edge_and_a_cycle() -> None:
    """The two checks above would fail on a graph that breaks them."""
    graph = {
        "fetchsync.link.session": {"fetchsync.sync.state"},
        "fetchsync.sync.state": {"fetchsync.link.session"},
    }
    assert upward_edges(graph) == [("fetchsync.link.session", "fetchsync.sync.state")]
    assert cycles(graph) == [["fetchsync.link.session", "fetchsync.sync.state"]]
