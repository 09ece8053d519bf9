"""The old name of :mod:`sb3_formation.experiment.recipes`, kept for one release: every name read here warns."""

from __future__ import annotations

from typing import Any

from sb3_formation.experiment import recipes
from sb3_formation.utils.deprecation import warn_renamed

#: Old names of this module -> their names in :mod:`~sb3_formation.experiment.recipes`.
RENAMED = {
    "SetUp": "Recipe",
    "load_setup": "load_recipe",
    "setup_names": "recipe_names",
    "SETUPS_FOLDER": "RECIPES_FOLDER",
    "DEFAULT_SETUP": "DEFAULT_RECIPE",
    "thesis_setup_for": "thesis_recipe_for",
}


def __getattr__(name: str) -> Any:
    new = RENAMED.get(name, name)
    if not hasattr(recipes, new):
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warn_renamed(f"sb3_formation.experiment.setups.{name}", f"sb3_formation.experiment.recipes.{new}")
    return getattr(recipes, new)
