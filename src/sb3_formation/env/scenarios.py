"""Scenarios: where the agents start, where the goal is, where the obstacles are; and the curriculum that draws them.

The thesis gives placements in pixels with 1 px = 1 cm (sections 4.3 and 5.3); :data:`CURRICULUM_LAYOUTS`
converts them to metres once, here. They are the thesis's 15 m x 10 m world's (:data:`THESIS_WORLD`); in a world of
another size the positions scale with its width and height (:meth:`CurriculumLayout.fitted`; radii stay), and a world
in which the starting formation does not fit at the scaled start positions is refused (:func:`check_world_fits`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.geometry import reference_polygon
from sb3_formation.env.shapes import as_walls, circle_gap, wall_gap

CM = 0.01  #: one thesis pixel (m)


@dataclass(frozen=True)
class Scenario:
    """A complete placement, in metres: ``Scenario(agent_positions, goal, obstacles, walls, headings)``.

    :param agent_positions: ``(n, 2)`` agent centres; row i is agent i
    :param goal: ``(2,)`` goal centre
    :param obstacles: ``(m, 3)`` static circles as (x, y, radius); may be empty
    :param walls: ``(w, 5)`` static walls as (x0, y0, x1, y1, thickness), capsules (:mod:`~sb3_formation.env.shapes`);
        may be empty
    :param headings: ``(n,)`` unicycle agents' starting headings (rad, anti-clockwise from +x); empty: every agent
        faces the goal from the starting centroid (holonomic agents have none, and ignore them)
    """

    agent_positions: np.ndarray
    goal: np.ndarray
    obstacles: np.ndarray | tuple[Any, ...] = ()
    walls: np.ndarray | tuple[Any, ...] = ()
    headings: np.ndarray | tuple[Any, ...] = ()

    def __post_init__(self) -> None:
        obstacles = _real_array("obstacles", self.obstacles)
        arrays = {
            "agent_positions": _real_array("agent_positions", self.agent_positions),
            "goal": _real_array("goal", self.goal),
            "obstacles": obstacles.reshape(0, 3) if obstacles.size == 0 else obstacles,
            "walls": as_walls(_real_array("walls", self.walls)),
            "headings": _real_array("headings", self.headings),
        }
        shapes = {"agent_positions": "(n, 2)", "goal": "(2,)", "obstacles": "(m, 3)", "walls": "(w, 5)", "headings": "(n,)"}
        columns = {"agent_positions": 2, "obstacles": 3, "walls": 5}
        for name, array in arrays.items():
            if name in columns:
                fits = array.ndim == 2 and array.shape[1] == columns[name]
            else:
                fits = array.ndim == 1 and (name == "headings" or len(array) == 2)
            if not fits:
                raise ValueError(f"Scenario.{name} must have shape {shapes[name]}, got {array.shape}")
            if not np.all(np.isfinite(array)):
                raise ValueError(f"Scenario.{name} contains NaN or infinite values")
            array.setflags(write=False)
            object.__setattr__(self, name, array)
        assert isinstance(self.obstacles, np.ndarray) and isinstance(self.walls, np.ndarray)  # set just above
        if np.any(self.obstacles[:, 2] <= 0):
            bad = int(np.flatnonzero(self.obstacles[:, 2] <= 0)[0])
            raise ValueError(f"Scenario obstacle {bad} has radius {self.obstacles[bad, 2]} m; radii must be > 0")
        if np.any(self.walls[:, 4] <= 0):
            bad = int(np.flatnonzero(self.walls[:, 4] <= 0)[0])
            raise ValueError(f"Scenario wall {bad} has thickness {self.walls[bad, 4]} m; thicknesses must be > 0")

    @property
    def centroid(self) -> np.ndarray:
        """Centroid (m) of the starting positions."""
        centroid: np.ndarray = self.agent_positions.mean(axis=0)
        return centroid

    def validate(self, config: FormationConfig) -> None:
        """Raise ``ValueError`` saying which agent is misplaced if the scenario does not fit ``config``.

        Checks: one position per agent, every agent inside the world, no two agents overlapping, no agent
        overlapping an obstacle or a wall, every obstacle's centre, every wall's ends and the goal inside the world (an
        obstacle may cross the border, as the curriculum's large ones may).
        """
        n_agents, radius = config.n_agents, config.agent_radius
        if len(self.agent_positions) != n_agents:
            raise ValueError(f"Scenario has {len(self.agent_positions)} agent positions but n_agents={n_agents}")
        if len(self.headings) not in (0, n_agents):
            raise ValueError(f"Scenario has {len(self.headings)} headings but n_agents={n_agents} (give n or none)")
        for index, (x, y) in enumerate(self.agent_positions):
            if not (radius <= x <= config.world_width - radius and radius <= y <= config.world_height - radius):
                raise ValueError(
                    f"Scenario: agent_{index} at ({x:.3f}, {y:.3f}) m is outside the world "
                    f"[0, {config.world_width}] x [0, {config.world_height}] m (radius {radius} m)"
                )
        offsets = self.agent_positions[:, None, :] - self.agent_positions[None, :, :]
        between = np.hypot(offsets[..., 0], offsets[..., 1])
        for first, second in zip(*np.nonzero(np.triu(between < 2 * radius, k=1))):
            raise ValueError(
                f"Scenario: agent_{first} and agent_{second} overlap ({between[first, second]:.3f} m apart, "
                f"need >= {2 * radius:.3f} m)"
            )
        for index, (x, y) in enumerate(self.agent_positions):
            for obstacle_index, circle in enumerate(self.obstacles):
                gap = circle_gap(x, y, circle) - radius
                if gap < 0:
                    raise ValueError(
                        f"Scenario: agent_{index} overlaps obstacle {obstacle_index} at ({circle[0]:.3f}, {circle[1]:.3f}) "
                        f"m radius {circle[2]:.3f} m by {-gap:.3f} m"
                    )
            for wall_index, wall in enumerate(self.walls):
                gap = wall_gap(x, y, wall) - radius
                if gap < 0:
                    raise ValueError(f"Scenario: agent_{index} overlaps wall {wall_index} by {-gap:.3f} m")
        points = [(f"obstacle {index}", x, y) for index, (x, y, _) in enumerate(self.obstacles)]
        for index, (x0, y0, x1, y1, _) in enumerate(self.walls):
            points += [(f"wall {index}'s end", x0, y0), (f"wall {index}'s end", x1, y1)]
        for name, x, y in points:
            if not (0 <= x <= config.world_width and 0 <= y <= config.world_height):
                raise ValueError(
                    f"Scenario: {name} at ({x:.3f}, {y:.3f}) m is outside the world "
                    f"[0, {config.world_width}] x [0, {config.world_height}] m"
                )
        gx, gy = self.goal
        if not (0 <= gx <= config.world_width and 0 <= gy <= config.world_height):
            raise ValueError(f"Scenario: goal ({gx:.3f}, {gy:.3f}) m is outside the world")
        shapes = [(f"obstacle {index}", circle_gap(gx, gy, circle)) for index, circle in enumerate(self.obstacles)]
        shapes += [(f"wall {index}", wall_gap(gx, gy, wall)) for index, wall in enumerate(self.walls)]
        for name, gap in shapes:
            if gap < 0:
                raise ValueError(f"Scenario: goal ({gx:.3f}, {gy:.3f}) m lies inside {name}, where no centroid can reach it")


def _real_array(name: str, values: Any) -> np.ndarray:
    """A field of :class:`Scenario` as a float64 array.

    :raises ValueError: ragged rows, or values that are not real numbers (naming the field)
    """
    try:
        array = np.asarray(values)
    except ValueError:  # numpy refuses rows of different lengths
        raise ValueError(f"Scenario.{name} must be a rectangular array: its rows differ in length") from None
    if array.size and array.dtype.kind not in "iuf":
        raise ValueError(f"Scenario.{name} must hold real numbers, got {array.dtype} values")
    return array.astype(np.float64)


@dataclass(frozen=True)
class CurriculumLayout:
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

    def fitted(self, width: float, height: float) -> CurriculumLayout:
        """The layout with every x scaled by ``width`` / 15 m and every y by ``height`` / 10 m (:data:`THESIS_WORLD`);
        radii unchanged. The thesis's world gets the layout itself.

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
CURRICULUM_LAYOUTS: dict[str, CurriculumLayout] = {
    "ch4": CurriculumLayout(
        goal_x=(400 * CM, 1000 * CM),
        start_x=(400 * CM, 1000 * CM),
        stage1_obstacle_x=((400 * CM, 700 * CM), (700 * CM, 1000 * CM)),
        stage3_obstacle_x=(400 * CM, 1000 * CM),
        stage3_radii=(80 * CM, 50 * CM, 50 * CM),  # one large (80 cm), two smaller (50 cm)
    ),
    "ch5": CurriculumLayout(
        goal_x=(400 * CM, 1100 * CM),
        start_x=(400 * CM, 1000 * CM),
        stage1_obstacle_x=((400 * CM, 750 * CM), (750 * CM, 1100 * CM)),
        stage3_obstacle_x=(400 * CM, 1100 * CM),
        stage3_radii=(80 * CM, 80 * CM),  # two large (80 cm)
    ),
}


class PlacementError(RuntimeError):
    """A scenario satisfying the placement rules could not be drawn within the allowed number of tries."""


def start_formation(config: FormationConfig, centroid: np.ndarray, order: np.ndarray | None = None) -> np.ndarray:
    """Agent positions (m) on the starting n-gon around ``centroid``; agent ``order[k]`` takes vertex k.

    :param config: task configuration (n, d_ref, eta_c, formation_scale)
    :param centroid: ``(2,)`` centroid (m)
    :param order: permutation of the agents over the vertices; ``None`` keeps agent i on vertex i
    """
    vertices: np.ndarray = reference_polygon(config.n_agents, config.start_circumradius) + centroid
    if order is None:
        return vertices
    positions = np.empty_like(vertices)
    positions[order] = vertices
    return positions


def curriculum_layout(config: FormationConfig) -> CurriculumLayout:
    """The placements of ``config.layout`` fitted to ``config``'s world (:meth:`CurriculumLayout.fitted`)."""
    return CURRICULUM_LAYOUTS[config.layout].fitted(config.world_width, config.world_height)


def check_world_fits(config: FormationConfig) -> None:
    """Refuse a world in which the starting formation would cross a wall at one of the (scaled) start positions.

    :raises ValueError: naming the world, the start position and the room the formation needs
    """
    layout = curriculum_layout(config)
    reach = config.start_circumradius + config.agent_radius  # from the centroid to an agent's far edge
    for x in (*layout.start_x, *layout.goal_x):  # stages 1-2 start at the goal's x
        for y in layout.start_y:
            room = min(x, config.world_width - x, y, config.world_height - y)
            if room < reach:
                raise ValueError(
                    f"the {config.world_width:g} m x {config.world_height:g} m world is too small for the curriculum of "
                    f"layout {config.layout!r}: a team starting at ({x:.2f}, {y:.2f}) m needs {reach:.2f} m to every "
                    f"wall, has {room:.2f} m; enlarge the world or shrink the formation (d_ref, eta_c, formation_scale)"
                )


def sample_scenario(config: FormationConfig, stage: int, rng: np.random.Generator) -> Scenario:
    """Draw a curriculum scenario of ``stage`` under ``config.layout`` from ``rng``.

    Stages 1 and 2 share their placements (the stages differ in reward terms): the centroid starts at the goal's x,
    the agents take the n-gon's vertices in random order in stage 1 and in order in stage 2; three large obstacles
    lie in the x range further from the centroid and one small one at the centroid-goal mid-point. Stage 3 puts the
    centroid at the other x, the agents in order, and the stage-3 obstacles anywhere in their range. A draw whose
    obstacles overlap the start formation or the goal area (with ``placement_clearance``) is drawn again, at most
    ``config.max_placement_tries`` times, then :class:`PlacementError` is raised.

    :param config: task configuration
    :param stage: curriculum stage 1, 2 or 3
    :param rng: the environment's generator; the only source of randomness
    """
    if stage not in (1, 2, 3):
        raise ValueError(f"stage must be 1, 2 or 3, got {stage!r}")
    layout = curriculum_layout(config)
    for _ in range(config.max_placement_tries):
        goal = np.array([rng.choice(layout.goal_x), rng.uniform(*layout.goal_y)])
        start_y = max(layout.start_y, key=lambda y: abs(y - goal[1]))
        if stage == 3:
            others = [x for x in layout.start_x if x != goal[0]]
            start_x = max(others, key=lambda x: abs(x - goal[0]))
            order = None
        else:
            start_x = goal[0]
            order = rng.permutation(config.n_agents) if stage == 1 else None
        positions = start_formation(config, np.array([start_x, start_y]), order)
        obstacles = _draw_obstacles(layout, stage, positions.mean(axis=0), goal, rng)
        if _obstacles_clear(config, obstacles, positions, goal):
            return Scenario(positions, goal, obstacles)
    raise PlacementError(
        f"could not place the stage-{stage} obstacles of layout {config.layout!r} clear of the start formation and the "
        f"goal in {config.max_placement_tries} tries (n_agents={config.n_agents}, "
        f"placement_clearance={config.placement_clearance} m)"
    )


def _draw_obstacles(
    layout: CurriculumLayout, stage: int, centroid: np.ndarray, goal: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    if stage == 3:
        radii = np.array(layout.stage3_radii)
        x_range = layout.stage3_obstacle_x
    else:
        radii = np.full(layout.stage1_large_count, layout.stage1_large_radius)
        x_range = max(layout.stage1_obstacle_x, key=lambda bounds: abs(0.5 * (bounds[0] + bounds[1]) - centroid[0]))
    xs = rng.uniform(*x_range, size=len(radii))
    ys = rng.uniform(*layout.obstacle_y, size=len(radii))
    obstacles = np.stack([xs, ys, radii], axis=1)
    if stage != 3:
        midpoint = 0.5 * (centroid + goal)
        obstacles = np.vstack([obstacles, [midpoint[0], midpoint[1], layout.stage1_small_radius]])
    return obstacles


def _obstacles_clear(config: FormationConfig, obstacles: np.ndarray, positions: np.ndarray, goal: np.ndarray) -> bool:
    centres, radii = obstacles[:, :2], obstacles[:, 2]
    to_agents = np.hypot(*(positions[:, None, :] - centres[None, :, :]).transpose(2, 0, 1))
    to_goal = np.hypot(*(centres - goal).T)
    clearance = config.placement_clearance
    return bool(
        np.all(to_agents >= radii + config.agent_radius + clearance) and np.all(to_goal >= radii + config.eta_g + clearance)
    )
