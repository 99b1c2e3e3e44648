"""No import cycle between the package's modules, counting imports inside functions.

An import inside a function hides a cycle from Python (it runs after both modules are loaded) but
not from a reader: two modules that import each other are one module to understand. The run
directory's files live in ``espl_jax.rundir`` and the formula of a seed in
``espl_jax.expression`` so that run, the meta-RL report and the hall of fame need not import each
other.
"""

import ast
import os
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _modules(package_dir: Path, package: str) -> dict[str, Path]:
    """Module name -> file, for every .py under ``package_dir`` (following the espl_jax/envs
    link to the top-level envs/)."""
    out = {}
    for folder, _, files in os.walk(package_dir, followlinks=True):
        parts = [package, *Path(folder).relative_to(package_dir).parts]
        for name in files:
            if name.endswith(".py"):
                stem = name[:-3]
                out[".".join(parts if stem == "__init__" else [*parts, stem])] = Path(folder, name)
    return out


def import_graph(package_dir: Path, package: str) -> dict[str, dict[str, int]]:
    """module -> {imported module of the package: line of the first such import}, counting
    every import statement wherever it is (module level, functions, ``TYPE_CHECKING``)."""
    modules = _modules(package_dir, package)
    graph = {}
    for name, path in modules.items():
        own_package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        edges: dict[str, int] = {}
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:  # relative: from . import x, from ..a import b
                    base = own_package.split(".")[: len(own_package.split(".")) - node.level + 1]
                    source = ".".join(base + ([node.module] if node.module else []))
                else:
                    source = node.module or ""
                # `from pkg import mod` imports the submodule mod; `from mod import name`, mod
                targets = [
                    f"{source}.{alias.name}" if f"{source}.{alias.name}" in modules else source
                    for alias in node.names
                ]
            else:
                continue
            for target in targets:
                while target and target not in modules:  # a.b.c where c is a name in a.b
                    target = target.rpartition(".")[0]
                if target and target != name:
                    edges.setdefault(target, node.lineno)
        graph[name] = edges
    return graph


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
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


def _describe(graph: dict[str, dict[str, int]], component: list[str]) -> str:
    return "; ".join(
        f"{a} imports {b} (line {graph[a][b]})"
        for a in component
        for b in component
        if b in graph[a]
    )


def test_no_import_cycle_in_espl_jax():
    graph = import_graph(ROOT / "espl_jax", "espl_jax")
    assert "espl_jax.envs.tasks" in graph  # envs/ is part of the package and of the check
    found = cycles(graph)
    assert not found, "import cycles: " + " | ".join(_describe(graph, c) for c in found)


def test_cycle_through_a_function_level_import_is_found(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("import os\n\n\ndef f():\n    from pkg.sub import b\n")
    (pkg / "sub" / "b.py").write_text("from ..a import f\n")
    (pkg / "c.py").write_text("from pkg import a\n")
    graph = import_graph(pkg, "pkg")
    assert graph["pkg.a"] == {"pkg.sub.b": 5}
    assert graph["pkg.sub.b"] == {"pkg.a": 1}
    assert cycles(graph) == [["pkg.a", "pkg.sub.b"]]
