"""The layer rule of docs/ARCHITECTURE.md: every import of ``mapets_rl`` and of the recipes
(module level, function-local and ``TYPE_CHECKING`` ones alike, read with ``ast``) points to its
own floor or a lower one; ``mapets_rl/config.py`` imports nothing of the project; recipes never
import each other and are imported as ``mapets_rl.recipes``; code is loaded by name at run time
(recipes by name, ``importlib.import_module``, the ``mapets_rl.recipes`` entry points) only by
the application, ``mapets_rl.app``. The scripts of ``benchmarks/`` and ``examples/`` stand on top:
they import the library, the recipes and the application, never each other (a benchmark only
its folder's ``_common.py``; the modules of ``examples/extending/``, one researcher's package,
each other), and reach no ``_``-prefixed member of the library."""

from __future__ import annotations

import ast
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROJECT = ("mapets_rl", "recipes")
"""The source folders; recipes/ installs as ``mapets_rl.recipes`` (``recipes`` is its old name)."""

FLOORS = {
    "mapets_rl": 0,  # the package root (quiet_dependencies)
    "mapets_rl._console": 0,
    "mapets_rl._entry_points": 0,
    "mapets_rl._compile_cache": 0,
    "mapets_rl.config": 0,
    "mapets_rl.machine": 0,
    "mapets_rl.memory": 0,
    "mapets_rl.metrics": 0,
    "mapets_rl.statistics": 0,
    "mapets_rl.plotting": 0,
    "mapets_rl.ray_runtime": 0,
    "mapets_rl.threads": 0,
    "mapets_rl.envs": 1,
    "mapets_rl.comm": 2,
    "mapets_rl.models": 2,
    "mapets_rl.modules": 2,
    "mapets_rl.shapley": 2,
    "mapets_rl.planning": 3,
    "mapets_rl.objectives": 3,
    "mapets_rl.experiment": 4,
    "mapets_rl.recipes": 5,
    "mapets_rl.app": 6,
}
"""Component -> floor: a component imports only components on its floor or below."""


RUNTIME_LOADERS = (
    "import_module",
    "__import__",
    "resolve_name",
    "load_recipe",
    "available_recipes",
)
"""Functions that load code by name at run time (``pkgutil.resolve_name`` included)."""
USER_CODE_LOADS = {"mapets_rl.recipes.mapets": "resolve_name()"}
"""Loads by name outside the application that load the user's code, not the project's:
MA-PETS's ``reward_fn="package.module:function"``, the reward of a scenario of another
package."""
RECIPE_GROUP = "mapets_rl.recipes"
OLD_NAME_ALIAS = "mapets_rl.recipes"
"""recipes/__init__.py, which gives ``recipes.X`` as ``mapets_rl.recipes.X`` (by name) until the
old name goes: the one load by name outside the application."""


def module_name(path: Path, root: Path = ROOT) -> str:
    """The installed name of a source file: ``recipes/sac.py`` -> ``mapets_rl.recipes.sac``."""
    parts = path.relative_to(root).with_suffix("").parts
    if parts[0] == "recipes":
        parts = ("mapets_rl", *parts)
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


def runtime_loads(path: Path) -> Iterator[tuple[int, str]]:
    """(line, what) of every load of code by name in ``path``: a call of one of
    :data:`RUNTIME_LOADERS`, or the recipes' entry-point group named outside a docstring."""
    tree = ast.parse(path.read_text(), filename=str(path))
    docstrings = {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
    }
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            func = node.func
            name = getattr(func, "attr", None) or getattr(func, "id", None)
            if name in RUNTIME_LOADERS:
                yield node.lineno, f"{name}()"
        elif (
            isinstance(node, ast.Constant)
            and node.value == RECIPE_GROUP
            and id(node) not in docstrings
        ):
            yield node.lineno, f"the entry-point group {RECIPE_GROUP!r}"


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
            elif target == "recipes":
                why = "the recipes are mapets_rl.recipes: recipes is their old name"
            elif mine == target == "mapets_rl.recipes":
                why = "recipes never import each other"
            elif FLOORS.get(target, 0) > FLOORS[mine]:
                why = f"floor {FLOORS[mine]} imports floor {FLOORS.get(target)}"
            else:
                why = ""
            if why:
                found.append(f"{where}:{line}: {importer} -> {module} ({why})")
        if mine != "mapets_rl.app" and importer != OLD_NAME_ALIAS:
            found += [
                f"{where}:{line}: {importer} loads code by name at run time ({what}): only "
                "mapets_rl.app does"
                for line, what in runtime_loads(path)
                if USER_CODE_LOADS.get(importer) != what
            ]
    return found


