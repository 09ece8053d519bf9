"""``TeamState``: a frozen snapshot of one team's episode, and the flat global state vector of PettingZoo's ``state()``.

Rendering, evaluation recordings and video captions read states, never the env's internals; a state can also be
rebuilt from a recorded trajectory (without lidar readings), so a saved episode can be drawn without replaying it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.dynamics import dynamics_model
from sb3_formation.env.scenes import scene_slots
from sb3_formation.env.shapes import WALL_COLUMNS


@dataclass(frozen=True)
class TeamState:
    """One team at one instant (after a reset or a step). Arrays are read-only copies; n agents, m obstacles.

    :param step: steps played since the reset
    :param positions: ``(n, 2)`` agent centres (m)
    :param velocities: ``(n, 2)`` agent velocities (m/s)
    :param goal: ``(2,)`` goal centre (m)
    :param obstacles: ``(m, 3)`` obstacle x, y, radius (m) now: the static ones, then the moving ones
    :param neighbours: ``(n, 2)`` neighbour graph: agent i's preceding and succeeding neighbour
    :param contacts_agent: ``(n,)`` other agents each agent touched during the last step (0 after a reset)
    :param contacts_obstacle: ``(n,)`` obstacles or walls each agent touched during the last step (0 after a reset)
    :param angle_errors_deg: ``(n,)`` abs(beta^ref - beta^i) (deg)
    :param bearing_errors: ``(n,)`` mean over the two neighbours of norm(g_ref - g)
    :param neighbour_distance_errors: ``(n,)`` mean over the two neighbours of max(d_j^i - d^ref, 0) (m)
    :param centroid: ``(2,)`` centroid p^c of the agents (m), eq. 20
    :param goal_distance: distance (m) from the centroid to the goal (the episode succeeds within eta_g)
    :param lidar_obstacles: ``(n, rays)`` obstacle-channel readings in [0, 1] (1: nothing in range), or ``None``
        when not recorded
    :param lidar_agents: ``(n, rays)`` agent-channel readings, or ``None``
    :param walls: ``(w, 5)`` walls x0, y0, x1, y1, thickness (m) (:mod:`~sb3_formation.env.shapes`); the world's
        border is not listed
    :param headings: ``(n,)`` unicycle agents' headings (rad, anti-clockwise from +x), or ``None`` for holonomic agents
    :param obstacle_velocities: ``(m, 2)`` every obstacle's velocity (m/s) over the last step (0 for static ones and
        before the first step), or ``None`` when no obstacle moves
    :param moving: how many of the obstacles (the last ones) move
    :param flying: ``(n,)`` bool: the agents whose motors run, when some failed (their ring is in ``neighbours``); ``None``:
        every agent flies
    :param others: ``(k, 2)`` the centres (m) of the other formations' agents in a crossing, formation after formation;
        ``None``: the team flies alone
    """

    step: int
    positions: np.ndarray
    velocities: np.ndarray
    goal: np.ndarray
    obstacles: np.ndarray
    neighbours: np.ndarray
    contacts_agent: np.ndarray
    contacts_obstacle: np.ndarray
    angle_errors_deg: np.ndarray
    bearing_errors: np.ndarray
    neighbour_distance_errors: np.ndarray
    centroid: np.ndarray
    goal_distance: float
    lidar_obstacles: np.ndarray | None = None
    lidar_agents: np.ndarray | None = None
    walls: np.ndarray = field(default_factory=lambda: np.zeros((0, len(WALL_COLUMNS))))
    headings: np.ndarray | None = None
    obstacle_velocities: np.ndarray | None = None
    moving: int = 0
    flying: np.ndarray | None = None
    others: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if isinstance(value, np.ndarray):
                array = np.array(value)  # a copy: the snapshot never changes with the env
                array.setflags(write=False)
                object.__setattr__(self, name, array)

    @property
    def n_agents(self) -> int:
        """Number of agents n."""
        return len(self.positions)

    @property
    def neighbour_distances(self) -> np.ndarray:
        """``(n, 2)`` distance (m) from each agent to its preceding and succeeding neighbour."""
        offsets = self.positions[self.neighbours] - self.positions[:, None, :]
        distances: np.ndarray = np.hypot(offsets[..., 0], offsets[..., 1])
        return distances


def state_fields(config: FormationConfig) -> list[tuple[str, int, np.ndarray, np.ndarray, str]]:
    """The fields of the global state vector, in order: (name, size, low, high, unit). The obstacle and wall fields
    have room for the most circles and walls a scene of ``config.scenes`` has (:func:`~sb3_formation.env.scenes.scene_slots`:
    4 and 0 for the thesis's curriculum); the dynamics' own fields (unicycles' headings) follow the velocities
    (:meth:`~sb3_formation.env.dynamics.DynamicsModel.state_fields`)."""
    n, (slots, wall_slots) = config.n_agents, scene_slots(config)
    width, height, v = config.world_width, config.world_height, config.v_max * (1 + 1e-9)
    corner = np.array([width, height])
    largest_radius = max(width, height)
    return [
        ("positions", 2 * n, np.zeros(2 * n), np.tile(corner, n), "m, agent 0 (x, y) first"),
        ("velocities", 2 * n, np.full(2 * n, -v), np.full(2 * n, v), "m/s, agent 0 (x, y) first"),
        *dynamics_model(config).state_fields(n),
        ("goal", 2, np.zeros(2), corner, "m"),
        (
            "obstacles",
            3 * slots,
            np.tile([-largest_radius, -largest_radius, 0.0], slots),
            np.tile([width + largest_radius, height + largest_radius, largest_radius], slots),
            "m, (x, y, radius) per obstacle; unused slots are (0, 0, 0)",
        ),
        (
            "walls",
            5 * wall_slots,
            np.zeros(5 * wall_slots),
            np.tile([width, height, width, height, largest_radius], wall_slots),
            "m, (x0, y0, x1, y1, thickness) per wall; unused slots are 0",
        ),
        ("step", 1, np.zeros(1), np.array([float(config.max_steps)]), "steps since the reset"),
    ]


def state_layout(config: FormationConfig) -> dict[str, slice]:
    """Field name -> slice of the global state vector."""
    layout, start = {}, 0
    for name, size, *_ in state_fields(config):
        layout[name] = slice(start, start + size)
        start += size
    return layout


def state_vector(state: TeamState, config: FormationConfig) -> np.ndarray:
    """The flat float32 global state of :func:`state_fields` (PettingZoo's ``state()``).

    :raises ValueError: the scenario has more obstacles or walls than the vector has slots (a hand-made scenario), or
        a state of unicycles has no headings
    """
    slots, wall_slots = scene_slots(config)
    for kind, shapes, room in (("obstacles", state.obstacles, slots), ("walls", state.walls, wall_slots)):
        if len(shapes) > room:
            raise ValueError(
                f"the global state has room for {room} {kind} (the most a scene of {config.scenes!r} places, chapter "
                f"{config.chapter!r}) but this scenario has {len(shapes)}"
            )
    obstacles, walls = np.zeros((slots, 3)), np.zeros((wall_slots, 5))
    obstacles[: len(state.obstacles)] = state.obstacles
    walls[: len(state.walls)] = state.walls
    extras = dynamics_model(config).state_values(state)
    parts = [state.positions.ravel(), state.velocities.ravel(), *extras, state.goal, obstacles.ravel(), walls.ravel()]
    return np.concatenate([*parts, [float(state.step)]]).astype(np.float32)
