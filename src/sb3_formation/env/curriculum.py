"""The thesis's curriculum placements, as one entry of the scenes registry (:class:`Curriculum`).

The thesis gives placements in pixels with 1 px = 1 cm (sections 4.3 and 5.3); :data:`CHAPTER_PLACEMENTS` converts
them to metres once, here. They are the thesis's 15 m x 10 m world's (:data:`THESIS_WORLD`); in a world of another
size the positions scale with its width and height (:meth:`ChapterPlacements.fitted`; radii stay), and a world in
which the starting formation does not fit at the scaled start positions is refused (:meth:`Curriculum.check_fits`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import cast

import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.scenarios import PlacementError, Scenario, Scenes, start_formation

CM = 0.01  #: one thesis pixel (m)


@dataclass(frozen=True)
class ChapterPlacements:
    """Placement rules of one thesis chapter, in metres.

    :param goal_x: the goal's possible x
    :param start_x: stage 3: the centroid's possible x (the one differing from, and furthest from, the goal's x)
    :param stage1_obstacle_x: stage 1-2: the two x ranges of the large obstacles (the one further from the centroid is used)
    :param stage3_obstacle_x: stage 3: x range of the obstacles
    :param stage3_radii: stage 3: obstacle radii
    """

    goal_x: tuple[float, ...]
    start_x: tuple[float, ...]
    stage1_obstacle_x: tuple[tuple[float, float], tuple[float, float]]
    stage3_obstacle_x: tuple[float, float]
    stage3_radii: tuple[float, ...]
    goal_y: tuple[float, float] = (200 * CM, 800 * CM)  # goal y uniform in [200, 800] cm
    start_y: tuple[float, float] = (200 * CM, 800 * CM)  # centroid y is 200 or 800 cm, whichever is further from the goal
    obstacle_y: tuple[float, float] = (100 * CM, 900 * CM)  # obstacle y uniform in [100, 900] cm
    stage1_large_radius: float = 200 * CM  # three large obstacles of radius 200 cm
    stage1_large_count: int = 3
    stage1_small_radius: float = 70 * CM  # one small obstacle of radius 70 cm at the centroid-goal mid-point

    def fitted(self, width: float, height: float) -> ChapterPlacements:
        """The placements with every x scaled by ``width`` / 15 m and every y by ``height`` / 10 m (:data:`THESIS_WORLD`);
        radii unchanged. The thesis's world gets them unchanged.

        :param width: the world's width (m)
        :param height: the world's height (m)
        """
        if (width, height) == THESIS_WORLD:
            return self
        sx, sy = width / THESIS_WORLD[0], height / THESIS_WORLD[1]
        return dataclasses.replace(
            self,
            goal_x=tuple(x * sx for x in self.goal_x),
            start_x=tuple(x * sx for x in self.start_x),
            stage1_obstacle_x=cast(  # two ranges, as in self
                "tuple[tuple[float, float], tuple[float, float]]",
                tuple((low * sx, high * sx) for low, high in self.stage1_obstacle_x),
            ),
            stage3_obstacle_x=(self.stage3_obstacle_x[0] * sx, self.stage3_obstacle_x[1] * sx),
            goal_y=(self.goal_y[0] * sy, self.goal_y[1] * sy),
            start_y=(self.start_y[0] * sy, self.start_y[1] * sy),
            obstacle_y=(self.obstacle_y[0] * sy, self.obstacle_y[1] * sy),
        )


#: The world of the thesis's placements (m): 1500 x 1000 px (sections 4.3, 5.3).
THESIS_WORLD = (1500 * CM, 1000 * CM)


#: Thesis 4.3 (chapter 4) and 5.3 (chapter 5), converted from cm.
CHAPTER_PLACEMENTS: dict[str, ChapterPlacements] = {
    "ch4": ChapterPlacements(
        goal_x=(400 * CM, 1000 * CM),
        start_x=(400 * CM, 1000 * CM),
        stage1_obstacle_x=((400 * CM, 700 * CM), (700 * CM, 1000 * CM)),
        stage3_obstacle_x=(400 * CM, 1000 * CM),
        stage3_radii=(80 * CM, 50 * CM, 50 * CM),  # one large (80 cm), two smaller (50 cm)
    ),
    "ch5": ChapterPlacements(
        goal_x=(400 * CM, 1100 * CM),
        start_x=(400 * CM, 1000 * CM),
        stage1_obstacle_x=((400 * CM, 750 * CM), (750 * CM, 1100 * CM)),
        stage3_obstacle_x=(400 * CM, 1100 * CM),
        stage3_radii=(80 * CM, 80 * CM),  # two large (80 cm)
    ),
}


def chapter_placements(config: FormationConfig) -> ChapterPlacements:
    """The placements of ``config.chapter`` fitted to ``config``'s world (:meth:`ChapterPlacements.fitted`)."""
    return CHAPTER_PLACEMENTS[config.chapter].fitted(config.world_width, config.world_height)


