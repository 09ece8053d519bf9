"""Scene families: seeded generators of scenes whose obstacles block the way, entries of the scenes registry.

A family (:class:`SceneFamily`) is data: the ranges of its parameters (in metres or in the team's own widths) and the
function that builds a scene from values drawn in them; a new family is one more entry of :data:`SCENE_FAMILIES`.
Sizes scale with the team: D_0 = 2 (r_0 + R_a) is the width of the starting formation (2.56 m for the thesis's
n = 6), D_min = 2 (R_a / sin(pi / n) + R_a) the width of the smallest formation, neighbours touching (1.2 m for
n = 6) (:mod:`~sb3_formation.env.clearance`).

Every family builds its scene travelling in +x, then mirrors it left to right with probability 1/2. The team starts
in its starting formation, agents in order; the reward stage is the task's (placements do not depend on it). Every
drawn scene is checked: a centroid path must exist along which the smallest formation clears every shape by
:data:`SOLVABLE_MARGIN` (:func:`~sb3_formation.env.clearance.reachable`); a draw that fails is drawn again, at most
``max_placement_tries`` times.

A family may add moving obstacles (:class:`Traffic`, :mod:`~sb3_formation.env.movers`): each goes back and forth on a
line that crosses the straight way from the start to the goal. The moving families (:data:`MOVING_FAMILIES`) are a
crowd of pedestrians in an empty world, walking across it (``crowd``: they react to the agents; ``crowd-blind``: they
do not, and walk no faster than the agents), and each static family with 2-4 obstacles that slide to and fro across
the way (``passage-moving``, ...). Solvability is judged on the static shapes only: a mover may block the way for a
while, never for good (it keeps moving).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from sb3_formation.env.clearance import ClearanceMap, reachable, shrunk_footprint, start_footprint
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.movers import Mover
from sb3_formation.env.scenarios import PlacementError, Scenario, Scenes, start_formation
from sb3_formation.env.shapes import shape_gaps

#: Thickness (m) of the families' walls.
WALL_THICKNESS = 0.2
#: Room (m) the smallest formation keeps from every shape along the path that makes a scene solvable.
SOLVABLE_MARGIN = 0.05
#: Room (m) a drawn start formation keeps from every shape and the border, and the goal from every shape.
PLACEMENT_ROOM = 0.3


class SceneDraft(NamedTuple):
    """A scene as a family's build function lays it out, in the +x frame (m)."""

    start: np.ndarray  #: ``(2,)`` the starting centroid
    goal: np.ndarray  #: ``(2,)``
    circles: np.ndarray  #: ``(m, 3)``
    walls: np.ndarray  #: ``(w, 5)``


@dataclass(frozen=True)
class FormationWidths:
    """The widths of a team's formations, which a scene family's sizes scale with (m).

    :param start: D_0, the starting formation's width
    :param smallest: D_min, the smallest formation's width
    :param footprint: r_0 + R_a, the starting formation's footprint radius
    """

    start: float
    smallest: float
    footprint: float

    @classmethod
    def of(cls, config: FormationConfig) -> FormationWidths:
        """The widths of ``config``'s team."""
        return cls(2 * start_footprint(config), 2 * shrunk_footprint(config), start_footprint(config))


