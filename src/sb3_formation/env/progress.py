"""What the goal term rewards progress along, chosen once from ``config.goal_progress``: the straight distance from a
team's centroid to its goal (the thesis's, eqs 23 / 38) or the way round the shapes on the team's goal field.

The goal term is k_1 + (w_t - w_t+1) / (dt v_max) of the way w; the way is the only thing a :class:`GoalProgress`
measures. Agents always observe the reward of the thesis's goal term (Table 3.1's previous reward): the map stays out
of observations.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import cast

import numpy as np

from sb3_formation.env.clearance import ClearanceMap, goal_field, path_distance
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.rewards import TERM_ROW, goal_term
from sb3_formation.env.scenarios import Scenario
from sb3_formation.env.stacked import StepTeams

_N_TERMS = len(TERM_ROW)

#: every team's reward terms (each team's ``(terms, n)`` block, flat) -> every agent's reward and every team's mean
Combine = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
#: every team's goal distance (m) before and after a step
GoalDistances = tuple[np.ndarray, np.ndarray]


class GoalProgress(ABC):
    """The way (m) from each team's centroid to its goal whose decrease the goal term rewards.

    :param configs: every team's task configuration
    :param starts: the first row of each team, then the number of rows
    """

    def __init__(self, configs: Sequence[FormationConfig], starts: np.ndarray) -> None:
        self.configs = list(configs)
        self.starts = starts

    @abstractmethod
    def reset(self, team: int, scenario: Scenario, centroid: np.ndarray, goal_distance: float) -> float:
        """Start a team's episode in ``scenario``; return its way (m) now.

        :param centroid: ``(2,)`` the team's centroid (m)
        :param goal_distance: its distance (m) to the goal
        """

    @abstractmethod
    def ways(self, previous: np.ndarray, goal_distances: np.ndarray, centroids: np.ndarray, stepped: StepTeams) -> np.ndarray:
        """Every team's way (m) after a step: the stepped teams' new ways, the others' ``previous`` ones.

        :param previous: ``(teams,)`` the ways before the step (not written)
        :param goal_distances: ``(teams,)`` the goal distances (m) after the step
        :param centroids: ``(teams, 2)`` the centroids (m) after the step
        """

    @abstractmethod
    def observed_rewards(
        self, rewards: np.ndarray, terms: np.ndarray, goal_distances: GoalDistances, stepped: StepTeams, combine: Combine
    ) -> np.ndarray:
        """The rewards agents observe as their previous reward: ``rewards`` with the thesis's goal term.

        :param rewards: ``(agents,)`` the step's rewards
        :param terms: the step's reward terms (each team's ``(terms, n)`` block, flat; not written)
        :param goal_distances: ``(teams,)`` the goal distances (m) before and after the step
        :param combine: how the engine sums terms into rewards
        """


class EuclideanProgress(GoalProgress):
    """The thesis's goal term: the way is the centroid's straight distance to the goal."""

    def reset(self, team: int, scenario: Scenario, centroid: np.ndarray, goal_distance: float) -> float:
        return float(goal_distance)

    def ways(self, previous: np.ndarray, goal_distances: np.ndarray, centroids: np.ndarray, stepped: StepTeams) -> np.ndarray:
        return goal_distances

    def observed_rewards(
        self, rewards: np.ndarray, terms: np.ndarray, goal_distances: GoalDistances, stepped: StepTeams, combine: Combine
    ) -> np.ndarray:
        return rewards


class GeodesicProgress(GoalProgress):
    """The way round the shapes: the path distance from the centroid on the team's goal field, made at its reset from
    its scene's clearance map (:mod:`~sb3_formation.env.clearance`)."""

    def __init__(self, configs: Sequence[FormationConfig], starts: np.ndarray) -> None:
        super().__init__(configs, starts)
        self._fields: list[tuple[ClearanceMap, np.ndarray] | None] = [None] * len(self.configs)

    def reset(self, team: int, scenario: Scenario, centroid: np.ndarray, goal_distance: float) -> float:
        obstacles, walls = cast(np.ndarray, scenario.obstacles), cast(np.ndarray, scenario.walls)  # arrays once built
        clearance = ClearanceMap.of(self.configs[team], obstacles, walls)
        self._fields[team] = clearance, goal_field(clearance, scenario.goal)
        return self._way(team, centroid)

    def _way(self, team: int, centroid: np.ndarray) -> float:
        clearance, field = cast("tuple[ClearanceMap, np.ndarray]", self._fields[team])  # made at the team's reset
        return path_distance(clearance, field, centroid)

    def ways(self, previous: np.ndarray, goal_distances: np.ndarray, centroids: np.ndarray, stepped: StepTeams) -> np.ndarray:
        ways: np.ndarray = previous.copy()
        for team in stepped.teams:
            ways[team] = self._way(team, centroids[team])
        return ways

    def observed_rewards(
        self, rewards: np.ndarray, terms: np.ndarray, goal_distances: GoalDistances, stepped: StepTeams, combine: Combine
    ) -> np.ndarray:
        before, after = goal_distances
        straight = terms.copy()
        for team in stepped.teams:
            config = self.configs[team]
            block = straight[_N_TERMS * self.starts[team] : _N_TERMS * self.starts[team + 1]].reshape(_N_TERMS, -1)
            block[TERM_ROW["goal"]] = goal_term(
                before[team], after[team], after[team], config.eta_g, config.r_reached, config.k1, config.dt, config.v_max
            )
        return combine(straight)[0]


#: ``FormationConfig.goal_progress`` -> its class
GOAL_PROGRESS_CLASSES: dict[str, type[GoalProgress]] = {"euclidean": EuclideanProgress, "geodesic": GeodesicProgress}
