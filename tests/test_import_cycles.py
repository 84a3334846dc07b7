"""No import cycles in the pointfence package.

Every module of every folder the distribution maps (pyproject.toml, ``[tool.setuptools]``:
``packages`` and ``package-dir``) is parsed with ``ast``, without importing anything, and the
graph of its imports of pointfence modules is built:

* every ``import`` statement counts, wherever it stands: at module level, inside a function
  (a lazy import defers the cost, not the dependency: two modules that need each other are one
  concept split in two, whichever of them imports late), and under ``if TYPE_CHECKING:`` (a
  module that needs another's types depends on it as well);
* ``from package import name`` is an edge to ``package.name`` where that is a module, else to
  the package (its ``__init__``);
* importing ``a.b.c`` is an edge to ``a.b.c`` only, not to ``a`` and ``a.b`` (which Python
  initialises first): otherwise every subpackage whose ``__init__`` re-exports its modules would
  be a cycle with each of them.

A cycle is a strongly connected component of that graph (two or more modules, or a module that
imports itself). The test fails on any cycle not in ``KNOWN``, naming one concrete loop of
imports (file and line of each), and on any entry of ``KNOWN`` that no longer exists, so a
fixed cycle is removed from the list in the same change.

The same holds one level up, between the subpackages (``pointfence.kernels``,
``pointfence.service``, ``pointfence.bench``, ...: a module's subpackage is the first two parts
of its name): the layers of the product (kernels under service, bench measuring both, never
served from) must not need each other either (``KNOWN_PACKAGES``).
"""
from __future__ import annotations

import ast
from collections import deque
from pathlib import Path

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]

#: Cycles between modules that are tolerated, each the set of modules of one strongly connected
#: component: none (a new cycle fails; an entry must go when its cycle is gone).
KNOWN: list[frozenset] = []

#: Cycles between subpackages that are tolerated: none (the last two went in issue 19: the demo's
#: scenes moved from bench/ to service/dynamic_scenes.py, trajectory files to clients/trajectory.py).
KNOWN_PACKAGES: list[frozenset] = []


def package_dirs(root: Path = ROOT) -> dict:
    """{package name: its folder} for every package pyproject.toml lists."""
    cfg = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    dirs = cfg.get("package-dir", {})
    out = {}
    for pkg in cfg["packages"]:
        # the folder of the longest mapped prefix, then the rest of the name as subfolders
        parts = pkg.split(".")
        for k in range(len(parts), 0, -1):
            prefix = ".".join(parts[:k])
            if prefix in dirs:
                out[pkg] = root / dirs[prefix] / Path(*parts[k:])
                break
        else:
            out[pkg] = root / Path(*parts)
    return out


def modules(root: Path = ROOT) -> dict:
    """{module name: its file} for every .py file of every listed package (a package's own name
    is its ``__init__.py``)."""
    out = {}
    for pkg, folder in package_dirs(root).items():
        for f in sorted(folder.glob("*.py")):
            out[pkg if f.stem == "__init__" else f"{pkg}.{f.stem}"] = f
    return out


def _imports(tree: ast.AST, name: str, is_package: bool, known: set) -> list:
    """[(imported pointfence module, line)] of every import statement in ``tree``."""
    package = name if is_package else name.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names if a.name in known]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            for a in node.names:
                sub = f"{mod}.{a.name}"
                if sub in known:
                    out.append((sub, node.lineno))
                elif mod in known:
                    out.append((mod, node.lineno))
    return out


def import_graph(root: Path = ROOT) -> tuple:
    """({module: {imported module: first line}}, {module: file})."""
    files = modules(root)
    known = set(files)
    graph = {}
    for name, f in files.items():
        tree = ast.parse(f.read_text(), filename=str(f))
        edges = {}
        for target, line in _imports(tree, name, f.stem == "__init__", known):
            edges.setdefault(target, line)
        graph[name] = edges
    return graph, files


