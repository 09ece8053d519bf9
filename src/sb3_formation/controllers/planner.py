"""The privileged reference planner: it reads the map, plans a centroid path, and flies the formation along it.

Privileged: unlike every other policy of the package it is not decentralised. At the start of each episode it reads
the team's :class:`~sb3_formation.env.state.TeamState` (the circles, the walls and the goal: the map), and it steers
every agent of a team together. It shows that a scene can be solved, and it is a teacher for learned policies; it is
not a baseline that a decentralised policy could match with its own sensors.

- **Plan** (once per episode): on the scene's clearance map (:mod:`~sb3_formation.env.clearance`), the cheapest path
  of the centroid to the goal along which the smallest formation (footprint R_a / sin(pi / n) + R_a) keeps ``margin``
  from every shape, a move's cost growing near shapes (``gap_weight``), so that the path keeps to the middle of
  openings. Along it, the formation's circumradius r(s) at arc length s is the largest that the clearance allows from
  ``behind`` before s to ``ahead`` after it, between the smallest formation's (neighbours 5 % apart from touching)
  and the starting one's: ``r(s) = clip(min gap - margin - R_a, r_min, r_0)``.
- **Fly** (every step): the centroid c (from the agents' positions, p_i = p^g - d_g^i of each observation) is
  projected on the path (never backwards); the carrot is the path point ``lookahead`` further on (the goal at the end).
  Agent i's command is ``v_i = v_c + k_position (c + r u_i - p_i)``, with ``v_c = speed v_max`` towards the carrot and
  u_i the unit vertex i of the reference n-gon (its shape and orientation are the task's), turned into a force as the
  classical controller does (:func:`~sb3_formation.controllers.classical.command_action`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sb3_formation.controllers.base import Controller, check_gains
from sb3_formation.controllers.classical import command_action
from sb3_formation.env.clearance import ClearanceMap, shortest_path, shrunk_footprint
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.geometry import reference_polygon
from sb3_formation.env.state import TeamState


@dataclass(frozen=True)
class PlannerGains:
    """Gains of :class:`PrivilegedPlanner` (see the module docstring).

    :param speed: centroid speed as a fraction of v_max
    :param k_position: gain (1/s) from an agent's distance to its place in the formation to its speed
    :param lookahead: distance (m) of the carrot along the path
    :param margin: room (m) the formation keeps from every shape
    :param gap_weight: how strongly (m) the path keeps away from shapes where there is room
    :param ahead: the formation takes the clearance this far (m) ahead along the path
    :param behind: and this far (m) behind
    """

    speed: float = 0.9
    k_position: float = 0.5
    lookahead: float = 0.5
    margin: float = 0.08
    gap_weight: float = 0.3
    ahead: float = 1.5
    behind: float = 1.0

    def __post_init__(self) -> None:
        check_gains(self)


@dataclass
class TeamPlan:
    """One team's plan: the path, its arc lengths and the formation's circumradius along it, and the progress made.

    :param goal: ``(2,)`` goal (m)
    :param path: ``(k, 2)`` centroid path (m)
    :param arc: ``(k,)`` arc length (m) of each path point
    :param radius: ``(k,)`` formation circumradius (m) at each path point
    :param index: the path point the centroid was last projected on
    """

    goal: np.ndarray
    path: np.ndarray
    arc: np.ndarray
    radius: np.ndarray
    index: int = 0


class PrivilegedPlanner(Controller):
    """A centroid path planned on the map and the formation flown along it, resized to the clearance (privileged).

    :param config: the task configuration
    :param gains: keyword values of :class:`PlannerGains`
    """

    #: Reads the map (:meth:`start_episodes`): not a decentralised policy.
    privileged = True

    def __init__(self, config: FormationConfig, **gains: float) -> None:
        super().__init__(config)
        self.settings = self._take_gains(PlannerGains, gains)
        self._fit_task()

    def _fit_task(self) -> None:
        self.plans: dict[int, TeamPlan] = {}  # by team; none carried over from another task

    def start_episodes(self, teams: Sequence[int], states: Sequence[TeamState]) -> None:
        """Plan the new episodes of ``teams`` from their states after the reset (the map: shapes and goal).

        :param teams: the teams (row k of :meth:`predict` belongs to team k // n)
        :param states: each team's state after its reset
        """
        for team, state in zip(teams, states):
            self.plans[int(team)] = self.plan(state)

    def plan(self, state: TeamState) -> TeamPlan:
        """The plan of an episode that starts in ``state`` (a straight line to the goal if no path fits)."""
        config, gains = self.config, self.settings
        clearance = ClearanceMap.of(config, state.obstacles, state.walls)
        footprint = shrunk_footprint(config) + gains.margin
        path = shortest_path(clearance, state.centroid, state.goal, config.eta_g / 2, footprint, gains.gap_weight)
        if path is None:
            path = np.stack([state.centroid, state.goal])
        else:
            path = np.vstack([path, state.goal])
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
        gaps = np.array([clearance.gaps[clearance.cell(point)] for point in path])
        smallest = 1.05 * (shrunk_footprint(config) - config.agent_radius)
        radius = np.empty(len(path))
        for index, length in enumerate(arc):
            near = (arc >= length - gains.behind) & (arc <= length + gains.ahead)
            radius[index] = gaps[near].min() - gains.margin - config.agent_radius
        radius = np.clip(radius, smallest, config.start_circumradius)
        return TeamPlan(goal=np.array(state.goal), path=path, arc=arc, radius=radius)

    def act(self, observations: np.ndarray, agents: np.ndarray, deterministic: bool) -> np.ndarray:
        """Actions for whole teams' rows (row k: agent k % n of team k // n, as :meth:`predict` passes them); a team
        without a plan (never started through :meth:`start_episodes`) stays still."""
        n_agents, layout = self.config.n_agents, self.layout
        actions = np.zeros((len(observations), 2))
        for team in range(len(observations) // n_agents):
            plan = self.plans.get(team)
            if plan is None:
                continue
            rows = slice(team * n_agents, (team + 1) * n_agents)
            positions = plan.goal - observations[rows, layout["goal_offset"]]
            actions[rows] = command_action(self.commands(plan, positions), observations[rows], layout, self.config)
        return actions

    def commands(self, plan: TeamPlan, positions: np.ndarray) -> np.ndarray:
        """Every agent's velocity command (m/s) at ``positions`` (``(n, 2)``, m), advancing the plan's progress."""
        config, gains = self.config, self.settings
        centroid = positions.mean(axis=0)
        window = slice(plan.index, min(plan.index + 40, len(plan.path)))  # 4 m of path: the centroid never jumps more
        plan.index += int(np.argmin(np.linalg.norm(plan.path[window] - centroid, axis=1)))
        carrot_arc = plan.arc[plan.index] + gains.lookahead
        carrot = plan.path[min(int(np.searchsorted(plan.arc, carrot_arc)), len(plan.path) - 1)]
        offset = carrot - centroid
        distance = float(np.linalg.norm(offset))
        speed = gains.speed * config.v_max * min(1.0, distance / max(gains.lookahead, 1e-9))
        centroid_velocity = offset / max(distance, 1e-12) * speed
        places = centroid + reference_polygon(config.n_agents, float(plan.radius[plan.index]))
        return centroid_velocity + gains.k_position * (places - positions)