def _draw_obstacles(
    placements: ChapterPlacements, stage: int, centroid: np.ndarray, goal: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    if stage == 3:
        radii = np.array(placements.stage3_radii)
        x_range = placements.stage3_obstacle_x
    else:
        radii = np.full(placements.stage1_large_count, placements.stage1_large_radius)
        x_range = max(placements.stage1_obstacle_x, key=lambda bounds: abs(0.5 * (bounds[0] + bounds[1]) - centroid[0]))
    xs = rng.uniform(*x_range, size=len(radii))
    ys = rng.uniform(*placements.obstacle_y, size=len(radii))
    obstacles = np.stack([xs, ys, radii], axis=1)
    if stage != 3:
        midpoint = 0.5 * (centroid + goal)
        obstacles = np.vstack([obstacles, [midpoint[0], midpoint[1], placements.stage1_small_radius]])
    return obstacles


def _obstacles_clear(config: FormationConfig, obstacles: np.ndarray, positions: np.ndarray, goal: np.ndarray) -> bool:
    centres, radii = obstacles[:, :2], obstacles[:, 2]
    to_agents = np.hypot(*(positions[:, None, :] - centres[None, :, :]).transpose(2, 0, 1))
    to_goal = np.hypot(*(centres - goal).T)
    clearance = config.placement_clearance
    return bool(
        np.all(to_agents >= radii + config.agent_radius + clearance) and np.all(to_goal >= radii + config.eta_g + clearance)
    )


class Curriculum(Scenes):
    """The thesis's curriculum (sections 4.3 and 5.3): the placements of ``config.chapter``, by stage.

    Stages 1 and 2 share their placements (the stages differ in reward terms): the centroid starts at the goal's x,
    the agents take the n-gon's vertices in random order in stage 1 and in order in stage 2; three large obstacles
    lie in the x range further from the centroid and one small one at the centroid-goal mid-point. Stage 3 puts the
    centroid at the other x, the agents in order, and the stage-3 obstacles anywhere in their range. A draw whose
    obstacles overlap the start formation or the goal area (with ``placement_clearance``) is drawn again, at most
    ``config.max_placement_tries`` times.
    """

    description = "the thesis's curriculum: its chapter's placements of stages 1-2 and of stage 3 (sections 4.3, 5.3)"
    staged = True

    def draw(self, config: FormationConfig, stage: int, rng: np.random.Generator) -> Scenario:
        """Draw a curriculum scenario of ``stage`` under ``config.chapter`` from ``rng`` (see the class docstring).

        :param config: task configuration
        :param stage: curriculum stage 1, 2 or 3
        :param rng: the environment's generator; the only source of randomness
        """
        if stage not in (1, 2, 3):
            raise ValueError(f"stage must be 1, 2 or 3, got {stage!r}")
        placements = chapter_placements(config)
        for _ in range(config.max_placement_tries):
            goal = np.array([rng.choice(placements.goal_x), rng.uniform(*placements.goal_y)])
            start_y = max(placements.start_y, key=lambda y: abs(y - goal[1]))
            if stage == 3:
                others = [x for x in placements.start_x if x != goal[0]]
                start_x = max(others, key=lambda x: abs(x - goal[0]))
                order = None
            else:
                start_x = goal[0]
                order = rng.permutation(config.n_agents) if stage == 1 else None
            positions = start_formation(config, np.array([start_x, start_y]), order)
            obstacles = _draw_obstacles(placements, stage, positions.mean(axis=0), goal, rng)
            if _obstacles_clear(config, obstacles, positions, goal):
                return Scenario(positions, goal, obstacles)
        raise PlacementError(
            f"could not place the stage-{stage} obstacles of chapter {config.chapter!r} clear of the start formation and "
            f"the goal in {config.max_placement_tries} tries (n_agents={config.n_agents}, "
            f"placement_clearance={config.placement_clearance} m)"
        )

    def check_fits(self, config: FormationConfig) -> None:
        """Refuse a world in which the starting formation would cross a wall at one of the (scaled) start positions.

        :raises ValueError: naming the world, the start position and the room the formation needs
        """
        placements = chapter_placements(config)
        reach = config.start_circumradius + config.agent_radius  # from the centroid to an agent's far edge
        for x in (*placements.start_x, *placements.goal_x):  # stages 1-2 start at the goal's x
            for y in placements.start_y:
                room = min(x, config.world_width - x, y, config.world_height - y)
                if room < reach:
                    raise ValueError(
                        f"the {config.world_width:g} m x {config.world_height:g} m world is too small for the curriculum "
                        f"of chapter {config.chapter!r}: a team starting at ({x:.2f}, {y:.2f}) m needs {reach:.2f} m to "
                        f"every wall, has {room:.2f} m; enlarge the world or shrink the formation (d_ref, eta_c, "
                        "formation_scale)"
                    )

    def slots(self, config: FormationConfig) -> tuple[int, int]:
        """Stages 1-2's large obstacles and small one, or stage 3's, whichever are more; no walls."""
        placements = CHAPTER_PLACEMENTS[config.chapter]
        return max(placements.stage1_large_count + 1, len(placements.stage3_radii)), 0
