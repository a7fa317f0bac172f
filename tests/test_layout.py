"""The layout's rules (issues 11 and 34), checked from the source itself.
Every .py under dosppm_core/, services/ and harness/ is parsed with `ast`;
every import in it, at the top or inside a function, relative ones
resolved, is an edge of the module graph.

- The library computes: nothing in dosppm_core imports services, harness,
  argparse, zmq, subprocess, http or socket.
- The harness measures the product and is no part of it: it may import
  dosppm_core and services, and nothing there imports it, except the
  `dosppm` command's door to the harness's verbs
  (services/cli/harness_verbs.py), inside a function; so importing the
  command, as `dosppm render`, `server` and `worker` do, loads no harness
  module.
- One module per foreign library: zmq only in services/transport.py,
  embreex only in dosppm_core/accel.py, OpenEXR only in dosppm_core/film.py.
- No import cycles between modules.
- Modules of at most 800 lines, functions of at most 60.

No module is imported: the source is only read.
"""
from __future__ import annotations

import ast
import os
from collections import deque
from dataclasses import dataclass, field

import pytest

from tests.helpers.paths import REPO

PACKAGES = ("dosppm_core", "services", "harness")
HARNESS = "harness"
CORE_MUST_NOT_IMPORT = ("services", HARNESS, "argparse", "zmq", "subprocess", "http", "socket")
# The one module outside the harness that may import it, and only inside a
# function: the door through which `dosppm bench|reference|compare|evaluate`
# reach harness/cli/ when one of them runs.
HARNESS_DOOR = "services/cli/harness_verbs.py"
# What the product's processes import first: the `dosppm` command.
PRODUCT_ENTRY = "services.cli.main"
# library (top-level module name) -> the one file allowed to import it
ONE_MODULE_PER_LIBRARY = {
    "zmq": "services/transport.py",
    "embreex": "dosppm_core/accel.py",
    "OpenEXR": "dosppm_core/film.py",
}
MAX_MODULE_LINES = 800
MAX_FUNCTION_LINES = 60


@dataclass(frozen=True)
class Module:
    name: str          # dotted: "dosppm_core.chunks.store"; a package is its __init__
    path: str          # relative to the repository: "dosppm_core/chunks/store.py"
    is_package: bool
    text: str = field(repr=False)


@dataclass(frozen=True)
class Import:
    """One imported name: `import a.b` gives target "a.b", names ();
    `from a.b import c, d` gives target "a.b", names ("c", "d")."""
    target: str
    names: tuple[str, ...]
    line: int
    type_checking: bool    # under `if TYPE_CHECKING:`: never executed
    deferred: bool = False  # inside a function: executed when it is called, not on import


@dataclass(frozen=True)
class Edge:
    source: str
    target: str
    path: str
    line: int


# -- reading the source ---------------------------------------------------------------
def read_modules(root: str = REPO, packages=PACKAGES) -> dict[str, Module]:
    modules = {}
    for package in packages:
        for folder, dirs, files in os.walk(os.path.join(root, package)):
            dirs[:] = sorted(d for d in dirs if d != "__pycache__")
            for file in sorted(f for f in files if f.endswith(".py")):
                rel = os.path.relpath(os.path.join(folder, file), root).replace(os.sep, "/")
                parts = rel[:-3].split("/")
                is_package = parts[-1] == "__init__"
                name = ".".join(parts[:-1] if is_package else parts)
                with open(os.path.join(root, rel), encoding="utf-8") as f:
                    modules[name] = Module(name, rel, is_package, f.read())
    return modules


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _resolve(module: Module, level: int, name: str | None) -> str:
    """The absolute name of `from <level dots><name> import ...` in `module`."""
    package = module.name if module.is_package else module.name.rpartition(".")[0]
    parts = package.split(".")
    if level - 1 > len(parts) - 1:
        raise ValueError(f"{module.path}: relative import beyond the top-level package")
    base = ".".join(parts[:len(parts) - (level - 1)])
    return f"{base}.{name}" if name else base


