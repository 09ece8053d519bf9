"""The two-channel lidar, computed analytically for all agents and rays at once.

Every agent casts ``n_rays`` rays, ``360 / n_rays`` degrees apart starting at +x, from its surface outwards.
A ray reports the distance from the agent's surface to the first shape it meets, divided by the range, so a reading
lies in [0, 1] and 1 means nothing within range. Each channel sees only its own kind of body (no occlusion across
channels): the obstacle channel sees the static circles, the walls and the world's border, the agent channel sees the
agents other than the agent itself and its designated neighbours.

The scan is one numba-compiled loop over agents, shapes and rays (shapes out of reach are skipped before any ray is
cast): with numpy the many tiny array operations of a 6-agent scan cost ~150 us, the compiled loop ~10 us.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numba
import numpy as np

from sb3_formation.env.shapes import as_walls, border_entry, circle_entry, wall_entry, wall_gap

OBSTACLE_CHANNEL, AGENT_CHANNEL = 0, 1


def ray_directions(n_rays: int) -> np.ndarray:
    """Unit directions of the lidar rays, ``360 / n_rays`` deg apart starting at +x (anti-clockwise).

    :param n_rays: number of rays b x d
    :return: ``(n_rays, 2)`` array
    """
    angles = np.arange(n_rays) * (2.0 * np.pi / n_rays)
    return np.stack([np.cos(angles), np.sin(angles)], axis=1)


def agent_visibility(n_agents: int, neighbours: np.ndarray) -> np.ndarray:
    """Which agents each agent's agent channel sees: all but itself and its designated neighbours.

    :param n_agents: team size n
    :param neighbours: ``(n, k)`` neighbour indices
    :return: ``(n, n)`` bool
    """
    visible = ~np.eye(n_agents, dtype=bool)
    visible[np.arange(n_agents)[:, None], neighbours] = False
    return visible


class LidarLayout(NamedTuple):
    """What a team's scan checks: its circles, who sees which, their channels, and its walls."""

    #: ``(m, 3)`` x, y, radius (m): the obstacles (other formations' agents last), then the agents (whose centres each
    #: scan sets)
    circles: np.ndarray
    visible: np.ndarray  #: ``(n, m)`` bool: the circles each agent may see
    channels: np.ndarray  #: ``(m,)`` channel (0 or 1) of every circle
    walls: np.ndarray  #: ``(w, 5)`` walls (x0, y0, x1, y1, thickness) in m, seen by channel 0


@numba.njit(cache=True)
def lidar_ranges(
    origins: np.ndarray,
    directions: np.ndarray,
    layout: LidarLayout,
    agent_radius: float,
    width: float,
    height: float,
    max_range: float,
    ranges: np.ndarray,
) -> None:  # pragma: no cover - compiled; tested through its results
    """Distance (m) along every ray from each agent's surface to the nearest visible shape, per channel.

    A ray's reading is the distance from the agent's surface to the first point of a shape at or beyond the surface
    (:func:`~sb3_formation.env.shapes.circle_entry`, :func:`~sb3_formation.env.shapes.wall_entry`; 0 if the shape
    touches the surface). The world's border and the walls belong to channel 0; each circle to its channel.

    :param origins: ``(n, 2)`` agent centres (m)
    :param directions: ``(n_rays, 2)`` unit ray directions
    :param layout: the circles (each seen by its channel and by the agents it is visible to) and the walls
    :param agent_radius: R_a (m); rays start on the agent's surface
    :param width: world width (m)
    :param height: world height (m)
    :param max_range: lidar range (m)
    :param ranges: ``(2, n, n_rays)``, where the distances (in [0, max_range]) go
    """
    circles, visible, channels, walls = layout
    n_agents, n_rays, n_circles = origins.shape[0], directions.shape[0], circles.shape[0]
    for agent in range(n_agents):
        px, py = origins[agent, 0], origins[agent, 1]
        for ray in range(n_rays):
            border = border_entry(px, py, directions[ray, 0], directions[ray, 1], width, height)
            ranges[0, agent, ray] = min(max(border - agent_radius, 0.0), max_range)
            ranges[1, agent, ray] = max_range
        for circle in range(n_circles):
            if not visible[agent, circle]:
                continue
            cx, cy, radius = circles[circle, 0], circles[circle, 1], circles[circle, 2]
            reach = agent_radius + max_range + radius
            if (cx - px) * (cx - px) + (cy - py) * (cy - py) >= reach * reach:
                continue
            channel = channels[circle]
            for ray in range(n_rays):
                entry = circle_entry(px, py, directions[ray, 0], directions[ray, 1], cx, cy, radius, agent_radius)
                if entry - agent_radius < ranges[channel, agent, ray]:
                    ranges[channel, agent, ray] = entry - agent_radius
        for wall in range(walls.shape[0]):
            if wall_gap(px, py, walls[wall]) >= agent_radius + max_range:
                continue
            for ray in range(n_rays):
                entry = wall_entry(px, py, directions[ray, 0], directions[ray, 1], walls[wall], agent_radius)
                if entry - agent_radius < ranges[0, agent, ray]:
                    ranges[0, agent, ray] = entry - agent_radius


