"""The layers, read from the import graph (issue 15).

    vio core   everything in vio/ outside vio/app/: numpy, OpenCV, gtsam; no devices, no tools
      ^
    drivers, calib   sources, MAVLink, recording; calibration tools over the core
      ^
    vio.app    the commands, replay, the daemon, `vio status`: the only code that may import drivers and calib

Rules, checked on every module of vio/, drivers/ and calib/ (parsed with `ast`, nothing is imported):

1. the core imports neither `drivers` nor `calib` nor `vio.app`;
2. `drivers` and `calib` do not import `vio.app`;
3. no cycle between the four packages (vio core, drivers, calib, vio.app);
4. no cycle between files.

Every import counts for rules 1-3: module-level, function-local (a lazy import is still a dependency, only a
later one) and under `if TYPE_CHECKING:` (a type named across a layer couples the layers as much).
For rule 4 function-local imports count too (a factory that imports its products lazily while they import
the factory's module is the cycle rule 4 exists to catch); imports under `if TYPE_CHECKING:` do not (they
never run, and naming a type is how a cycle is broken). An import edge points at the module named
(`from a.b import c` at a.b.c when that is a module, else at a.b); the implicit import of parent packages
is not an edge (a package's `__init__` importing its own submodules is the normal pattern, not a cycle).
Modules named by string (the COMMANDS table in vio/app/cli.py) are not seen; they all live in vio.app or
drivers/calib, which rules 1-2 already govern through their own imports.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("vio", "drivers", "calib")


@dataclass(frozen=True)
class Import:
    source: str  # importing module, dotted
    target: str  # imported module (dotted; may be outside the project)
    line: int
    local: bool  # inside a function
    type_only: bool  # under `if TYPE_CHECKING:`


def module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def collect_imports(root: Path) -> tuple[set[str], list[Import]]:
    """All project modules under root and every import statement in them."""
    files = sorted(p for pkg in PACKAGES if (root / pkg).is_dir() for p in (root / pkg).rglob("*.py"))
    modules = {module_name(root, p) for p in files}
    imports: list[Import] = []
    for path in files:
        name = module_name(root, path)
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]

        def visit(node: ast.AST, local: bool, type_only: bool, name: str = name, package: str = package) -> None:
            for child in ast.iter_child_nodes(node):
                if isinstance(child, ast.Import):
                    for alias in child.names:
                        imports.append(Import(name, alias.name, child.lineno, local, type_only))
                elif isinstance(child, ast.ImportFrom):
                    if child.level:
                        base = package.split(".")[: len(package.split(".")) - (child.level - 1)]
                        mod = ".".join(base + ([child.module] if child.module else []))
                    else:
                        mod = child.module or ""
                    for alias in child.names:
                        sub = f"{mod}.{alias.name}"
                        imports.append(Import(name, sub if sub in modules else mod, child.lineno, local, type_only))
                elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                    visit(child, True, type_only)
                elif isinstance(child, ast.If) and _is_type_checking(child.test):
                    for stmt in child.body:
                        visit(ast.Module(body=[stmt], type_ignores=[]), local, True)
                    for stmt in child.orelse:
                        visit(ast.Module(body=[stmt], type_ignores=[]), local, type_only)
                else:
                    visit(child, local, type_only)

        visit(ast.parse(path.read_text(), filename=str(path)), False, False)
    return modules, imports


def layer(module: str) -> str | None:
    """'vio' (the core), 'vio.app', 'drivers', 'calib'; None outside the project."""
    top = module.split(".")[0]
    if top not in PACKAGES:
        return None
    if top == "vio" and (module == "vio.app" or module.startswith("vio.app.")):
        return "vio.app"
    return top


FORBIDDEN = {"vio": {"drivers", "calib", "vio.app"}, "drivers": {"vio.app"}, "calib": {"vio.app"}}


def layer_violations(imports: list[Import]) -> list[str]:
    out: list[str] = []
    for imp in imports:
        src, dst = layer(imp.source), layer(imp.target)
        if src and dst and dst in FORBIDDEN.get(src, ()):
            where = "function-local " if imp.local else "type-only " if imp.type_only else ""
            line = f"{imp.source}:{imp.line} ({src}) {where}imports {imp.target} ({dst})"
            if line not in out:
                out.append(line)
    return sorted(out)


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's SCCs with more than one node, or one node importing itself (iterative: no recursion limit)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph.get(start, ()))))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    top = stack.pop()
                    on_stack.discard(top)
                    component.append(top)
                    if top == node:
                        break
                if len(component) > 1 or node in graph.get(node, ()):
                    found.append(sorted(component))
    return found


def package_cycles(imports: list[Import]) -> list[list[str]]:
    graph: dict[str, set[str]] = {}
    for imp in imports:
        src, dst = layer(imp.source), layer(imp.target)
        if src and dst and src != dst:
            graph.setdefault(src, set()).add(dst)
    return sorted(strongly_connected(graph))


def file_cycles(modules: set[str], imports: list[Import]) -> list[list[str]]:
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for imp in imports:
        if not imp.type_only and imp.target in modules and imp.target != imp.source:
            graph[imp.source].add(imp.target)
    return sorted(strongly_connected(graph))


def _edges_within(component: list[str], imports: list[Import]) -> list[str]:
    members = set(component)
    return sorted({f"{i.source}:{i.line} -> {i.target}" for i in imports
                   if not i.type_only and i.source in members and i.target in members and i.source != i.target})


@pytest.fixture(scope="module")
def graph() -> tuple[set[str], list[Import]]:
    return collect_imports(ROOT)


def test_the_graph_sees_the_whole_project(graph) -> None:
    modules, imports = graph
    assert {"vio.estimator", "vio.app.cli", "vio.app.daemon.service", "drivers.source", "calib.cli"} <= modules
    assert any(i.source == "vio.app.daemon.service" and i.target == "drivers.source" and i.local for i in imports)


def test_core_imports_no_driver_tool_or_app_module(graph) -> None:
    _, imports = graph
    bad = [v for v in layer_violations(imports) if v.split(" ")[1] == "(vio)"]
    assert not bad, "the vio core must not import drivers, calib or vio.app:\n  " + "\n  ".join(bad)


def test_drivers_and_calib_do_not_import_the_app_layer(graph) -> None:
    _, imports = graph
    bad = [v for v in layer_violations(imports) if v.split(" ")[1] in ("(drivers)", "(calib)")]
    assert not bad, "drivers and calib must not import vio.app:\n  " + "\n  ".join(bad)


def test_no_cycle_between_packages(graph) -> None:
    _, imports = graph
    cycles = package_cycles(imports)
    detail = []
    for c in cycles:
        for src in c:
            for dst in c:
                edges = sorted({f"{i.source}:{i.line} -> {i.target}" for i in imports
                                if src != dst and layer(i.source) == src and layer(i.target) == dst})
                if edges:
                    more = f" (+{len(edges) - 3} more)" if len(edges) > 3 else ""
                    detail.append(f"{src} -> {dst}: " + "; ".join(edges[:3]) + more)
    assert not cycles, "import cycle between packages:\n  " + "\n  ".join(detail)


def test_no_cycle_between_files(graph) -> None:
    modules, imports = graph
    cycles = file_cycles(modules, imports)
    detail = [" <-> ".join(c) + "\n      " + "\n      ".join(_edges_within(c, imports)) for c in cycles]
    assert not cycles, "import cycle between files:\n  " + "\n  ".join(detail)


def test_the_checks_catch_what_they_are_for(tmp_path: Path) -> None:
    """The rules on a small tree that breaks each of them (so a checker that sees nothing cannot pass)."""
    files = {
        "vio/__init__.py": "",
        "vio/replay.py": "from vio import types\n\ndef run():\n    from drivers.mavlink_out import Out\n",
        "vio/types.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from vio.replay import run\n",
        "vio/app/__init__.py": "",
        "vio/app/cli.py": "import drivers.source\nfrom calib import cli\n",
        "drivers/__init__.py": "",
        "drivers/mavlink_out.py": "from . import source\n",
        "drivers/source.py": "def open_source():\n    from drivers.fake import Fake\n",
        "drivers/fake.py": "from drivers.source import open_source\n",
        "calib/__init__.py": "",
        "calib/cli.py": "from vio.app.cli import main\n",
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    modules, imports = collect_imports(tmp_path)
    assert layer_violations(imports) == [
        "calib.cli:1 (calib) imports vio.app.cli (vio.app)",
        "vio.replay:4 (vio) function-local imports drivers.mavlink_out (drivers)",
    ]
    assert package_cycles(imports) == [["calib", "vio.app"]]
    # the TYPE_CHECKING import (vio.types -> vio.replay) closes no cycle; the lazy factory import does
    assert file_cycles(modules, imports) == [["calib.cli", "vio.app.cli"], ["drivers.fake", "drivers.source"]]
