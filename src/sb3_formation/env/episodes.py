"""A team's episode summary from the running sums of its steps (how each metric is shown, titled and logged is
:mod:`sb3_formation.sb3.metrics`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from sb3_formation.env.config import REWARD_TERMS


def episode_summary(
    length: int,
    mean_return: float,
    errors: Sequence[float],
    collisions: Sequence[int],
    terms: Sequence[float],
    success: bool,
    stage: int,
    moving: bool = False,
    failed: int | None = None,
) -> dict[str, Any]:
    """A team's episode summary from its running sums (the engine keeps them: ``FormationEngine.episode_summary``).

    :param length: steps of the episode
    :param mean_return: sum over steps of the team's mean agent reward
    :param errors: sums over steps of the agents' angle (deg), bearing and neighbour-distance (m) errors over n
    :param collisions: obstacle and agent contacts summed over agents and steps (an agent pair counted by both), and
        of the obstacle contacts those where a moving obstacle ran into the agent (``collisions_rammed``, in the
        summary of an episode with moving obstacles only: summaries of still worlds are as they were before)
    :param terms: sums over steps of every reward term over n, in the order of ``REWARD_TERMS``
    :param success: the team reached the goal
    :param stage: curriculum stage
    :param moving: the episode had moving obstacles
    :param failed: the agents that failed in the episode (``failed_agents``, in the summary of a task whose agents may
        fail only; ``None`` otherwise); its errors and contacts are then the flying agents'
    """
    steps = max(length, 1)
    angle, bearing, distance = (error / steps for error in errors)
    rammed = {"collisions_rammed": collisions[2]} if moving else {}
    failures = {} if failed is None else {"failed_agents": failed}
    return {
        "success": success,
        "length": length,
        "return": mean_return,
        "angle_error_deg": float(angle),
        "bearing_error": float(bearing),
        "neighbour_distance_error": float(distance),
        "collisions_obstacle": collisions[0],
        "collisions_agent": collisions[1] // 2,  # each touching pair is reported by both agents
        **rammed,
        **failures,
        "reward_terms": {name: value / steps for name, value in zip(REWARD_TERMS, terms)},
        "stage": stage,
    }