@dataclass(frozen=True)
class Traffic:
    """The moving obstacles a family adds to its scenes: each goes back and forth on a line across the straight way
    from the start to the goal, crossing it at a point drawn uniformly from :data:`TRAFFIC_CROSSINGS` of the way, at
    an angle within 30 degrees of square to it, starting at a point of its line drawn uniformly. Its line keeps
    :data:`PLACEMENT_ROOM` (plus its radius) from the starting formation, the static shapes and the border.

    :param count: the fewest and most movers, drawn uniformly
    :param speed: their speeds' range, in shares of the agents' v_max
    :param radius: their radii's range (m)
    :param reach: how far (m) a line reaches on each side of the way, drawn uniformly; a walker's line is cut at the
        world's border (less the room), so a long reach crosses the whole world
    :param motion: ``"path"`` or ``"walk"`` (:data:`~sb3_formation.env.movers.MOTIONS`)
    :param reacts: walkers see and avoid the agents
    """

    count: tuple[int, int]
    speed: tuple[float, float]
    radius: tuple[float, float]
    reach: tuple[float, float]
    motion: str = "path"
    reacts: bool = False

    def draw(
        self, config: FormationConfig, draft: SceneDraft, widths: FormationWidths, rng: np.random.Generator
    ) -> tuple[Mover, ...]:
        """The movers of one scene drawn for ``draft`` (+x frame).

        :raises _NoRoom: no line clear of the shapes was found for one of them
        """
        start, goal = draft.start, draft.goal
        way = (goal - start) / math.hypot(*(goal - start).tolist())
        movers = []
        for _ in range(int(rng.integers(self.count[0], self.count[1] + 1))):
            radius = float(rng.uniform(*self.radius))
            speed = float(rng.uniform(*self.speed)) * config.v_max
            for _ in range(50):
                line = self._line(config, draft, way, radius, rng)
                if line is not None and _clear_line(config, draft, widths, line, radius):
                    break
            else:
                raise _NoRoom
            first, second = line
            middle = first + float(rng.uniform(0.05, 0.95)) * (second - first)
            waypoints = np.array([middle, second, first])
            movers.append(Mover(radius, waypoints, speed, self.motion, reacts=self.reacts))
        return tuple(movers)

    def _line(
        self, config: FormationConfig, draft: SceneDraft, way: np.ndarray, radius: float, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Both ends of one mover's line, or ``None`` when a drawn end lies outside the world."""
        crossing = draft.start + float(rng.uniform(*TRAFFIC_CROSSINGS)) * (draft.goal - draft.start)
        angle = math.atan2(way[1], way[0]) + math.pi / 2 + float(rng.uniform(-math.pi / 6, math.pi / 6))
        direction = np.array([math.cos(angle), math.sin(angle)])
        room = radius + PLACEMENT_ROOM
        ends = []
        for sign in (1.0, -1.0):
            reach = float(rng.uniform(*self.reach))
            if self.motion == "walk":  # walkers cross the whole world when the reach allows
                reach = min(reach, _reach_inside(crossing, sign * direction, room, config))
            ends.append(crossing + sign * reach * direction)
        low, high = np.array([room, room]), np.array([config.world_width - room, config.world_height - room])
        if any(np.any(end < low) or np.any(end > high) for end in ends):
            return None
        return ends[0], ends[1]


#: The share of the straight way from the start to the goal at which a mover's line crosses it (drawn uniformly).
TRAFFIC_CROSSINGS = (0.25, 0.85)


def _reach_inside(point: np.ndarray, direction: np.ndarray, room: float, config: FormationConfig) -> float:
    """How far (m) from ``point`` along the unit ``direction`` the world's border, less ``room``, is."""
    reach = math.inf
    for axis, size in ((0, config.world_width), (1, config.world_height)):
        if direction[axis] > 1e-9:
            reach = min(reach, (size - room - point[axis]) / direction[axis])
        elif direction[axis] < -1e-9:
            reach = min(reach, (room - point[axis]) / direction[axis])
    return max(reach, 0.0)


def _clear_line(
    config: FormationConfig, draft: SceneDraft, widths: FormationWidths, line: tuple[np.ndarray, np.ndarray], radius: float
) -> bool:
    """Whether a mover of ``radius`` on ``line`` keeps :data:`PLACEMENT_ROOM` from the starting formation's footprint,
    every static shape and the border (checked at points 5 cm apart)."""
    first, second = line
    points = first + np.linspace(0.0, 1.0, max(2, int(math.hypot(*(second - first).tolist()) / 0.05) + 1))[:, None] * (
        second - first
    )
    room = radius + PLACEMENT_ROOM
    to_start = np.hypot(*(points - draft.start).T)
    if np.any(to_start < widths.footprint + room):
        return False
    gaps = shape_gaps(points, draft.circles, draft.walls, config.world_width, config.world_height)
    return bool(np.all(gaps >= room - 1e-9))  # a walker's end lies on the border less the room, up to rounding


@dataclass(frozen=True)
class SceneFamily(Scenes):
    """A family of scenes: ranges of its parameters, and the function that builds a scene from one draw of them.

    :param name: its name in the registry
    :param description: one line, for the docs and ``--help``
    :param ranges: parameter -> (low, high, unit), drawn uniformly; unit ``"D0"`` or ``"Dmin"`` multiplies both ends
        by that size of the team, ``"Dmin-D0"`` the low end by D_min and the high end by D_0, ``"W"`` both by the
        world's width; ``"m"`` and ``""`` take them as they are, and with ``""`` and two integer ends an integer is drawn
    :param build: (drawn values in metres, world width, world height, the team's widths, rng) -> a
        :class:`SceneDraft` in the +x frame, or ``None`` when the values leave no room
    :param max_circles: the most static circles a scene of the family has
    :param max_walls: the most walls
    :param traffic: the moving obstacles added to each scene, if any
    """

    name: str
    description: str
    ranges: dict[str, tuple[float, float, str]]
    build: Callable[[dict[str, float], float, float, FormationWidths, np.random.Generator], SceneDraft | None]
    max_circles: int
    max_walls: int
    traffic: Traffic | None = None

    def draw_values(self, widths: FormationWidths, width: float, rng: np.random.Generator) -> dict[str, float]:
        """One draw of the family's parameters, in metres (or counts)."""
        scales = {"D0": (widths.start,) * 2, "Dmin": (widths.smallest,) * 2, "Dmin-D0": (widths.smallest, widths.start)}
        scales |= {"W": (width, width), "m": (1.0, 1.0), "": (1.0, 1.0)}
        values = {}
        for name, (low, high, unit) in self.ranges.items():
            if unit == "" and float(low).is_integer() and float(high).is_integer():
                values[name] = float(rng.integers(int(low), int(high) + 1))
            else:
                values[name] = float(rng.uniform(low * scales[unit][0], high * scales[unit][1]))
        return values

    def draw(self, config: FormationConfig, stage: int, rng: np.random.Generator) -> Scenario:
        """Draw a scene from ``rng``: build it, mirror it with probability 1/2, put the starting formation at its start,
        and keep it if the formation, the goal and every wall lie in the world clear of the shapes and the scene is
        solvable; else draw again (the stage does not change the placements)."""
        widths, width, height = FormationWidths.of(config), config.world_width, config.world_height
        for _ in range(config.max_placement_tries):
            try:
                draft = self.build(self.draw_values(widths, width, rng), width, height, widths, rng)
                if draft is None:
                    continue
                movers = () if self.traffic is None else self.traffic.draw(config, draft, widths, rng)
            except _NoRoom:
                continue
            start, goal, circles, walls = draft
            if rng.random() < 0.5:
                start, goal = np.array([width - start[0], start[1]]), np.array([width - goal[0], goal[1]])
                circles = circles * [-1.0, 1.0, 1.0] + [width, 0.0, 0.0]
                walls = walls * [-1.0, 1.0, -1.0, 1.0, 1.0] + [width, 0.0, width, 0.0, 0.0]
                movers = tuple(replace(mover, waypoints=mover.waypoints * [-1.0, 1.0] + [width, 0.0]) for mover in movers)
            positions = start_formation(config, start)
            if _fits(config, positions, goal, circles, walls) and is_solvable(config, start, goal, circles, walls):
                return Scenario(positions, goal, circles, walls, movers=movers)
        raise PlacementError(
            f"could not draw a solvable {self.name!r} scene in the {width:g} m x {height:g} m world for a team of "
            f"{config.n_agents} in {config.max_placement_tries} tries: enlarge the world or shrink the formation"
        )

    def slots(self, config: FormationConfig) -> tuple[int, int]:
        return self.max_circles + (0 if self.traffic is None else self.traffic.count[1]), self.max_walls

    def obstacle_speed(self, config: FormationConfig) -> float:
        return 0.0 if self.traffic is None else self.traffic.speed[1] * config.v_max


@dataclass(frozen=True)
class MixedScenes(Scenes):
    """Scenes of several families: each episode draws one of them, uniformly, then its scene.

    :param description: one line, for the docs and ``--help``
    :param families: the families drawn from
    """

    description: str
    families: tuple[SceneFamily, ...]
    benchmarked = False

    def draw(self, config: FormationConfig, stage: int, rng: np.random.Generator) -> Scenario:
        return self.families[int(rng.integers(len(self.families)))].draw(config, stage, rng)

    def check_fits(self, config: FormationConfig) -> None:
        for family in self.families:
            family.check_fits(config)

    def slots(self, config: FormationConfig) -> tuple[int, int]:
        circles, walls = zip(*(family.slots(config) for family in self.families))
        return max(circles), max(walls)

    def obstacle_speed(self, config: FormationConfig) -> float:
        return max(family.obstacle_speed(config) for family in self.families)


class _NoRoom(Exception):
    """The drawn values leave no room for a part of the scene: draw again."""


def _between(rng: np.random.Generator, low: float, high: float) -> float:
    """A uniform draw in [low, high]; :class:`_NoRoom` when the interval is empty."""
    if high < low:
        raise _NoRoom
    return float(rng.uniform(low, high))


def _vertical_wall_with_gap(x: float, gap_low: float, gap_high: float, height: float) -> list[list[float]]:
    """Two walls along x = ``x`` from the floor and from the ceiling, leaving [gap_low, gap_high] open between their
    surfaces."""
    half = WALL_THICKNESS / 2
    return [[x, 0.0, x, gap_low - half, WALL_THICKNESS], [x, gap_high + half, x, height, WALL_THICKNESS]]


def _passage(
    values: dict[str, float], width: float, height: float, widths: FormationWidths, rng: np.random.Generator
) -> SceneDraft:
    opening, x = values["opening"], values["wall_x"]
    centre = _between(rng, opening / 2 + 0.5, height - opening / 2 - 0.5)
    walls = _vertical_wall_with_gap(x, centre - opening / 2, centre + opening / 2, height)
    start = np.array(
        [_between(rng, widths.footprint + PLACEMENT_ROOM, x - widths.footprint - 1.0), _start_y(widths, height, rng)]
    )
    goal = np.array([_between(rng, x + 1.5, width - 1.0), _between(rng, 1.0, height - 1.0)])
    return SceneDraft(start, goal, np.zeros((0, 3)), np.array(walls))


def _corridor(
    values: dict[str, float], width: float, height: float, widths: FormationWidths, rng: np.random.Generator
) -> SceneDraft:
    channel, length, x = values["width"], values["length"], values["barrier_x"]
    centre = _between(rng, channel / 2 + 0.5, height - channel / 2 - 0.5)
    low, high = centre - channel / 2 - WALL_THICKNESS / 2, centre + channel / 2 + WALL_THICKNESS / 2
    walls = _vertical_wall_with_gap(x, centre - channel / 2, centre + channel / 2, height)
    walls += [[x - length / 2, y, x + length / 2, y, WALL_THICKNESS] for y in (low, high)]
    start_x_high = x - length / 2 - widths.footprint - 0.5
    start = np.array([_between(rng, widths.footprint + PLACEMENT_ROOM, start_x_high), _start_y(widths, height, rng)])
    goal = np.array([_between(rng, x + length / 2 + 1.0, width - 1.0), _between(rng, 1.0, height - 1.0)])
    return SceneDraft(start, goal, np.zeros((0, 3)), np.array(walls))


def _trap(
    values: dict[str, float], width: float, height: float, widths: FormationWidths, rng: np.random.Generator
) -> SceneDraft:
    inner, depth = values["inner_width"], values["depth"]
    start = np.array([_between(rng, widths.footprint + PLACEMENT_ROOM, 0.2 * width), _start_y(widths, height, rng)])
    goal = np.array([_between(rng, 0.8 * width, width - 1.0), _between(rng, 1.0, height - 1.0)])
    along = (goal - start) / np.linalg.norm(goal - start)
    across = np.array([-along[1], along[0]])
    back = start + values["position"] * (goal - start)  # the middle of the U's back wall
    half = inner / 2 + WALL_THICKNESS / 2
    corners = [back + half * across, back - half * across]
    mouth = [corner - depth * along for corner in corners]
    walls = [[*corners[0], *corners[1]], [*corners[0], *mouth[0]], [*corners[1], *mouth[1]]]
    return SceneDraft(start, goal, np.zeros((0, 3)), np.array([[*wall, WALL_THICKNESS] for wall in walls]))


def _clutter(
    values: dict[str, float], width: float, height: float, widths: FormationWidths, rng: np.random.Generator
) -> SceneDraft | None:
    circles: list[list[float]] = []
    band = (0.3 * width, 0.7 * width)
    for _ in range(50 * int(values["count"])):
        if len(circles) == int(values["count"]):
            break
        radius = _between(rng, values["radius_low"], values["radius_high"])
        x, y = _between(rng, *band), _between(rng, 0.0, height)
        if all(math.hypot(x - cx, y - cy) - radius - r >= values["gap"] for cx, cy, r in circles):
            circles.append([x, y, radius])
    if len(circles) < int(values["count"]):  # no room left for them all
        return None
    start = np.array([_between(rng, widths.footprint + PLACEMENT_ROOM, band[0] - 0.5), _start_y(widths, height, rng)])
    goal = np.array([_between(rng, band[1] + 0.5, width - 1.0), _between(rng, 1.0, height - 1.0)])
    return SceneDraft(start, goal, np.array(circles).reshape(-1, 3), np.zeros((0, 5)))


def _open(
    values: dict[str, float], width: float, height: float, widths: FormationWidths, rng: np.random.Generator
) -> SceneDraft:
    """No static shape: the team starts near the left border, the goal lies in the right fifth of the world."""
    start = np.array([_between(rng, widths.footprint + PLACEMENT_ROOM, 0.15 * width), _start_y(widths, height, rng)])
    goal = np.array([_between(rng, 0.8 * width, width - 1.0), _between(rng, 1.0, height - 1.0)])
    return SceneDraft(start, goal, np.zeros((0, 3)), np.zeros((0, 5)))


def _start_y(widths: FormationWidths, height: float, rng: np.random.Generator) -> float:
    return _between(rng, widths.footprint + PLACEMENT_ROOM, height - widths.footprint - PLACEMENT_ROOM)


_FAMILIES = (
    SceneFamily(
        "passage",
        "a wall across the world with one opening, from a little wider than the smallest formation to wider than the "
        "starting one",
        {"opening": (1.15, 1.1, "Dmin-D0"), "wall_x": (0.4, 0.6, "W")},
        _passage,
        max_circles=0,
        max_walls=2,
    ),
    SceneFamily(
        "corridor",
        "a walled channel narrower than the starting formation, 1.5-2.5 formation widths long, through a wall across "
        "the world",
        {"width": (1.15, 0.9, "Dmin-D0"), "length": (1.5, 2.5, "D0"), "barrier_x": (0.45, 0.55, "W")},
        _corridor,
        max_circles=0,
        max_walls=4,
    ),
    SceneFamily(
        "trap",
        "a U of three walls on the straight line to the goal, opening towards the team, wide and deep enough to hold it",
        {"inner_width": (1.2, 1.6, "D0"), "depth": (0.8, 1.2, "D0"), "position": (0.45, 0.6, "")},
        _trap,
        max_circles=0,
        max_walls=3,
    ),
    SceneFamily(
        "clutter",
        "8-12 circles of radius 0.3-0.6 m in the middle of the world, gaps at least a little wider than the smallest "
        "formation",
        {
            "count": (8, 12, ""),
            "radius_low": (0.3, 0.3, "m"),
            "radius_high": (0.6, 0.6, "m"),
            "gap": (1.1, 1.1, "Dmin"),
        },
        _clutter,
        max_circles=12,
        max_walls=0,
    ),
)
#: The scene families by name (ranges: see :class:`SceneFamily`).
SCENE_FAMILIES: dict[str, SceneFamily] = {family.name: family for family in _FAMILIES}

#: Pedestrians crossing the world (their reach lets every line run from border to border).
_CROWD = Traffic(count=(5, 20), speed=(0.5, 1.5), radius=(0.2, 0.3), reach=(20.0, 20.0), motion="walk", reacts=True)
#: Obstacles sliding to and fro across the way through a static family's scene.
_SLIDERS = Traffic(count=(2, 4), speed=(0.5, 1.5), radius=(0.2, 0.4), reach=(1.0, 3.0))
_MOVING = (
    SceneFamily(
        "crowd",
        "5-20 pedestrians (navground's ORCA, radius 0.2-0.3 m) walking to and fro across an empty world at 0.5-1.5 "
        "times v_max, avoiding the agents",
        {},
        _open,
        max_circles=0,
        max_walls=0,
        traffic=_CROWD,
    ),
    SceneFamily(
        "crowd-blind",
        "the crowd's pedestrians at 0.5-1 times v_max, walking as if the agents were not there",
        {},
        _open,
        max_circles=0,
        max_walls=0,
        traffic=replace(_CROWD, speed=(0.5, 1.0), reacts=False),
    ),
    *(
        replace(
            family,
            name=f"{family.name}-moving",
            description=f"{family.name}, with 2-4 obstacles (radius 0.2-0.4 m) sliding to and fro across the way at "
            "0.5-1.5 times v_max",
            traffic=_SLIDERS,
        )
        for family in _FAMILIES
    ),
)
#: The scene families with moving obstacles by name.
MOVING_FAMILIES: dict[str, SceneFamily] = {family.name: family for family in _MOVING}


@dataclass(frozen=True)
class CrossingScenes(Scenes):
    """Formations whose straight ways to their goals cross near the centre of an empty world
    (:attr:`~sb3_formation.env.scenarios.Scenes.formations` of them, each a team of the engine).

    Formation j flies along the direction ``theta_j`` through a centre drawn within :data:`CROSSING_JITTER` of the
    world's: it starts in its starting formation as far back along ``theta_j`` as the world holds it
    (:data:`PLACEMENT_ROOM` from the border), and its goal lies as far ahead, so every way is a diameter through the
    centre. ``theta_0`` is drawn uniformly; with two formations ``theta_1`` is 60-120 degrees from it (either side),
    with four ``theta_j = theta_0 + j 90 degrees`` each turned by up to 10 degrees (two pairs flying head-on, as
    navground's ``Cross``). A draw whose starting formations come within ``PLACEMENT_ROOM`` of each other, or whose
    ways are shorter than :data:`CROSSING_MIN_WAY` of the world's height, is drawn again.

    :param name: its name in the registry
    :param description: one line, for the docs and ``--help``
    :param formations: 2 or 4
    """

    name: str
    description: str
    formations: int = 2

    def draw(self, config: FormationConfig, stage: int, rng: np.random.Generator) -> Scenario:
        raise ValueError(
            f"the {self.name!r} scenes place {self.formations} formations together: draw them with draw_formations"
        )

    def draw_formations(self, config: FormationConfig, stage: int, rng: np.random.Generator) -> tuple[Scenario, ...]:
        width, height, room = config.world_width, config.world_height, start_footprint(config) + PLACEMENT_ROOM
        for _ in range(config.max_placement_tries):
            centre = np.array([width / 2, height / 2]) + rng.uniform(-CROSSING_JITTER, CROSSING_JITTER, 2)
            first = float(rng.uniform(0.0, 2 * math.pi))
            if self.formations == 2:
                turns = [0.0, float(rng.choice([-1.0, 1.0]) * rng.uniform(math.pi / 3, 2 * math.pi / 3))]
            else:
                turns = [j * math.pi / 2 + float(rng.uniform(-1.0, 1.0)) * math.radians(10) for j in range(4)]
            placed = []
            for turn in turns:
                direction = np.array([math.cos(first + turn), math.sin(first + turn)])
                reach = min(_reach_inside(centre, -direction, room, config), _reach_inside(centre, direction, room, config))
                placed.append((centre - reach * direction, centre + reach * direction, reach))
            starts = np.array([start for start, _, _ in placed])
            apart = np.hypot(*(starts[:, None] - starts[None, :]).transpose(2, 0, 1))[np.triu_indices(len(starts), 1)]
            if min(reach for _, _, reach in placed) >= CROSSING_MIN_WAY / 2 * height and apart.min() >= 2 * room:
                return tuple(Scenario(start_formation(config, start), goal) for start, goal, _ in placed)
        raise PlacementError(
            f"could not draw a {self.name!r} scene in the {width:g} m x {height:g} m world for {self.formations} "
            f"formations of {config.n_agents} in {config.max_placement_tries} tries: enlarge the world or shrink "
            "the formation"
        )

    def slots(self, config: FormationConfig) -> tuple[int, int]:
        return (self.formations - 1) * config.n_agents, 0  # the other formations' agents are circles of a scan


#: m: how far a crossing's centre lies from the world's centre, at most in x and in y
CROSSING_JITTER = 0.5
#: the shortest way of a crossing's formation, in shares of the world's height (diameters through the centre)
CROSSING_MIN_WAY = 0.5
#: The crossing scenes by name.
CROSSING_SCENES: dict[str, CrossingScenes] = {
    scenes.name: scenes
    for scenes in (
        CrossingScenes(
            "crossing",
            "two formations crossing each other's way at 60-120 degrees near the centre of an empty world",
            formations=2,
        ),
        CrossingScenes(
            "crossing-4",
            "four formations crossing near the centre of an empty world, two pairs head-on at about 90 degrees",
            formations=4,
        ),
    )
}


def _fits(config: FormationConfig, positions: np.ndarray, goal: np.ndarray, circles: np.ndarray, walls: np.ndarray) -> bool:
    """The formation inside the world and :data:`PLACEMENT_ROOM` clear of every shape and the border, the goal area
    (eta_g around the goal) clear of every shape and the border, every wall's ends in the world."""
    width, height = config.world_width, config.world_height
    ends = walls[:, :4].reshape(-1, 2)
    if np.any(ends < 0) or np.any(ends > [width, height]):
        return False
    agents = shape_gaps(positions, circles, walls, width, height)
    goal_gap = shape_gaps(goal[None, :], circles, walls, width, height)[0]
    inside = 0 <= goal[0] <= width and 0 <= goal[1] <= height
    return bool(inside and np.all(agents >= config.agent_radius + PLACEMENT_ROOM) and goal_gap >= config.eta_g)


def is_solvable(config: FormationConfig, start: np.ndarray, goal: np.ndarray, circles: np.ndarray, walls: np.ndarray) -> bool:
    """Whether the smallest formation (:func:`~sb3_formation.env.clearance.shrunk_footprint`) can carry the centroid
    from ``start`` to within eta_g of ``goal`` keeping :data:`SOLVABLE_MARGIN` from every shape and the border."""
    clearance = ClearanceMap.of(config, circles, walls)
    return reachable(clearance, start, goal, config.eta_g, shrunk_footprint(config) + SOLVABLE_MARGIN)
