"""The statistics of evaluation results: a success rate's Wilson interval, and the mean and spread of each episode
metric."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sb3_formation.sb3.metrics import EPISODE_METRICS, SAFETY_METRICS


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
    of each of :data:`SAFETY_METRICS` that the episodes have (a filtered policy's)."""
    names = [*EPISODE_METRICS, *(name for name in SAFETY_METRICS if episodes and all(name in row for row in episodes))]
    return {
        name: {
            "mean": float(np.mean([episode[name] for episode in episodes])) if episodes else None,
            "std": float(np.std([episode[name] for episode in episodes])) if episodes else None,
        }
        for name in names
    }