def test_every_import_respects_the_layers() -> None:
    assert violations() == []
    assert (ROOT / "mapets_rl" / "config.py").is_file()


def test_the_check_sees_a_violation(tmp_path: Path) -> None:
    """A function-local import of the runner from a lower floor, an import in the config base,
    one recipe importing another (by either name), the library importing the application and
    loading code by name (a recipe, a module, the recipes' entry points) are each reported,
    the application's loads are not (the test can fail)."""
    for folder in ("planning", "experiment", "app"):
        (tmp_path / "mapets_rl" / folder).mkdir(parents=True)
    (tmp_path / "recipes").mkdir()
    (tmp_path / "mapets_rl" / "config.py").write_text("from . import metrics\n")
    (tmp_path / "mapets_rl" / "planning" / "cem.py").write_text(
        "def f():\n    from mapets_rl.experiment import check\n"
    )
    (tmp_path / "recipes" / "sac.py").write_text(
        "import recipes.mappo\nfrom mapets_rl.recipes import coma\n"
    )
    (tmp_path / "recipes" / "mappo.py").write_text(
        "from mapets_rl.experiment import check\nimport pkgutil\npkgutil.resolve_name('x:y')\n"
    )
    loads = (
        '"""Names mapets_rl.recipes in a docstring: not a load."""\n'
        "import importlib\n"
        "from importlib.metadata import entry_points\n"
        "def f(name):\n"
        "    importlib.import_module(name)\n"
        '    return entry_points(group="mapets_rl.recipes")\n'
    )
    (tmp_path / "mapets_rl" / "experiment" / "runner.py").write_text(
        loads + "def g():\n    from mapets_rl.app.plugins import load_recipe\n"
    )
    (tmp_path / "mapets_rl" / "app" / "cli.py").write_text(loads)
    assert violations(tmp_path) == [
        "mapets_rl/config.py:1: mapets_rl.config -> mapets_rl.metrics "
        "(mapets_rl/config.py imports nothing of the project)",
        "mapets_rl/experiment/runner.py:8: mapets_rl.experiment.runner -> "
        "mapets_rl.app.plugins.load_recipe (floor 4 imports floor 6)",
        "mapets_rl/experiment/runner.py:5: mapets_rl.experiment.runner loads code by name at "
        "run time (import_module()): only mapets_rl.app does",
        "mapets_rl/experiment/runner.py:6: mapets_rl.experiment.runner loads code by name at "
        "run time (the entry-point group 'mapets_rl.recipes'): only mapets_rl.app does",
        "mapets_rl/planning/cem.py:2: mapets_rl.planning.cem -> mapets_rl.experiment.check "
        "(floor 3 imports floor 4)",
        "recipes/mappo.py:3: mapets_rl.recipes.mappo loads code by name at run time "
        "(resolve_name()): only mapets_rl.app does",
        "recipes/sac.py:1: mapets_rl.recipes.sac -> recipes.mappo (the recipes are "
        "mapets_rl.recipes: recipes is their old name)",
        "recipes/sac.py:2: mapets_rl.recipes.sac -> mapets_rl.recipes.coma (recipes never "
        "import each other)",
    ]


@pytest.mark.parametrize(
    "name", ["mapets_rl/experiment/__init__.py", "recipes/mapets.py", "mapets_rl/app/cli.py"]
)
def test_the_check_reads_the_real_imports(name: str) -> None:
    """The parser finds the imports the top floors do hold (it is not blind)."""
    assert list(project_imports(ROOT / name))


@pytest.mark.parametrize(
    "name", ["mapets_rl/app/plugins.py", "mapets_rl/app/sweep.py", "recipes/mapets.py"]
)
def test_the_check_sees_the_real_runtime_loads(name: str) -> None:
    """The application's own loads by name are found (and allowed there only)."""
    assert list(runtime_loads(ROOT / name))


SCRIPT_FOLDERS = ("benchmarks", "examples")
"""The scripts on top of the building: users of the library, held to its public names."""
SHARED = {"benchmarks": {"_common"}, "benchmarks/ablations": {"_common"}}
"""What a script of a folder may import of its own folder: the folder's ``_common.py``."""
PACKAGES = ("examples/extending",)
"""Folders whose modules form one package (a researcher's, on ``sys.path``): they may import
each other."""
THIRD_PARTY_HOOKS = {"_step", "_reset"}
"""``_``-named members the library defines because a dependency's protocol names them so
(torchrl's ``EnvBase._step`` / ``_reset``, what every torchrl env implements): timing one is
timing the env, not reaching into the library."""


