"""Episode statistics, and playing episodes of a :class:`FormationEnv` with any per-agent policy."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from sb3_formation.env.config import REWARD_TERMS
from sb3_formation.env.formation_env import FormationEnv

#: A team policy: observations of the live agents in, their actions out.
TeamPolicy = Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]]


class EpisodeStatistics:
    """Running sums of one team's episode, turned into the team's episode summary when it ends."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Start a new episode."""
        self.length = 0
        self.mean_return = 0.0
        self.errors = [0.0, 0.0, 0.0]
        self.collisions = [0, 0]
        self.terms = [0.0] * len(REWARD_TERMS)

    def add(self, rewards: np.ndarray, infos: Sequence[dict[str, Any]]) -> None:
        """Add one step: the team's rewards and per-agent infos (plain Python sums: a handful of agents per call)."""
        n_agents = len(infos)
        self.length += 1
        self.mean_return += float(rewards.mean())
        errors, collisions, terms = self.errors, self.collisions, self.terms
        for info in infos:
            errors[0] += info["angle_error_deg"] / n_agents
            errors[1] += info["bearing_error"] / n_agents
            errors[2] += info["neighbour_distance_error"] / n_agents
            collisions[0] += info["collisions_obstacle"]
            collisions[1] += info["collisions_agent"]
            for index, value in enumerate(info["reward_terms"].values()):
                terms[index] += value / n_agents

    def summary(self, success: bool, stage: int) -> dict[str, Any]:
        """The episode's means over steps (and over agents), collision totals, success and curriculum stage."""
        steps = max(self.length, 1)
        angle, bearing, distance = (error / steps for error in self.errors)
        return {
            "success": success,
            "length": self.length,
            "return": self.mean_return,
            "angle_error_deg": float(angle),
            "bearing_error": float(bearing),
            "neighbour_distance_error": float(distance),
            "collisions_obstacle": self.collisions[0],
            "collisions_agent": self.collisions[1] // 2,  # each touching pair is reported by both agents
            "reward_terms": {name: value / steps for name, value in zip(REWARD_TERMS, self.terms)},
            "stage": stage,
        }


def random_policy(env: FormationEnv, seed: int | None = None) -> TeamPolicy:
    """A policy drawing every agent's action uniformly from [-1, 1]^2 with its own seeded generator."""
    rng = np.random.default_rng(seed)
    return lambda observations: {agent: rng.uniform(-1.0, 1.0, 2) for agent in observations}


def run_episode(env: FormationEnv, policy: TeamPolicy, seed: int | None = None) -> dict[str, Any]:
    """Play one episode from ``env.reset(seed=seed)`` to its end and summarise it.

    :param env: the environment; left at the episode's last state (so it can be rendered)
    :param policy: maps the live agents' observations to their actions
    :param seed: reset seed (``None`` continues the env's generator)
    :return: :meth:`EpisodeStatistics.summary` of the episode, plus ``final_goal_distance`` (m)
    """
    observations, _ = env.reset(seed=seed)
    statistics = EpisodeStatistics()
    success = False
    while env.agents:
        observations, rewards, terminations, _, infos = env.step(policy(observations))
        statistics.add(np.fromiter(rewards.values(), dtype=np.float64), list(infos.values()))
        success = any(terminations.values())
    return {**statistics.summary(success, env.stage), "final_goal_distance": env.goal_distance}
