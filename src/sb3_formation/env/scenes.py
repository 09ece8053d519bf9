"""The scenes registry: every way the package places an episode, by name.

A task's ``scenes`` (:attr:`FormationConfig.scenes`) names an entry of :data:`SCENES`, a
:class:`~sb3_formation.env.scenarios.Scenes` that draws one :class:`~sb3_formation.env.scenarios.Scenario` per
episode: ``"curriculum"``, the thesis's stages (:mod:`~sb3_formation.env.curriculum`); ``"passage"``,
``"corridor"``, ``"trap"`` and ``"clutter"``, the scene families (:mod:`~sb3_formation.env.families`);
``"mixed"``, one family drawn per episode; the families with moving obstacles, ``"crowd"``, ``"crowd-blind"`` and
``"passage-moving"``, ``"corridor-moving"``, ``"trap-moving"``, ``"clutter-moving"``; and ``"mixed-moving"``, one of
them drawn per episode; ``"crossing"`` and ``"crossing-4"``, formations that cross each other's way
(:class:`~sb3_formation.env.families.CrossingScenes`). A new way of placing episodes is one more entry here; nothing
else in the package names a scene.
"""

from __future__ import annotations

import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.curriculum import Curriculum
from sb3_formation.env.families import CROSSING_SCENES, MOVING_FAMILIES, SCENE_FAMILIES, MixedScenes
from sb3_formation.env.scenarios import Scenario, Scenes

#: Every value ``FormationConfig.scenes`` may take, and what it draws.
SCENES: dict[str, Scenes] = {
    "curriculum": Curriculum(),
    **SCENE_FAMILIES,
    "mixed": MixedScenes("one of the scene families, drawn uniformly per episode", tuple(SCENE_FAMILIES.values())),
    **MOVING_FAMILIES,
    "mixed-moving": MixedScenes(
        "one of the scene families with moving obstacles, drawn uniformly per episode", tuple(MOVING_FAMILIES.values())
    ),
    **CROSSING_SCENES,
}
#: The scenes a task has unless it names others (:attr:`FormationConfig.scenes`'s default).
DEFAULT_SCENES: str = FormationConfig.scenes
#: The scene sets ``sb3-formation benchmark`` plays, in its table's order.
BENCHMARK_SCENES: tuple[str, ...] = tuple(name for name, scenes in SCENES.items() if scenes.benchmarked)


def scenes_named(name: str) -> Scenes:
    """The entry of :data:`SCENES` called ``name``.

    :raises ValueError: an unknown name (the known ones are listed)
    """
    if not isinstance(name, str) or name not in SCENES:
        raise ValueError(f"FormationConfig.scenes={name!r} is invalid: it must be one of {tuple(SCENES)}")
    return SCENES[name]


def draw_scenario(config: FormationConfig, stage: int, rng: np.random.Generator) -> Scenario:
    """The next episode's placement: a draw of ``config.scenes`` at ``stage`` from ``rng``."""
    return scenes_named(config.scenes).draw(config, stage, rng)


def check_scenes_fit(config: FormationConfig) -> None:
    """Refuse, with a one-line message, an unknown ``config.scenes`` or a world in which it cannot place the team.

    :raises ValueError: naming the scenes, the world and what to change
    """
    scenes_named(config.scenes).check_fits(config)


def scene_slots(config: FormationConfig) -> tuple[int, int]:
    """The most circles and walls a scenario of ``config.scenes`` has: the room ``state()`` keeps for them."""
    return scenes_named(config.scenes).slots(config)
