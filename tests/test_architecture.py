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