def imports_of(module: Module) -> list[Import]:
    """Every import statement of the module, wherever it sits."""
    out = []

    def visit(node: ast.AST, type_checking: bool, deferred: bool) -> None:
        if isinstance(node, ast.Import):
            out.extend(Import(a.name, (), node.lineno, type_checking, deferred) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(module, node.level, node.module) if node.level else node.module
            out.append(Import(target, tuple(a.name for a in node.names), node.lineno, type_checking, deferred))
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.body:
                visit(child, True, deferred)
            for child in node.orelse:
                visit(child, type_checking, deferred)
            return
        deferred = deferred or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
        for child in ast.iter_child_nodes(node):
            visit(child, type_checking, deferred)

    visit(ast.parse(module.text, module.path), False, False)
    return out


def imported_names(imp: Import) -> list[str]:
    """Every dotted name an import may load: the target, and for a
    from-import each target.name (a submodule, if it is one)."""
    return [imp.target] + [f"{imp.target}.{n}" for n in imp.names if n != "*"]


def _prefixes(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts) + 1)]


def _ancestors(name: str) -> set[str]:
    return set(_prefixes(name)[:-1])


def module_edges(modules: dict[str, Module], include_type_checking: bool = False,
                 include_deferred: bool = True) -> list[Edge]:
    """The modules each module makes Python execute, as Python resolves it.

    `import a.b.c` runs a, a.b and a.b.c; `from a.b import c` runs a and
    a.b, then a.b.c if that is a module, else it reads the name c from a.b
    (so depends on a.b's __init__). A module's own ancestor packages are
    already in sys.modules (Python imported them first), so passing
    through them runs nothing: a package __init__ that imports its
    submodules is no cycle. Naming the ancestor itself (`import pkg`, or
    `from pkg import NAME` where NAME is not a submodule) does read it: a
    submodule doing that while pkg's __init__ imports it is a cycle."""
    edges = []
    for m in modules.values():
        for imp in imports_of(m):
            if (imp.type_checking and not include_type_checking) or (imp.deferred and not include_deferred):
                continue
            passed = [p for p in _prefixes(imp.target) if p not in _ancestors(m.name)]
            if imp.names:
                submodules = [f"{imp.target}.{n}" for n in imp.names if f"{imp.target}.{n}" in modules]
                reads_package = len(submodules) < len(imp.names)
                ran = passed + [imp.target] * reads_package + submodules
            else:
                ran = passed + [imp.target]
            edges += [Edge(m.name, t, m.path, imp.line) for t in dict.fromkeys(ran)
                      if t in modules and t != m.name]
    return edges


# -- cycles ---------------------------------------------------------------------------
def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components, iteratively; each sorted."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
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
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == node:
                        break
                out.append(sorted(component))
    return out


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Components of more than one module: each holds at least one cycle."""
    return sorted(c for c in strongly_connected(graph) if len(c) > 1)


def shortest_cycle(graph: dict[str, set[str]], component: list[str]) -> list[str]:
    """A shortest cycle through the component's first module, as a path
    that returns to where it starts."""
    start, inside = component[0], set(component)
    previous, queue = {start: None}, deque([start])
    while queue:
        node = queue.popleft()
        for child in sorted(graph.get(node, ())):
            if child == start:
                path = [node]
                while previous[path[-1]] is not None:
                    path.append(previous[path[-1]])
                return path[::-1] + [start]
            if child in inside and child not in previous:
                previous[child] = node
                queue.append(child)
    return component


def describe_cycle(component: list[str], graph: dict[str, set[str]], edges: list[Edge]) -> str:
    where = {}
    for e in edges:
        where.setdefault((e.source, e.target), f"{e.path}:{e.line}")
    path = shortest_cycle(graph, component)
    steps = " -> ".join(f"{a} ({where[a, b]})" for a, b in zip(path, path[1:])) + f" -> {path[-1]}"
    return f"{len(component)} modules {component}; e.g. {steps}"


def graph_of(edges: list[Edge]) -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.source, set()).add(e.target)
    return graph


# -- the rules ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def modules():
    found = read_modules()
    assert all(p in found for p in PACKAGES), f"not every one of {PACKAGES} found under {REPO}"
    return found


def importers(modules, library: str) -> dict[str, list[int]]:
    """file -> lines of the imports that load `library` (or a submodule)."""
    out: dict[str, list[int]] = {}
    for m in modules.values():
        for imp in imports_of(m):
            if any(n.split(".")[0] == library for n in imported_names(imp)):
                out.setdefault(m.path, []).append(imp.line)
    return out


def test_the_library_imports_no_service_and_no_io_framework(modules):
    bad = []
    for m in modules.values():
        if not m.name.startswith("dosppm_core"):
            continue
        for imp in imports_of(m):
            hit = sorted({n.split(".")[0] for n in imported_names(imp)} & set(CORE_MUST_NOT_IMPORT))
            bad += [f"{m.path}:{imp.line} imports {imp.target} ({', '.join(hit)})"] if hit else []
    assert not bad, "dosppm_core computes; the services run things:\n" + "\n".join(bad)


@pytest.mark.parametrize("library", list(ONE_MODULE_PER_LIBRARY))
def test_each_foreign_library_has_one_module(modules, library):
    owner = ONE_MODULE_PER_LIBRARY[library]
    others = {path: lines for path, lines in importers(modules, library).items() if path != owner}
    assert not others, f"only {owner} may import {library}; also: " + \
        ", ".join(f"{path}:{','.join(map(str, lines))}" for path, lines in sorted(others.items()))


def harness_imports_outside_it(modules: dict[str, Module]) -> list[str]:
    """Every import of the harness by the library or the services that the
    rules do not allow: any, but the door's own imports inside a function."""
    bad = []
    for m in modules.values():
        if m.name.split(".")[0] == HARNESS:
            continue
        for imp in imports_of(m):
            if not any(n.split(".")[0] == HARNESS for n in imported_names(imp)):
                continue
            if m.path == HARNESS_DOOR and imp.deferred:
                continue
            where = "at import time" if not imp.deferred else "outside the door"
            bad.append(f"{m.path}:{imp.line} imports {imp.target} ({where})")
    return bad