def cycles(graph: dict) -> list:
    """The strongly connected components with a cycle (Tarjan), each a frozenset of modules."""
    index, low, on, stack, out = {}, {}, set(), [], []
    counter = [0]

    def visit(v):
        # iterative, so a long chain of imports cannot hit the recursion limit
        work = [(v, iter(graph[v]))]
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        while work:
            u, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(graph[w])))
                    break
                if w in on:
                    low[u] = min(low[u], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[u])
                if low[u] == index[u]:
                    comp = set()
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.add(w)
                        if w == u:
                            break
                    if len(comp) > 1 or u in graph[u]:
                        out.append(frozenset(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def loop_in(graph: dict, comp: frozenset) -> list:
    """One shortest loop of imports inside the component: [m0, m1, ..., m0]."""
    best = None
    for start in sorted(comp):
        prev = {start: None}
        queue = deque([start])
        while queue:
            u = queue.popleft()
            for w in sorted(graph[u]):
                if w == start:
                    path = [u]
                    while prev[path[-1]] is not None:
                        path.append(prev[path[-1]])
                    path = path[::-1] + [start]
                    if best is None or len(path) < len(best):
                        best = path
                    queue.clear()
                    break
                if w in comp and w not in prev:
                    prev[w] = u
                    queue.append(w)
    return best


def describe(graph: dict, files: dict, comp: frozenset) -> str:
    path = loop_in(graph, comp)
    steps = [f"{a} ({files[a].relative_to(ROOT)}:{graph[a][b]}) imports {b}" for a, b in zip(path, path[1:])]
    return f"cycle among {sorted(comp)}:\n    " + "\n    ".join(steps)


def package_graph(graph: dict) -> dict:
    """The import graph between subpackages: {package: {imported package: (module, imported
    module)}}, the first module pair (in name order) that makes each edge."""
    def top(m):
        return ".".join(m.split(".")[:2])

    out = {top(m): {} for m in graph}
    for a in sorted(graph):
        for b in sorted(graph[a]):
            if top(a) != top(b):
                out[top(a)].setdefault(top(b), (a, b))
    return out


def test_the_graph_covers_every_package_and_finds_imports():
    """The walker sees every mapped folder and resolves relative, absolute, function-level and
    package imports (a broken walker would find no cycle at all)."""
    graph, files = import_graph()
    for pkg in ("pointfence", "pointfence.kernels", "pointfence.kernels.warp", "pointfence.service",
                "pointfence.service.robot", "pointfence.clients", "pointfence.calib", "pointfence.bench"):
        assert pkg in files, pkg
    # module level, relative
    assert "pointfence.kernels.errors" in graph["pointfence.kernels.warp.proxy"]
    # function level, relative (WarpBackend.pipeline imports its pipeline lazily)
    assert "pointfence.kernels.warp.pipeline" in graph["pointfence.kernels.warp.backend"]
    # absolute `from package import name` where the name is no module: the package itself
    assert "pointfence.kernels" in graph["pointfence.service.app"] or any(
        "pointfence.kernels" in graph[m] for m in graph if m.startswith("pointfence.service"))


def test_cycle_finder_names_a_loop():
    g = {"a": {"b": 1}, "b": {"c": 2}, "c": {"a": 3, "d": 4}, "d": {}, "e": {"e": 5}}
    found = set(cycles(g))
    assert found == {frozenset("abc"), frozenset("e")}
    assert loop_in(g, frozenset("abc")) == ["a", "b", "c", "a"]


def test_no_import_cycles_beyond_the_known_ones():
    graph, files = import_graph()
    found = set(cycles(graph))
    new = [describe(graph, files, c) for c in sorted(found - set(KNOWN), key=sorted)]
    gone = [sorted(c) for c in KNOWN if c not in found]
    assert not new, "import cycles (a lazy import counts too):\n" + "\n".join(new)
    assert not gone, f"these KNOWN cycles no longer exist as listed; remove or update them in KNOWN: {gone}"
    assert not any(m.startswith("pointfence.kernels") for c in KNOWN for m in c), "kernels/ must have no cycle"


def test_no_cycles_between_subpackages_beyond_the_known_ones():
    graph, files = import_graph()
    pk = package_graph(graph)
    found = set(cycles(pk))

    def why(comp):
        path = loop_in(pk, comp)
        return f"cycle among {sorted(comp)}:\n    " + "\n    ".join(
            f"{a} imports {b} ({pk[a][b][0]} -> {pk[a][b][1]}, {files[pk[a][b][0]].relative_to(ROOT)})"
            for a, b in zip(path, path[1:]))

    new = [why(c) for c in sorted(found - set(KNOWN_PACKAGES), key=sorted)]
    gone = [sorted(c) for c in KNOWN_PACKAGES if c not in found]
    assert not new, "import cycles between subpackages:\n" + "\n".join(new)
    assert not gone, f"these KNOWN_PACKAGES cycles no longer exist as listed; remove or update them: {gone}"
    assert not any("pointfence.kernels" in c for c in KNOWN_PACKAGES), "kernels/ imports no other subpackage"
