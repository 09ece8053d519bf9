"""Evaluating a trained policy on fixed-seed curriculum episodes (thesis 4.4, 5.4): success rate and errors."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .config import FormationConfig
from .normalization import ScaleNormalizeVecEnv
from .training import TrainedModel
from .vec_env import FormationVecEnv

#: Means over successful episodes reported by :func:`evaluate` (keys of the VecEnv's episode summaries).
EPISODE_ERRORS = ("angle_error_deg", "bearing_error", "neighbour_distance_error", "collisions_obstacle", "collisions_agent")


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


@dataclass
class EvaluationResult:
    """Outcome of :func:`evaluate`.

    :param episodes: one summary per episode (success, length, return, mean errors, collisions, reward terms, team)
    :param stage: curriculum stage of the episodes
    :param seed: seed of the teams' scenario generators
    :param deterministic: whether the policy's mean actions were used
    """

    episodes: list[dict[str, Any]]
    stage: int
    seed: int
    deterministic: bool
    summary: dict[str, Any] = field(init=False)

    def __post_init__(self) -> None:
        successes = [episode for episode in self.episodes if episode["success"]]
        low, high = wilson_interval(len(successes), len(self.episodes))
        self.summary = {
            "episodes": len(self.episodes),
            "successes": len(successes),
            "success_rate": len(successes) / len(self.episodes),
            "success_rate_ci95": [low, high],
            "stage": self.stage,
            "seed": self.seed,
            "deterministic": self.deterministic,
            "successful_episode_means": _means(successes),
            "all_episode_means": _means(self.episodes),
        }


def _means(episodes: list[dict[str, Any]]) -> dict[str, float | None]:
    """Mean of each error, collision count and length over ``episodes`` (``None`` when there are none)."""
    return {
        name: float(np.mean([episode[name] for episode in episodes])) if episodes else None
        for name in (*EPISODE_ERRORS, "length")
    }


#: Fields that shape the observation vector: a model only fits envs that agree on them.
OBSERVATION_SHAPING_FIELDS = ("n_agents", "lidar_rays")


def check_model_fits(trained: TrainedModel, config: FormationConfig) -> None:
    """Raise ``ValueError`` naming every difference if ``trained`` cannot act in envs of ``config``."""
    differences = [
        f"{name}={getattr(trained.config, name)} in the model, {getattr(config, name)} in the env"
        for name in OBSERVATION_SHAPING_FIELDS
        if getattr(trained.config, name) != getattr(config, name)
    ]
    if differences:
        raise ValueError("the model does not fit this env's observations: " + "; ".join(differences))


def evaluate(
    trained: TrainedModel,
    episodes: int,
    stage: int = 3,
    seed: int = 0,
    n_envs: int = 8,
    deterministic: bool = True,
    env_overrides: dict[str, Any] | None = None,
) -> EvaluationResult:
    """Play ``episodes`` episodes of ``stage`` with a trained policy, on scenarios fixed by ``seed``.

    The episodes are spread over ``n_envs`` teams; team j draws its scenarios from the seed ``seed + j * n_agents``
    and plays a fixed quota of episodes, so two policies evaluated with the same seed meet the same scenarios.

    :param trained: the model with its configuration and normaliser statistics (:func:`load_trained`)
    :param episodes: number of episodes
    :param stage: curriculum stage of the scenarios (3 in the thesis's evaluations)
    :param seed: seed of the scenarios
    :param n_envs: teams played in parallel
    :param deterministic: use the policy's mean action (else sample)
    :param env_overrides: :class:`FormationConfig` fields to change from the model's training configuration
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    config = trained.config.replace(**{**(env_overrides or {}), "stage": stage})
    check_model_fits(trained, config)
    n_teams = min(n_envs, episodes)
    venv = FormationVecEnv(config, n_envs=n_teams, team_observations=trained.team_observations)
    venv.seed(seed)
    env = ScaleNormalizeVecEnv(venv, venv.agent_observation_dim, venv.binary_observation_mask, training=False)
    env.load_state_dict(trained.normalizer_state)
    quota = math.ceil(episodes / n_teams)
    results: list[list[dict[str, Any]]] = [[] for _ in range(n_teams)]
    observations = env.reset()
    while any(len(team) < quota for team in results):
        actions, _ = trained.model.predict(observations, deterministic=deterministic)
        observations, _, _, infos = env.step(actions)
        for team in range(n_teams):
            summary = infos[team * config.n_agents].get("formation_episode")
            if summary is not None and len(results[team]) < quota:
                results[team].append({**summary, "team": team})
    env.close()
    ordered = [results[team][index] for index in range(quota) for team in range(n_teams)][:episodes]
    return EvaluationResult(ordered, stage, seed, deterministic)
