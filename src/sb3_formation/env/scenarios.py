"""A scenario is one drawn placement of an episode: where the agents start, where the goal is, where the obstacles
and walls are. :class:`Scenes` is what draws them: every entry of the registry :data:`sb3_formation.env.scenes.SCENES`
(the thesis's curriculum, :mod:`~sb3_formation.env.curriculum`, and the scene families,
:mod:`~sb3_formation.env.families`) is one.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.geometry import reference_polygon
from sb3_formation.env.movers import Mover
from sb3_formation.env.shapes import as_walls, circle_gap, wall_gap


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
    :param movers: the moving obstacles (:class:`~sb3_formation.env.movers.Mover`), each starting at its first waypoint;
        may be empty
    """

    agent_positions: np.ndarray
    goal: np.ndarray
    obstacles: np.ndarray | tuple[Any, ...] = ()
    walls: np.ndarray | tuple[Any, ...] = ()
    headings: np.ndarray | tuple[Any, ...] = ()
    movers: tuple[Mover, ...] = ()

    def __post_init__(self) -> None:
        movers = tuple(self.movers)
        if not all(isinstance(mover, Mover) for mover in movers):
            raise TypeError("Scenario.movers must hold Mover objects")
        if len({mover.reacts for mover in movers if mover.motion == "walk"}) > 1:
            raise ValueError("Scenario.movers: the walkers of one scenario must all react to the agents or all not react")
        object.__setattr__(self, "movers", movers)
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

    @property
    def facing(self) -> float:
        """The heading (rad) from the starting centroid to the goal: a unicycle's start without :attr:`headings`."""
        direction = self.goal - self.centroid
        return math.atan2(float(direction[1]), float(direction[0]))

    def validate(self, config: FormationConfig) -> None:
        """Raise ``ValueError`` saying which agent is misplaced if the scenario does not fit ``config``.

        Checks: one position per agent, every agent inside the world, no two agents overlapping, no agent
        overlapping an obstacle, a wall or a mover's start, every obstacle's centre, every wall's ends, every mover's
        waypoints and the goal inside the world (an obstacle may cross the border, as the curriculum's large ones may).
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
            for mover_index, mover in enumerate(self.movers):
                gap = circle_gap(x, y, np.array([*mover.start, mover.radius])) - radius
                if gap < 0:
                    raise ValueError(f"Scenario: agent_{index} overlaps mover {mover_index}'s start by {-gap:.3f} m")
        points = [(f"obstacle {index}", x, y) for index, (x, y, _) in enumerate(self.obstacles)]
        for index, mover in enumerate(self.movers):
            points += [(f"mover {index}'s waypoint", x, y) for x, y in mover.waypoints]
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


def crossing_scenario(parts: Sequence[Scenario]) -> Scenario:
    """The placement of one world in which formations fly together (a crossing): every formation's agents, one
    formation after the other, each starting with its own headings (or facing its own goal), and the first
    formation's shapes and movers (the formations share them); its goal is the first formation's.

    :param parts: every formation's placement
    """
    first = parts[0]
    headings = [part.headings if len(part.headings) else np.full(len(part.agent_positions), part.facing) for part in parts]
    positions = np.vstack([part.agent_positions for part in parts])
    return Scenario(positions, first.goal, first.obstacles, first.walls, np.concatenate(headings), first.movers)


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


class Scenes(ABC):
    """Where a task's episodes are placed (:attr:`FormationConfig.scenes` names one in the registry
    :data:`~sb3_formation.env.scenes.SCENES`): it draws a :class:`Scenario` for a config, a curriculum stage and a
    generator, and says whether a config's world can hold its scenes.
    """

    #: One line, for the docs and ``--help``.
    description: str
    #: Whether the curriculum stage changes the placements (the thesis's curriculum), not only the reward terms.
    staged: bool = False
    #: Whether ``sb3-formation benchmark`` plays a set of these scenes (a mixture of other entries is not played).
    benchmarked: bool = True
    #: How many formations fly one scene together, each a team of the engine (:meth:`draw_formations`).
    formations: int = 1

    @abstractmethod
    def draw(self, config: FormationConfig, stage: int, rng: np.random.Generator) -> Scenario:
        """One episode's placement, drawn from ``rng`` only.

        :param config: the task (world size, team, placement tries)
        :param stage: the curriculum stage 1, 2 or 3
        :param rng: the team's generator
        :raises PlacementError: no placement was found within ``config.max_placement_tries`` draws
        """

    def draw_formations(self, config: FormationConfig, stage: int, rng: np.random.Generator) -> tuple[Scenario, ...]:
        """One scene's placements, one per formation (:attr:`formations` of them), drawn from ``rng`` only; they share
        the obstacles and walls. Arguments as :meth:`draw`'s."""
        return (self.draw(config, stage, rng),)

    def check_fits(self, config: FormationConfig) -> None:
        """Refuse a world in which these scenes cannot place a team of ``config.n_agents``: by default, one in which
        no scene is drawn from the generator of seed 0.

        :raises ValueError: naming the world, the scenes and what to change
        """
        try:
            self.draw_formations(config, config.stage, np.random.default_rng(0))
        except PlacementError as error:
            raise ValueError(str(error)) from None

    @abstractmethod
    def slots(self, config: FormationConfig) -> tuple[int, int]:
        """The most circles and walls a scenario of these scenes has: the room ``state()`` keeps for them."""

    def obstacle_speed(self, config: FormationConfig) -> float:
        """The most speed (m/s) an obstacle of these scenes has: the bound the safety filter keeps the agents safe
        under by default (0: every obstacle stands still)."""
        return 0.0
