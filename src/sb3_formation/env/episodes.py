"""Episode metrics: their names (one list for TensorBoard, evaluation summaries, tables and figures), and a team's
episode summary from the running sums of its steps."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from sb3_formation.env.config import REWARD_TERMS


@dataclass(frozen=True)
class Metric:
    """One per-episode metric.

    :param label: table heading, with the unit
    :param title: short title of its chart
    :param axis: axis label of its chart, with the unit
    :param tensorboard: its TensorBoard tag during training (``None``: evaluation only)
    :param in_table: a column of comparison tables
    """

    label: str
    title: str
    axis: str
    tensorboard: str | None
    in_table: bool = True


#: Every per-episode metric, by its key in episode summaries (``formation_episode`` infos, ``episodes.csv``, the means
#: of ``summary.json``). Errors are means over the episode's steps of the means over agents; collisions are totals.
EPISODE_METRICS: dict[str, Metric] = {
    "angle_error_deg": Metric("angle error (deg)", "angle error", "angle error (deg)", "formation/angle_error_deg"),
    "bearing_error": Metric("bearing error", "bearing error", "bearing error", "formation/bearing_error"),
    "neighbour_distance_error": Metric(
        "distance error (m)", "neighbour-distance error", "distance error (m)", "formation/neighbour_distance_error"
    ),
    "length": Metric("steps", "episode length", "steps", "episode/length"),
    "collisions_obstacle": Metric(
        "obstacle collisions", "obstacle collisions", "collisions per episode", "episode/collisions_obstacle"
    ),
    "collisions_agent": Metric("agent collisions", "agent collisions", "collisions per episode", "episode/collisions_agent"),
    "comm_exceeded_fraction": Metric(
        "beyond communication range", "beyond communication range", "fraction of steps", None, in_table=False
    ),
}
#: TensorBoard tag of the rolling success rate during training.
SUCCESS_RATE_TAG = "episode/success_rate"


def episode_summary(
    length: int,
    mean_return: float,
    errors: Sequence[float],
    collisions: Sequence[int],
    terms: Sequence[float],
    success: bool,
    stage: int,
) -> dict[str, Any]:
    """A team's episode summary from its running sums (the engine keeps them: ``FormationEngine.episode_summary``).

    :param length: steps of the episode
    :param mean_return: sum over steps of the team's mean agent reward
    :param errors: sums over steps of the agents' angle (deg), bearing and neighbour-distance (m) errors over n
    :param collisions: obstacle and agent contacts summed over agents and steps (an agent pair counted by both)
    :param terms: sums over steps of every reward term over n, in the order of ``REWARD_TERMS``
    :param success: the team reached the goal
    :param stage: curriculum stage
    """
    steps = max(length, 1)
    angle, bearing, distance = (error / steps for error in errors)
    return {
        "success": success,
        "length": length,
        "return": mean_return,
        "angle_error_deg": float(angle),
        "bearing_error": float(bearing),
        "neighbour_distance_error": float(distance),
        "collisions_obstacle": collisions[0],
        "collisions_agent": collisions[1] // 2,  # each touching pair is reported by both agents
        "reward_terms": {name: value / steps for name, value in zip(REWARD_TERMS, terms)},
        "stage": stage,
    }
