"""The recipes, one algorithm per module, installed as ``mapets_rl.recipes`` (the folder stands
at the top of the source tree, above the library it uses; ``pyproject.toml`` maps it).

``import recipes.X``, the name of this package before, still works for one release where this
folder's parent is on ``sys.path`` (a source checkout): it warns (DeprecationWarning) and gives
the module ``mapets_rl.recipes.X`` itself, never a second copy of it.
"""

if __name__ == "recipes":  # this folder imported under its old top-level name
    import importlib
    import importlib.abc
    import importlib.util
    import sys
    import warnings
    from collections.abc import Sequence
    from importlib.machinery import ModuleSpec
    from types import ModuleType

    warnings.warn(
        "the package `recipes` is `mapets_rl.recipes` now (import mapets_rl.recipes.X); "
        "the old name goes in the next release",
        DeprecationWarning,
        stacklevel=2,
    )

    class _NewName(importlib.abc.MetaPathFinder, importlib.abc.Loader):
        """Finds ``recipes.X`` as the module ``mapets_rl.recipes.X``."""

        def find_spec(
            self,
            fullname: str,
            path: Sequence[str] | None = None,
            target: ModuleType | None = None,
        ) -> ModuleSpec | None:
            if fullname.startswith(f"{__name__}."):
                return importlib.util.spec_from_loader(fullname, self)
            return None

        def create_module(self, spec: ModuleSpec) -> ModuleType:
            return importlib.import_module(f"mapets_rl.{spec.name}")

        def exec_module(self, module: ModuleType) -> None:
            """The module ran once, under its new name."""

    __path__ = []  # no submodule of this name on disk: the finder gives them
    sys.meta_path.insert(0, _NewName())
