"""The import graph of ``mapets_rl`` and the recipes has no circle: no module imports, directly
or through others, a module that imports it (every import counts, function-local ones too, as
in the layer rule of ``tests/test_architecture.py``). Shared names live in a module below both
users (``mapets_rl.app.prog`` holds the ``PROG`` that the parser and the recipe help print)."""

from __future__ import annotations

import graphlib
from pathlib import Path

from tests.test_architecture import PROJECT, ROOT, module_name, project_imports


def import_cycle(root: Path) -> list[str] | None:
    """One circle of imports among the project modules under ``root`` (a module named in an
    import that is not a file counts as its package), or None when there is none."""
    modules = {module_name(p, root): p for d in PROJECT for p in (root / d).rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        edges = graph.setdefault(name, set())
        for _, imported in project_imports(path, root):
            while imported and imported not in modules:
                imported = imported.rpartition(".")[0]
            if imported and imported != name:
                edges.add(imported)
    try:
        graphlib.TopologicalSorter(graph).prepare()
    except graphlib.CycleError as err:
        return list(err.args[1])
    return None


def test_the_import_graph_has_no_circle() -> None:
    assert import_cycle(ROOT) is None


def test_a_planted_circle_is_found(tmp_path: Path) -> None:
    app = tmp_path / "mapets_rl" / "app"
    app.mkdir(parents=True)
    (app / "__init__.py").write_text("")
    (app / "cli.py").write_text("def f():\n    from mapets_rl.app.help import g\n")
    (app / "help.py").write_text("from mapets_rl.app.cli import f\n")
    assert set(import_cycle(tmp_path) or []) == {"mapets_rl.app.cli", "mapets_rl.app.help"}
