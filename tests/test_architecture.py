"""docs/architecture.md's layering, enforced: a package imports only packages of its own layer or below, never back
up, whether the import sits at the top of a module or inside a function (a function-local import hides an arrow from
a reader, not from this test)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "gra_mi"

LAYERS = ["core", "subject", "stage", "render", "capture", "fit", "relightnet", "refiner", "eval", "apps", "cli"]
"""Bottom to top, as docs/architecture.md draws them: each may import those before it."""


def imports_of(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
    return [(line, name) for line, name in found if name.startswith("gra_mi.")]


def test_every_package_is_placed_in_a_layer():
    packages = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    assert packages - {"data"} == set(LAYERS), "place a new package in LAYERS and in docs/architecture.md"


def test_no_import_runs_back_up_the_layers():
    rank = {name: k for k, name in enumerate(LAYERS)}
    back = []
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).parts
        if len(parts) < 2 or parts[0] not in rank:
            continue
        for line, module in imports_of(path):
            target = module.split(".")[1]
            if target in rank and rank[target] > rank[parts[0]]:
                back.append(f"{path.relative_to(PACKAGE.parent)}:{line} ({parts[0]}) imports {module} ({target})")
    assert not back, "imports that run back up the layers:\n" + "\n".join(back)


def test_the_walker_sees_function_local_imports(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from gra_mi.apps.demo import run_demo\n")
    assert imports_of(module) == [(2, "gra_mi.apps.demo")]


def module_graph() -> dict[str, set[str]]:
    """gra_mi's modules → the gra_mi modules each imports (``from gra_mi.a import b`` counts as importing the module
    ``gra_mi.a.b`` where that is one, else ``gra_mi.a``), function-local imports included."""
    modules = {}
    for path in PACKAGE.rglob("*.py"):
        name = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        modules[name.removesuffix(".__init__")] = path
    graph = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and node.module.startswith("gra_mi"):
                targets = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules else node.module for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names if a.name.startswith("gra_mi")]
            for target in targets:
                while target not in modules and "." in target:
                    target = target.rsplit(".", 1)[0]
                if target in modules and target != name and modules[target].name != "__init__.py":
                    graph[name].add(target)
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm, iterative)."""
    index, low, on_stack, stack, found, counter = {}, {}, set(), [], [], 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, edges = work[-1]
            for nxt in edges:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter
                    counter += 1
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return found


def test_no_import_circles():
    # Two modules that import each other (even inside a function) are one module split in two: their shared records
    # belong one floor below both (STYLE.md).
    found = circles(module_graph())
    assert not found, "import circles:\n" + "\n".join(" ↔ ".join(c) for c in found)


def test_the_circle_finder_finds_a_circle_through_a_function_local_import():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []
