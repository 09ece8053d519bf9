"""The classical formation controller: goal attraction, lidar repulsion and neighbour consensus, per agent.

Every agent computes a velocity command from its own observation (Table 3.1), its index and the config:

- goal attraction: ``v_g = k_goal v_max R(theta) c_g / |c_g|`` along the centroid-to-goal offset c_g (the same for
  the whole team, so the team moves as one), turned anti-clockwise by the detour angle
  ``theta = detour (1 - p)``, where p in [0, 1] is the team's progress towards the goal over the last step
  (``-(c_g,t - c_g,t-1) . c_g / |c_g|``, observed) as a fraction of ``k_goal v_max dt``. A team held up by an
  obstacle turns aside together, all agents seeing the same c_g, and turns back to the goal once it moves freely:
  without the detour a team stops for good in front of two obstacles whose gap it does not fit through;
- repulsion: every lidar ray that sees an obstacle or wall at a gap s below the reach s_0 (``repulsion_range``) from
  the agent's surface pushes away from it with ``k_obstacle (1/s - 1/s_0)``, and every ray that sees a
  non-neighbour agent within l_s with ``k_agent (1/s - 1/l_s)``, summed over rays as an integral over the ray angle
  (``2 pi / rays`` per ray), so the push does not depend on the ray count; a designated neighbour closer than
  ``2 R_a + l_s`` pushes with ``k_agent (1/s - 1/l_s)`` too;
- consensus: each neighbour j implies a position for the agent; the agent steers towards their mean with
  ``v_f = k_formation (p* - p)``. With reference bearings (bearing rewards, K_bearing > 0) neighbour j at offset
  d_j implies ``d_j - L g_j^ref`` (Table 5.2 bearings at the starting side length L); without them (angle rewards)
  the two neighbours imply the apex of the isosceles triangle on them with apex angle beta^ref, on the side that
  keeps the polygon anti-clockwise, plus ``k_spacing (|d_j| - L)`` along each d_j to hold the side length;
- actuation (:func:`command_action`): the command's speed is clipped to v_max and turned into the force that reaches
  it in one step, ``F = m (v* - v) / dt``, as a fraction of F_max, scaled down (direction kept) to fit the [-1, 1]^2
  action box. A unicycle follows the command by feedback linearisation of the point ahead of its axle
  (:meth:`~sb3_formation.env.dynamics.UnicycleModel.steer`), so every controller of the package drives holonomic and
  unicycle agents alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sb3_formation.controllers.base import Controller, check_gains, ring_groups, ring_shape
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.dynamics import HolonomicModel, dynamics_model
from sb3_formation.env.sensors import ray_directions

#: Smallest surface gap (m) used in a 1/s repulsion, so touching bodies push hard but finitely.
MIN_GAP = 0.01


@dataclass(frozen=True)
class ClassicalGains:
    """Gains of :class:`ClassicalController` (defaults tuned on stage 3 of the four thesis tasks, seeds apart from
    the evaluation's).

    :param k_goal: goal speed as a fraction of v_max (< 1 leaves headroom for formation corrections)
    :param k_formation: consensus gain (1/s): speed per metre of distance to the consensus position
    :param k_spacing: side-length gain of the angle law (1/s), per metre of |d_j| - L
    :param k_obstacle: obstacle and wall repulsion (m^2/s per radian of rays): speed k (1/s - 1/l_s) per ray angle
    :param k_agent: agent repulsion (m^2/s), as ``k_obstacle`` for the agent channel and close neighbours
    :param repulsion_range: reach s_0 (m) of the obstacle repulsion, at most the lidar range l_s
    :param detour_deg: detour angle (deg) the goal direction turns by when the team makes no progress
    :param use_bearings: use the reference bearings when the task rewards them (K_bearing > 0); else the angle law
    """

    k_goal: float = 0.9
    k_formation: float = 0.3
    k_spacing: float = 0.3
    k_obstacle: float = 0.005
    k_agent: float = 0.002
    repulsion_range: float = 0.8
    detour_deg: float = 80.0
    use_bearings: bool = True

    def __post_init__(self) -> None:
        check_gains(self)


class ClassicalController(Controller):
    """Goal attraction, lidar repulsion and neighbour consensus (see the module docstring), decentralised.

    :param config: the task configuration
    :param gains: keyword values of :class:`ClassicalGains` (unknown names are an error)
    """

    def __init__(self, config: FormationConfig, **gains: Any) -> None:
        super().__init__(config)
        self.settings = self._take_gains(ClassicalGains, gains)
        self._fit_task()

    def _fit_task(self) -> None:
        config = self.config
        self.bearings = config.k_bearing > 0 and self.settings.use_bearings
        self.directions = ray_directions(config.lidar_rays)

    def act(self, observations: np.ndarray, agents: np.ndarray, deterministic: bool) -> np.ndarray:
        layout, gains, config = self.layout, self.settings, self.config
        velocity = self.goal_velocity(
            observations[:, layout["centroid_goal_offset"]], observations[:, layout["centroid_goal_offset_change"]]
        )
        offsets = observations[:, layout["neighbour_offsets"]].reshape(-1, 2, 2)
        velocity += self.formation_velocity(offsets, agents)
        velocity += gains.k_obstacle * lidar_repulsion(
            observations[:, layout["lidar_obstacles"]], config, self.directions, gains.repulsion_range
        )
        velocity += gains.k_agent * lidar_repulsion(observations[:, layout["lidar_agents"]], config, self.directions)
        velocity += gains.k_agent * neighbour_repulsion(offsets, config)
        return command_action(velocity, observations, layout, config)

    def goal_velocity(self, goal: np.ndarray, goal_change: np.ndarray) -> np.ndarray:
        """The goal attraction (m/s), turned aside by the detour angle when the team makes no progress.

        :param goal: ``(k, 2)`` centroid-to-goal offsets c_g (m)
        :param goal_change: ``(k, 2)`` their change over the last step (m)
        """
        gains, config = self.settings, self.config
        direction = unit(goal)
        speed = gains.k_goal * config.v_max
        progress = np.clip(-(goal_change * direction).sum(axis=1) / max(speed * config.dt, 1e-300), 0.0, 1.0)
        turn = np.radians(gains.detour_deg) * (1.0 - progress)
        cos, sin = np.cos(turn), np.sin(turn)
        turned = np.stack(
            [cos * direction[:, 0] - sin * direction[:, 1], sin * direction[:, 0] + cos * direction[:, 1]], axis=1
        )
        return speed * turned

    def formation_velocity(self, offsets: np.ndarray, agents: np.ndarray) -> np.ndarray:
        """The consensus part of the velocity command (m/s): towards the mean of the positions the reference
        bearings imply, or (angle law) towards the apex on the neighbours plus the side-length correction.

        :param offsets: ``(k, 2, 2)`` offsets to the preceding and succeeding neighbours (m)
        :param agents: ``(k,)`` agent indices, or ``(k, 2)`` places and ring sizes
            (:func:`~sb3_formation.controllers.base.ring_places`)
        """
        gains, velocity = self.settings, np.empty((len(offsets), 2))
        for rows, places, size in ring_groups(agents, self.config.n_agents):
            ring, own = ring_shape(self.config, size), offsets[rows]
            if self.bearings:
                implied = own - ring.side_length * ring.bearings[places]
                velocity[rows] = gains.k_formation * implied.mean(axis=1)
            else:
                apex = apex_offset(own, ring.beta_ref_deg)
                velocity[rows] = gains.k_formation * apex + gains.k_spacing * spacing_offset(own, ring.side_length)
        return velocity


def unit(vectors: np.ndarray) -> np.ndarray:
    """Rows of ``vectors`` scaled to length 1 (zero rows stay zero)."""
    norms = np.linalg.norm(vectors, axis=-1, keepdims=True)
    return np.divide(vectors, norms, out=np.zeros_like(vectors), where=norms > 0)


def lidar_repulsion(
    readings: np.ndarray, config: FormationConfig, directions: np.ndarray, reach: float | None = None
) -> np.ndarray:
    """Sum over rays of ``(1/s - 1/l_s)`` times minus the ray direction, times the ray angle ``2 pi / rays`` (m/s per
    unit gain); rays reading 1 (nothing within range) push nothing.

    :param readings: ``(k, rays)`` lidar readings, fractions of the range l_s
    :param config: the task (lidar range l_s)
    :param directions: ``(rays, 2)`` ray directions
    """
    reach = config.lidar_range if reach is None else min(reach, config.lidar_range)
    gaps = np.maximum(readings * config.lidar_range, MIN_GAP)
    push = np.where(gaps < reach, 1.0 / gaps - 1.0 / reach, 0.0)
    return -(push @ directions) * (2.0 * math.pi / len(directions))


def neighbour_repulsion(offsets: np.ndarray, config: FormationConfig) -> np.ndarray:
    """Push ``(1/s - 1/l_s)`` away from each designated neighbour whose surface gap s is below the lidar range l_s
    (the agent channel does not see neighbours).

    :param offsets: ``(k, 2, 2)`` neighbour offsets (m)
    :param config: the task (R_a, l_s)
    """
    distances = np.linalg.norm(offsets, axis=-1)
    gaps = np.maximum(distances - 2 * config.agent_radius, MIN_GAP)
    push = np.where(gaps < config.lidar_range, 1.0 / gaps - 1.0 / config.lidar_range, 0.0)
    return -(push[..., None] * unit(offsets)).sum(axis=1)


def apex_offset(offsets: np.ndarray, beta_ref_deg: float) -> np.ndarray:
    """Offset (m) to the apex of the isosceles triangle on the two neighbours with apex angle beta^ref, on the side
    where the agent's interior angle is measured anti-clockwise from the succeeding to the preceding neighbour.

    :param offsets: ``(k, 2, 2)`` offsets to the preceding and succeeding neighbours (m)
    :param beta_ref_deg: reference interior angle beta^ref (deg)
    """
    preceding, succeeding = offsets[:, 0], offsets[:, 1]
    base = succeeding - preceding
    half_base = np.linalg.norm(base, axis=-1, keepdims=True) / 2
    height = half_base / math.tan(math.radians(beta_ref_deg) / 2)
    outward = unit(base) @ np.array([[0.0, -1.0], [1.0, 0.0]])  # base direction turned clockwise by 90 deg
    return (preceding + succeeding) / 2 + height * outward


def spacing_offset(offsets: np.ndarray, side_length: float) -> np.ndarray:
    """Sum over neighbours of ``(|d_j| - L) d_j / |d_j|`` (m): towards neighbours farther than L, away from closer.

    :param offsets: ``(k, 2, 2)`` neighbour offsets (m)
    :param side_length: the side length L (m)
    """
    distances = np.linalg.norm(offsets, axis=-1, keepdims=True)
    return ((distances - side_length) * unit(offsets)).sum(axis=1)


def force_action(command: np.ndarray, velocity: np.ndarray, config: FormationConfig) -> np.ndarray:
    """The action whose force reaches the commanded velocity in one step (a point's actuation,
    :meth:`~sb3_formation.env.dynamics.HolonomicModel.reach`): the command's speed clipped to v_max,
    ``F = m (v* - v) / dt`` as a fraction of F_max, scaled down (direction kept) to fit [-1, 1]^2.

    :param command: ``(k, 2)`` commanded velocities (m/s)
    :param velocity: ``(k, 2)`` current velocities (m/s)
    :param config: the task (v_max, m, dt, F_max)
    """
    return HolonomicModel(config).reach(command, velocity)


def command_action(
    command: np.ndarray, observations: np.ndarray, layout: dict[str, slice], config: FormationConfig
) -> np.ndarray:
    """The action that follows commanded world-frame velocities with the task's dynamics
    (:meth:`~sb3_formation.env.dynamics.DynamicsModel.follow`): :func:`force_action` for a point, feedback
    linearisation of the point ahead for a unicycle (:meth:`~sb3_formation.env.dynamics.UnicycleModel.steer`).

    :param command: ``(k, 2)`` commanded velocities (m/s)
    :param observations: ``(k, obs_dim)`` the agents' raw observations (their velocity, and a unicycle's heading)
    :param layout: the observation's field name -> slice
    :param config: the task
    """
    return dynamics_model(config).follow(command, observations, layout)