def loaded_on_import(modules: dict[str, Module], entry: str) -> set[str]:
    """Every module that importing `entry` executes: its imports outside
    functions, followed through each module they load."""
    graph = graph_of(module_edges(modules, include_deferred=False))
    seen, todo = {entry}, [entry]
    while todo:
        for child in graph.get(todo.pop(), ()):
            if child not in seen:
                seen.add(child)
                todo.append(child)
    return seen


def test_nothing_outside_the_harness_imports_it_but_the_door(modules):
    bad = harness_imports_outside_it(modules)
    assert not bad, (f"harness/ measures the product; only {HARNESS_DOOR} may import it, inside a "
                     "function:\n" + "\n".join(bad))


def test_the_dosppm_command_loads_no_harness_module(modules):
    """`dosppm render`, `server` and `worker` import the command and with it
    every verb's module: none of that may load the harness (its verbs do,
    when one runs)."""
    loaded = loaded_on_import(modules, PRODUCT_ENTRY)
    assert "services.cli.render" in loaded and "services.cli.harness_verbs" in loaded   # the walk walks
    harness = sorted(m for m in loaded if m.split(".")[0] == HARNESS)
    assert not harness, f"importing {PRODUCT_ENTRY} loads {harness}"


def test_no_import_cycles(modules):
    edges = module_edges(modules)
    graph = graph_of(edges)
    cycles = import_cycles(graph)
    assert not cycles, "import cycles:\n" + "\n".join(describe_cycle(c, graph, edges) for c in cycles)


def test_modules_are_at_most_800_lines(modules):
    long = sorted((m.text.count("\n") + (not m.text.endswith("\n") and bool(m.text)), m.path)
                  for m in modules.values())
    over = [f"{path}: {n} lines" for n, path in long if n > MAX_MODULE_LINES]
    assert not over, f"modules over {MAX_MODULE_LINES} lines:\n" + "\n".join(over)


def test_functions_are_at_most_60_lines(modules):
    over = []
    for m in sorted(modules.values(), key=lambda m: m.path):
        for node in ast.walk(ast.parse(m.text, m.path)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    over.append(f"{m.path}:{node.lineno} {node.name}: {n} lines")
    assert not over, f"functions over {MAX_FUNCTION_LINES} lines (def to last line):\n" + "\n".join(over)


# -- the checker checked --------------------------------------------------------------
def test_cycle_finder_reports_a_synthetic_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"a"}, "f": {"f"}}
    assert import_cycles(graph) == [["a", "b", "c"]]
    assert shortest_cycle(graph, ["a", "b", "c"]) == ["a", "b", "c", "a"]
    assert import_cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []
    two = {"x": {"y"}, "y": {"x"}, "p": {"q"}, "q": {"r"}, "r": {"p"}}
    assert import_cycles(two) == [["p", "q", "r"], ["x", "y"]]


