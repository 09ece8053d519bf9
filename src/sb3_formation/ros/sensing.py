"""What the simulator node publishes of a step, and when each agent gets it (``docs/deployment.md``): the engine's
sensing and timing models on the topics, without ROS.

:func:`published_team` reads one team of an engine after a reset or a step. In the ideal world the odometry and the
scans hold the truth. Under disturbances they hold what the agents sensed (:attr:`~sb3_formation.env.engine.
FormationEngine.sensed`): the odometry gives the agent's position estimate, its heading plus its heading error and
its velocity estimate (the twist: that velocity in the frame of the heading it gives); the scan is cast from the true
position in the agent's true body frame along the engine's rays, each turned by minus the heading error (what the
engine's lidar puts in reading k), with the beams' range errors and dropped beams
(:func:`~sb3_formation.ros.scans.with_beam_errors`). An agent node that reads the scan with the odometry's heading
(:func:`~sb3_formation.ros.scans.resample_scan`) turns the beams back onto the task's rays, as the engine's agent reads
its lidar in the frame of its heading estimate.

:class:`Deliveries` holds the observation delay (:attr:`~sb3_formation.env.disturbed.Disturber.observation_delays`):
agent i acts at step t on its inputs of step ``max(t - d_i, 0)`` of the episode (the reset's while the episode is
younger), the engine's delayed row.

Numpy and the environment layer only (no rclpy): the simulator node and the tests call these.
"""

from __future__ import annotations

from collections import deque
from typing import Generic, NamedTuple, TypeVar

import numpy as np

from sb3_formation.env.engine import FormationEngine
from sb3_formation.ros.scans import merged_scan, with_beam_errors

ItemT = TypeVar("ItemT")


class PublishedTeam(NamedTuple):
    """What the simulator publishes of one team at one step (agent i in row i), in the world frame unless said."""

    positions: np.ndarray  #: ``(n, 2)`` (m) the odometry's positions
    headings: np.ndarray  #: ``(n,)`` (rad) the odometry's yaws (0 for holonomic agents in the ideal world)
    velocities: np.ndarray  #: ``(n, 2)`` (m/s) the velocity each odometry gives, in the world frame
    body_velocities: np.ndarray  #: ``(n, 2)`` (m/s) the odometry's twist: that velocity in the frame of its yaw
    forward_speeds: np.ndarray  #: ``(n,)`` (m/s) a unicycle's forward speed as its odometry gives it (0: holonomic)
    ranges: np.ndarray  #: ``(n, n_rays)`` (m) each scan's ranges from the agent's centre, ``inf``: no return
    scan_angles: np.ndarray  #: ``(n,)`` (rad) each scan's first beam's angle in the agent's true body frame


def published_team(engine: FormationEngine, team: int, stopped_by_agents: bool = True) -> PublishedTeam:
    """What the simulator node publishes of ``team`` after the engine's last reset or step (see the module docstring).

    :param engine: the engine (its :attr:`~sb3_formation.env.engine.FormationEngine.sensed`: ``None`` in the ideal
        world)
    :param team: the team
    :param stopped_by_agents: the other agents stop a scan's beams (a real scanner); ``False``: the scans see through
        them, as the simulator's obstacle channel does
    """
    rows, latest, model = engine.team_rows(team), engine.latest, engine.model
    n_agents = rows.stop - rows.start
    positions, velocities = latest.positions[rows].copy(), latest.velocities[rows].copy()
    true_headings = engine.dynamics.headings_of(rows)  # views of arrays the next step changes: copied
    headings = np.zeros(n_agents) if true_headings is None else true_headings.copy()
    true_speeds = engine.dynamics.forward_speeds_of(rows)
    speeds = np.zeros(n_agents) if true_speeds is None else true_speeds.copy()
    lidar, sensed = engine.lidars[team], engine.sensed
    if sensed is None or sensed.heading_errors.size == 0:  # the truth (the ideal world, or no localisation error)
        body = model.body_velocities(velocities, speeds)  # a point's body frame is the world's
        ranges = merged_scan(lidar, positions, stopped_by_agents)
        published = PublishedTeam(positions, headings, velocities, body, speeds, ranges, -headings)
    else:
        yaws = headings + sensed.heading_errors[rows]
        estimates = sensed.velocities[rows].copy()
        cos, sin = np.cos(yaws), np.sin(yaws)
        body = np.stack([cos * estimates[:, 0] + sin * estimates[:, 1], cos * estimates[:, 1] - sin * estimates[:, 0]], axis=1)
        forward = body[:, 0].copy() if true_speeds is not None else np.zeros(n_agents)
        ranges = merged_scan(lidar, positions, stopped_by_agents, sensed.heading_errors[rows])
        published = PublishedTeam(sensed.positions[rows].copy(), yaws, estimates, body, forward, ranges, -yaws)
    if sensed is not None:
        errors = sensed.beam_noise[rows] if sensed.beam_noise.size else sensed.beam_noise
        dropped = sensed.dropped[rows] if sensed.dropped.size else sensed.dropped
        ranges = with_beam_errors(published.ranges, errors, dropped, lidar.agent_radius, lidar.max_range)
        published = published._replace(ranges=ranges)
    return published


class Deliveries(Generic[ItemT]):
    """What each agent of a team gets at each step of an episode under observation delays: agent i, of delay d_i
    steps, gets at step t the item of step ``max(t - d_i, 0)`` (the reset's while the episode is younger), as the
    engine's delayed observation (:meth:`~sb3_formation.env.disturbed.Disturber.delay_observations`).

    Call :meth:`start` at each reset, then :meth:`add` with each step's item (the reset's first).
    """

    def __init__(self) -> None:
        self.delays = np.zeros(0, dtype=np.int64)
        self._items: deque[ItemT] = deque(maxlen=1)

    def start(self, delays: np.ndarray) -> None:
        """A new episode whose agents' delays (steps, agent i's in row i) are ``delays``."""
        self.delays = np.asarray(delays, dtype=np.int64).copy()
        self._items = deque(maxlen=int(self.delays.max(initial=0)) + 1)

    def add(self, item: ItemT) -> None:
        """The item of the episode's next step (the reset's first)."""
        self._items.append(item)

    def delivered(self, agent: int) -> ItemT:
        """What ``agent`` gets at the last step added."""
        if not self._items:
            raise RuntimeError("nothing was added since the episode started")
        return self._items[max(len(self._items) - 1 - int(self.delays[agent]), 0)]