def private_members(root: Path = ROOT) -> set[str]:
    """The ``_``-prefixed (not dunder) names the library defines: functions, methods, classes,
    module and class attributes, instance attributes (``self._x = ...``)."""
    names = set()
    for path in sources(root):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                found = [node.name]
            elif isinstance(node, (ast.Assign, ast.AnnAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                found = [getattr(t, "id", None) or getattr(t, "attr", "") for t in targets]
            else:
                continue
            names |= {n for n in found if n.startswith("_") and not n.startswith("__")}
    return names - THIRD_PARTY_HOOKS


def script_violations(root: Path = ROOT) -> list[str]:
    """Every import of another script and every reach into a ``_``-prefixed library member in
    the scripts of :data:`SCRIPT_FOLDERS`, as ``file:line: what (why)``."""
    private = private_members(root)
    scripts = [p for top in SCRIPT_FOLDERS for p in sorted((root / top).rglob("*.py"))]
    by_folder: dict[str, set[str]] = {}
    for path in scripts:
        by_folder.setdefault(path.parent.relative_to(root).as_posix(), set()).add(path.stem)
    every_script = {stem for stems in by_folder.values() for stem in stems}
    found = []
    for path in scripts:
        folder = path.parent.relative_to(root).as_posix()
        allowed = SHARED.get(folder, set()) | (by_folder[folder] if folder in PACKAGES else set())
        where = path.relative_to(root)
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                modules = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                modules = [base, *(f"{base}.{alias.name}" for alias in node.names)]
            elif isinstance(node, ast.Attribute) and node.attr in private:
                owner = getattr(node.value, "id", None)
                if owner not in ("self", "cls"):
                    found.append(f"{where}:{node.lineno}: .{node.attr} (a private member)")
                continue
            elif isinstance(node, ast.Constant) and node.value in private:
                found.append(f"{where}:{node.lineno}: {node.value!r} (a private member by name)")
                continue
            else:
                continue
            for module in modules:
                top, *rest = module.split(".")
                if top in every_script and top not in allowed:
                    found.append(f"{where}:{node.lineno}: imports {top} (another script)")
                elif top == "recipes":
                    found.append(f"{where}:{node.lineno}: imports {module} (the old name)")
                elif top == "mapets_rl" and any(
                    part.startswith("_") and not part.startswith("__") for part in rest
                ):
                    found.append(f"{where}:{node.lineno}: imports {module} (a private member)")
    return sorted(set(found))


def test_scripts_import_only_the_librarys_public_names() -> None:
    assert script_violations() == []


def test_the_script_check_fails_on_planted_imports(tmp_path: Path) -> None:
    """A copy of the project in which a benchmark imports another benchmark, an example
    imports a benchmark's helper, and scripts reach into the library's private members (by
    attribute, by name, by import) is reported line by line; the original is clean."""
    for top in (*PROJECT, *SCRIPT_FOLDERS):
        shutil.copytree(ROOT / top, tmp_path / top, ignore=shutil.ignore_patterns("__pycache__"))
    planted = {
        "benchmarks/planner.py": "import cooperation_control\n",
        "benchmarks/ablations/horizon.py": "from shield_crashes import classify\n",
        "examples/demo.py": "from _common import run_episode\n",
        "benchmarks/startup.py": "def f(exp):\n    return exp._restore\n",
        "benchmarks/shapley.py": "NAMES = ('_save_boundary_checkpoint',)\n",
        "examples/mixed_traffic.py": "from mapets_rl.experiment.runner import _flatten\n",
    }
    for name, code in planted.items():
        path = tmp_path / name
        path.write_text(path.read_text() + code)
    found = script_violations(tmp_path)
    for name, why in [
        ("benchmarks/ablations/horizon.py", "imports shield_crashes (another script)"),
        ("benchmarks/planner.py", "imports cooperation_control (another script)"),
        ("benchmarks/shapley.py", "'_save_boundary_checkpoint' (a private member by name)"),
        ("benchmarks/startup.py", "._restore (a private member)"),
        ("examples/demo.py", "imports _common (another script)"),
        ("examples/mixed_traffic.py", "imports mapets_rl.experiment.runner._flatten"),
    ]:
        assert any(line.startswith(name + ":") and why in line for line in found), (name, found)
    assert len(found) == len(planted)