class Lidar:
    """The two-channel lidar of one team: obstacles (static circles and walls) and non-neighbour agents.

    :param n_rays: number of rays
    :param max_range: range (m), from the agent's surface
    :param agent_radius: R_a (m)
    :param width: world width (m)
    :param height: world height (m)
    :param neighbours: ``(n, k)`` designated neighbours, invisible to the agent channel
    """

    def __init__(
        self, n_rays: int, max_range: float, agent_radius: float, width: float, height: float, neighbours: np.ndarray
    ) -> None:
        self.directions = ray_directions(n_rays)
        self.max_range = max_range
        self.agent_radius = agent_radius
        self.width = width
        self.height = height
        self._agent_visibility = agent_visibility(len(neighbours), neighbours)
        self.set_obstacles(np.zeros((0, 3)))

    def set_obstacles(
        self, obstacles: np.ndarray | tuple[Any, ...], walls: np.ndarray | tuple[Any, ...] = (), agents: int = 0
    ) -> None:
        """Use ``obstacles`` (``(m, 3)``: x, y, radius in m) and ``walls`` (``(w, 5)``, see
        :mod:`~sb3_formation.env.shapes`) from now on, every agent flying.

        :param agents: how many of the last ``obstacles`` are agents of other formations (a crossing's): circles of
            the agent channel, seen by every agent
        """
        n_agents = len(self._agent_visibility)
        circles = np.vstack([np.asarray(obstacles, dtype=np.float64).reshape(-1, 3), np.zeros((n_agents, 3))])
        circles[-n_agents:, 2] = self.agent_radius
        n_obstacles = len(circles) - n_agents
        visible = np.hstack([np.ones((n_agents, n_obstacles), dtype=bool), self._agent_visibility])
        channels = np.r_[np.full(n_obstacles - agents, OBSTACLE_CHANNEL), np.full(agents + n_agents, AGENT_CHANNEL)]
        #: what a scan checks (the agents' circles take their centres at each scan)
        self.layout = LidarLayout(circles, visible, channels, as_walls(walls))

    def set_flying(self, flying: np.ndarray, neighbours: np.ndarray) -> None:
        """Agents that failed from now on (until :meth:`set_obstacles`): each is a circle of the obstacle channel, seen
        by every other agent, and the flying agents' agent channels skip their ring neighbours ``neighbours``.

        :param flying: ``(n,)`` bool: the agents that fly
        :param neighbours: ``(n, 2)`` the ring of the flying agents (:func:`~sb3_formation.env.geometry.flying_ring`)
        """
        n_agents = len(flying)
        visibility = agent_visibility(n_agents, neighbours)
        visibility[:, ~flying] = ~np.eye(n_agents, dtype=bool)[:, ~flying]  # a failed agent: an obstacle to the others
        self.layout.visible[:, -n_agents:] = visibility
        self.layout.channels[-n_agents:] = np.where(flying, AGENT_CHANNEL, OBSTACLE_CHANNEL)

    def scan(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Readings of every agent's rays, ``(obstacles, agents)``, each ``(n, n_rays)`` in [0, 1] (1 = nothing in range).

        :param positions: ``(n, 2)`` agent centres (m)
        """
        self.layout.circles[-len(positions) :, :2] = positions
        ranges = np.empty((2, len(positions), len(self.directions)))
        lidar_ranges(
            positions, self.directions, self.layout, self.agent_radius, self.width, self.height, self.max_range, ranges
        )
        ranges /= self.max_range
        return ranges[OBSTACLE_CHANNEL], ranges[AGENT_CHANNEL]