def _synthetic(files: dict[str, str]) -> dict[str, Module]:
    out = {}
    for path, text in files.items():
        parts = path[:-3].split("/")
        is_package = parts[-1] == "__init__"
        name = ".".join(parts[:-1] if is_package else parts)
        out[name] = Module(name, path, is_package, text)
    return out


def test_the_harness_rules_catch_what_they_forbid():
    """Each harness rule fails where it should, on a synthetic tree."""
    tree = {"dosppm_core/__init__.py": "", "dosppm_core/film.py": "",
            "services/__init__.py": "", "services/cli/__init__.py": "",
            "services/cli/main.py": "from services.cli import harness_verbs, render\n",
            "services/cli/render.py": "from dosppm_core import film\n",
            "services/cli/harness_verbs.py": "def run():\n    from harness.cli.main import main\n",
            "harness/__init__.py": "", "harness/cli/__init__.py": "",
            "harness/cli/main.py": "from services.cli import render\nimport dosppm_core.film\n"}
    assert harness_imports_outside_it(_synthetic(tree)) == []
    assert not any(m.startswith("harness") for m in loaded_on_import(_synthetic(tree), PRODUCT_ENTRY))
    # The door imports the harness on import; a verb, or the library, imports it at all.
    eager_door = {**tree, "services/cli/harness_verbs.py": "from harness.cli.main import main\n"}
    assert harness_imports_outside_it(_synthetic(eager_door)) == \
        ["services/cli/harness_verbs.py:1 imports harness.cli.main (at import time)"]
    assert "harness.cli.main" in loaded_on_import(_synthetic(eager_door), PRODUCT_ENTRY)
    for path, text in (("services/cli/render.py", "def run():\n    import harness.cli.main\n"),
                       ("dosppm_core/film.py", "from harness import cli\n")):
        found = harness_imports_outside_it(_synthetic({**tree, path: text}))
        assert len(found) == 1 and found[0].startswith(path), found
    # A module the command loads that loads the harness in turn.
    via = {**tree, "services/cli/render.py": "from services import helper\n",
           "services/helper.py": "from harness import cli\n"}
    assert "harness.cli" in loaded_on_import(_synthetic(via), PRODUCT_ENTRY)


def _cycles(files: dict[str, str]) -> list[list[str]]:
    return import_cycles(graph_of(module_edges(_synthetic(files))))


def test_the_graph_follows_how_python_resolves_imports():
    base = {"pkg/__init__.py": "from pkg.sub import f\nVERSION = 1\n", "pkg/other.py": "",
            "pkg/deep/__init__.py": "", "pkg/deep/leaf.py": "", "top.py": ""}
    # A package's __init__ importing its submodules is no cycle ...
    assert _cycles({**base, "pkg/sub.py": "import os\ndef f(): pass\n"}) == []
    assert _cycles({**base, "pkg/sub.py": "from pkg import other\nfrom . import other\nimport pkg.other\n"}) == []
    # ... unless the submodule reads the package back, however spelled,
    # at the top or inside a function.
    for back in ("from pkg import VERSION", "from . import VERSION", "import pkg",
                 "def g():\n    from pkg import VERSION"):
        assert _cycles({**base, "pkg/sub.py": back + "\n"}) == [["pkg", "pkg.sub"]], back
    # Relative imports resolve against the package; `from a import b`
    # depends on the module a.b when there is one.
    edges = module_edges(_synthetic({**base, "pkg/sub.py": "",
                                     "pkg/deep/mid.py": "from ..other import x\nfrom . import leaf\n"
                                                        "from .. import other\nimport top\n"}))
    assert {(e.source, e.target) for e in edges if e.source == "pkg.deep.mid"} == \
        {("pkg.deep.mid", "pkg.other"), ("pkg.deep.mid", "pkg.deep.leaf"), ("pkg.deep.mid", "top")}
    # Importing into another package runs that package's __init__.
    cross = {**base, "pkg/sub.py": "", "pkg/deep/__init__.py": "import top\n", "top.py": "import pkg.deep.leaf\n"}
    assert _cycles(cross) == [["pkg.deep", "top"]]
    # Imports only a type checker runs are no cycle.
    typed = "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg import VERSION\n"
    assert _cycles({**base, "pkg/sub.py": typed}) == []
