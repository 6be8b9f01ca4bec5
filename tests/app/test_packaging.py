"""Packaging: the recipes install as ``mapets_rl.recipes`` (no top-level ``recipes`` package in
site-packages), every package is in the wheel, and the old name ``recipes.X`` still gives the
same module for one release, with a DeprecationWarning."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
tomllib = pytest.importorskip("tomllib", reason="tomllib needs Python 3.11")


def _setuptools() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_the_wheel_holds_every_package_and_no_top_level_recipes() -> None:
    folders = {
        ".".join(init.parent.relative_to(ROOT).parts)
        for init in ROOT.glob("mapets_rl/**/__init__.py")
    }
    data = {  # folders of YAML files whose names Python could import, listed (no warning)
        ".".join(d.relative_to(ROOT).parts)
        for d in ROOT.glob("mapets_rl/configs/**/")
        if all(part.isidentifier() for part in d.relative_to(ROOT).parts)
    }
    config = _setuptools()
    assert set(config["packages"]) == folders | data | {"mapets_rl.recipes"}
    assert data == {"mapets_rl.configs", "mapets_rl.configs.fragments"}
    assert config["package-dir"] == {"mapets_rl.recipes": "recipes"}
    assert {name.split(".")[0] for name in config["packages"]} == {"mapets_rl"}


def test_the_entry_points_name_the_installed_recipes() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    targets = project["entry-points"]["mapets_rl.recipes"].values()
    assert targets and all(t.startswith("mapets_rl.recipes.") for t in targets)
    assert project["scripts"]["mapets-rl"] == "mapets_rl.app.cli:main"


def test_the_old_name_warns_and_gives_the_same_module() -> None:
    """From a source checkout, ``import recipes.mappo`` warns once and is
    ``mapets_rl.recipes.mappo`` itself (its classes are the same objects)."""
    code = (
        "import warnings\n"
        "with warnings.catch_warnings(record=True) as caught:\n"
        "    warnings.simplefilter('always')\n"
        "    import recipes.mappo\n"
        "    from recipes.mappo import MAPPO\n"
        "import mapets_rl.recipes.mappo as new\n"
        "assert recipes.mappo is new and MAPPO is new.MAPPO\n"
        "ours = [w for w in caught if 'mapets_rl.recipes' in str(w.message)]\n"
        "assert len(ours) == 1 and ours[0].category is DeprecationWarning, ours\n"
        "assert ours[0].filename == '<string>', ours[0].filename\n"
    )
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, timeout=300)
