"""The statistics of evaluation results: a success rate's Wilson interval, the mean and spread of each episode
metric, and the check of a stored summary's values."""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np

from sb3_formation.env.scenes import DEFAULT_SCENES, SCENES
from sb3_formation.sb3.metrics import EPISODE_METRICS, SAFETY_METRICS, WORLD_METRICS
from sb3_formation.utils.checks import is_count, is_number


def wilson_interval(successes: int, trials: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of a success rate (95 % for the default z).

    :param successes: number of successes
    :param trials: number of trials (> 0)
    :param z: standard-normal quantile of the confidence level
    """
    if trials <= 0 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials and trials > 0, got {successes} of {trials}")
    rate = successes / trials
    denominator = 1 + z * z / trials
    centre = (rate + z * z / (2 * trials)) / denominator
    half_width = z * math.sqrt(rate * (1 - rate) / trials + z * z / (4 * trials * trials)) / denominator
    low = 0.0 if successes == 0 else max(0.0, centre - half_width)  # exact ends: no rounding residue at 0 or n
    high = 1.0 if successes == trials else min(1.0, centre + half_width)
    return low, high


def mean_and_std(episodes: list[dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """Mean and population std of each of :data:`EPISODE_METRICS` over ``episodes`` (``None`` when there are none), and
    of each of :data:`SAFETY_METRICS` (a filtered policy's) and :data:`WORLD_METRICS` that the episodes have."""
    optional = [*SAFETY_METRICS, *WORLD_METRICS]
    names = [*EPISODE_METRICS, *(name for name in optional if episodes and all(name in row for row in episodes))]
    return {
        name: {
            "mean": float(np.mean([episode[name] for episode in episodes])) if episodes else None,
            "std": float(np.std([episode[name] for episode in episodes])) if episodes else None,
        }
        for name in names
    }


def check_summary(summary: Any, path: os.PathLike[str] | str) -> None:
    """Refuse an evaluation summary (``summary.json``, as :attr:`EvaluationResult.summary` writes it) whose values are
    not of the kinds its readers format: a file someone edited or a write cut short would otherwise fail in a table's
    format code, far from the file.

    :param summary: the file's JSON value
    :param path: the file, for the message
    :raises ValueError: naming the file and the first damaged entry
    """

    def damaged(entry: str, expected: str, value: Any) -> ValueError:
        return ValueError(f"{path} is damaged: {entry} must be {expected}, got {value!r:.60}; evaluate again to rewrite it")

    if not isinstance(summary, dict) or "success_rate" not in summary:
        raise ValueError(f"{path} is not an evaluation summary written by sb3-formation")
    rate = summary["success_rate"]
    if not (is_number(rate) and 0 <= rate <= 1):
        raise damaged("success_rate", "a number in [0, 1]", rate)
    interval = summary.get("success_rate_ci95")
    if not (isinstance(interval, list) and len(interval) == 2 and all(is_number(end) for end in interval)):
        raise damaged("success_rate_ci95", "two numbers", interval)
    for key in ("episodes", "stage", "seed"):
        if not is_count(summary.get(key)):
            raise damaged(key, "an integer >= 0", summary.get(key))
    if summary.get("scenes", DEFAULT_SCENES) not in SCENES:
        raise damaged("scenes", f"one of {', '.join(SCENES)}", summary["scenes"])
    for group in ("successful_episodes", "all_episodes"):
        metrics = summary.get(group)
        if not (isinstance(metrics, dict) and set(EPISODE_METRICS) <= set(metrics)):
            raise damaged(group, f"a mapping of the metrics {', '.join(EPISODE_METRICS)}", metrics)
        for name, statistics in metrics.items():
            valid = isinstance(statistics, dict) and all(
                statistics.get(key) is None or is_number(statistics.get(key)) for key in ("mean", "std")
            )
            if not valid or "mean" not in statistics:
                raise damaged(f"{group}.{name}", "a mean and a std (numbers, or null)", statistics)
