"""Run episodes of a :class:`FormationEnv` with any per-agent policy and summarise them per episode."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from .env import FormationEnv

#: A team policy: observations of the live agents in, their actions out.
TeamPolicy = Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]]


@dataclass(frozen=True)
class EpisodeSummary:
    """What happened in one episode; errors are means over agents and steps.

    :param steps: steps taken
    :param success: the centroid reached the goal
    :param mean_agent_return: undiscounted return, averaged over agents
    :param angle_error_deg: mean |beta^ref - beta^i| (deg)
    :param bearing_error: mean bearing error (norm of g_ref - g)
    :param neighbour_distance_error: mean positive neighbour-distance error (m)
    :param final_goal_distance: centroid-goal distance at the end (m)
    :param collisions_obstacle: agent-obstacle contacts summed over steps (a pair counted once per step)
    :param collisions_agent: agent-agent contacts summed over steps (a pair counted once per step)
    """

    steps: int
    success: bool
    mean_agent_return: float
    angle_error_deg: float
    bearing_error: float
    neighbour_distance_error: float
    final_goal_distance: float
    collisions_obstacle: int
    collisions_agent: int

    def as_dict(self) -> dict[str, float | int | bool]:
        """The summary as a plain dict (for JSON)."""
        return asdict(self)


def random_policy(env: FormationEnv, seed: int | None = None) -> TeamPolicy:
    """A policy drawing every agent's action uniformly from [-1, 1]^2 with its own seeded generator."""
    rng = np.random.default_rng(seed)
    return lambda observations: {agent: rng.uniform(-1.0, 1.0, 2) for agent in observations}


def run_episode(env: FormationEnv, policy: TeamPolicy, seed: int | None = None) -> EpisodeSummary:
    """Play one episode from ``env.reset(seed=seed)`` to its end and summarise it.

    :param env: the environment; left at the episode's last state (so it can be rendered)
    :param policy: maps the live agents' observations to their actions
    :param seed: reset seed (``None`` continues the env's generator)
    """
    observations, infos = env.reset(seed=seed)
    returns = dict.fromkeys(env.possible_agents, 0.0)
    errors = np.zeros(3)
    samples = 0
    collisions_obstacle = collisions_agent = 0
    steps, success = 0, False
    while env.agents:
        observations, rewards, terminations, _, infos = env.step(policy(observations))
        steps += 1
        for agent, reward in rewards.items():
            returns[agent] += reward
        for info in infos.values():
            errors += (info["angle_error_deg"], info["bearing_error"], info["neighbour_distance_error"])
            samples += 1
            collisions_obstacle += info["collisions_obstacle"]
            collisions_agent += info["collisions_agent"]
        success = any(terminations.values())
    angle, bearing, distance = errors / max(samples, 1)
    return EpisodeSummary(
        steps=steps,
        success=success,
        mean_agent_return=float(np.mean(list(returns.values()))),
        angle_error_deg=float(angle),
        bearing_error=float(bearing),
        neighbour_distance_error=float(distance),
        final_goal_distance=env.goal_distance,
        collisions_obstacle=collisions_obstacle,
        collisions_agent=collisions_agent // 2,  # each touching pair is reported by both of its agents
    )
