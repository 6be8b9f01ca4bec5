"""The layer rule of docs/ARCHITECTURE.md: every import of ``mapets_rl`` and ``recipes`` (module
level, function-local and ``TYPE_CHECKING`` ones alike, read with ``ast``) points to its own
floor or a lower one; ``mapets_rl/config.py`` imports nothing of the project; recipes never
import each other."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROJECT = ("mapets_rl", "recipes")

FLOORS = {
    "mapets_rl": 0,  # the package root (quiet_dependencies)
    "mapets_rl._console": 0,
    "mapets_rl._entry_points": 0,
    "mapets_rl._compile_cache": 0,
    "mapets_rl.config": 0,
    "mapets_rl.metrics": 0,
    "mapets_rl.statistics": 0,
    "mapets_rl.plotting": 0,
    "mapets_rl.envs": 1,
    "mapets_rl.comm": 2,
    "mapets_rl.models": 2,
    "mapets_rl.modules": 2,
    "mapets_rl.shapley": 2,
    "mapets_rl.planning": 3,
    "mapets_rl.objectives": 3,
    "mapets_rl.experiment": 4,
    "recipes": 5,
}
"""Component -> floor: a component imports only components on its floor or below."""


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def component(module: str) -> str:
    """``mapets_rl.planning.cem`` -> ``mapets_rl.planning``; ``recipes.sac`` -> ``recipes``."""
    parts = module.split(".")
    return parts[0] if parts[0] == "recipes" else ".".join(parts[:2])


def project_imports(path: Path, root: Path = ROOT) -> Iterator[tuple[int, str]]:
    """(line, module) of every import of a project module in ``path``, wherever it stands;
    ``from package import name`` yields ``package.name`` (the name may be a submodule)."""
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            modules = [f"{base}.{alias.name}" for alias in node.names]
        else:
            continue
        for module in modules:
            if module.split(".")[0] in PROJECT:
                yield node.lineno, module


def sources(root: Path = ROOT) -> list[Path]:
    return sorted(p for top in PROJECT for p in (root / top).rglob("*.py"))


def violations(root: Path = ROOT) -> list[str]:
    """Every import that breaks the layer rule, as ``file:line: importer -> imported (why)``."""
    found = []
    for path in sources(root):
        importer = module_name(path, root)
        mine = component(importer)
        where = str(path.relative_to(root))
        if mine not in FLOORS:
            found.append(f"{where}: {mine} has no floor in FLOORS (place it in ARCHITECTURE.md)")
            continue
        for line, module in project_imports(path, root):
            target = component(module)
            if target not in FLOORS:  # `from mapets_rl import quiet_dependencies`
                target = module.rpartition(".")[0]
            if importer == "mapets_rl.config":
                why = "mapets_rl/config.py imports nothing of the project"
            elif mine == target == "recipes":
                why = "recipes never import each other"
            elif FLOORS.get(target, 0) > FLOORS[mine]:
                why = f"floor {FLOORS[mine]} imports floor {FLOORS.get(target)}"
            else:
                why = ""
            if why:
                found.append(f"{where}:{line}: {importer} -> {module} ({why})")
    return found


def test_every_import_respects_the_layers() -> None:
    assert violations() == []
    assert (ROOT / "mapets_rl" / "config.py").is_file()


def test_the_check_sees_a_violation(tmp_path: Path) -> None:
    """A function-local import of the runner from a lower floor, an import in the config base
    and one recipe importing another are each reported (the test can fail)."""
    (tmp_path / "mapets_rl" / "planning").mkdir(parents=True)
    (tmp_path / "recipes").mkdir()
    (tmp_path / "mapets_rl" / "config.py").write_text("from . import metrics\n")
    (tmp_path / "mapets_rl" / "planning" / "cem.py").write_text(
        "def f():\n    from mapets_rl.experiment import check\n"
    )
    (tmp_path / "recipes" / "sac.py").write_text("import recipes.mappo\n")
    (tmp_path / "recipes" / "mappo.py").write_text("from mapets_rl.experiment import check\n")
    assert violations(tmp_path) == [
        "mapets_rl/config.py:1: mapets_rl.config -> mapets_rl.metrics "
        "(mapets_rl/config.py imports nothing of the project)",
        "mapets_rl/planning/cem.py:2: mapets_rl.planning.cem -> mapets_rl.experiment.check "
        "(floor 3 imports floor 4)",
        "recipes/sac.py:1: recipes.sac -> recipes.mappo (recipes never import each other)",
    ]


@pytest.mark.parametrize("name", ["mapets_rl/experiment/__init__.py", "recipes/mapets.py"])
def test_the_check_reads_the_real_imports(name: str) -> None:
    """The parser finds the imports the top floors do hold (it is not blind)."""
    assert list(project_imports(ROOT / name))
