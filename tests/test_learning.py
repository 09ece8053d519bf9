"""Learning checks: a fast recipe learns to bring its team to the goal within a short budget (the comparison with the
thesis recipe is ``benchmarks/fast_vs_thesis.py``); the recurrent PPO learns a memory task that the MLP policy cannot."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_formation import FormationPolicy
from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.recipes import layered_settings
from sb3_formation.experiment.runs import load_trained
from sb3_formation.experiment.training import train
from sb3_formation.sb3.recurrent import RecurrentFormationPPO

#: The chapter-5 bearing task (Table 5.1, thesis 5.3) in a world that learns in minutes: 3 agents, four times the
#: thesis's v_max (6 cm per step, 3 cm per sub-step < R_a) and 400-step episodes.
SMALL_WORLD = {"n_agents": 3, "v_max": 0.2, "max_steps": 400}
#: Agent-steps of the smoke test's training: 49 iterations of fast-ch5-bearing on 8 teams of 3 (6,144 agent-steps each).
#: The comparison with the thesis recipe on 600,000 agent-steps is ``benchmarks/fast_vs_thesis.py --small-world``.
SMOKE_BUDGET = 300_000


@pytest.mark.slow
def test_the_fast_recipe_learns_to_fly_the_team_to_the_goal(tmp_path: Path, one_torch_thread: None) -> None:
    """Learning smoke test: fast-ch5-bearing, trained for 300,000 agent-steps in the small world, brings its teams
    much closer to the goal than the same recipe after one iteration (an untrained policy in all but one update), on
    the same 40 deterministic stage-3 episodes. It fails when PPO, the rewards, the normaliser or the observations stop
    carrying the goal to the policy."""
    common = {"n_envs": 8, "seed": 0, "progress_bar": False, "env": SMALL_WORLD, "logdir": str(tmp_path)}
    trained_settings = layered_settings(recipe="fast-ch5-bearing", steps=SMOKE_BUDGET, **common)
    untrained_settings = layered_settings(recipe="fast-ch5-bearing", steps=1, **common)
    assert trained_settings.recipe.stage_iterations() == (0, 0, 49)
    assert untrained_settings.recipe.stage_iterations() == (0, 0, 1)
    summaries = {}
    for label, settings in (("trained", trained_settings), ("untrained", untrained_settings)):
        policy = load_trained(train(settings, command="test"))
        result = evaluate(policy, episodes=40, stage=3, seed=0, record=0)
        distances = [episode["final_goal_distance"] for episode in result.episodes]
        summaries[label] = (result.summary["success_rate"], float(np.mean(distances)))
    (trained_rate, trained_distance), (untrained_rate, untrained_distance) = summaries["trained"], summaries["untrained"]
    # the team ends at most half as far from the goal as the untrained policy leaves it, and succeeds at least as often
    assert trained_distance <= 0.5 * untrained_distance, summaries
    assert trained_rate >= untrained_rate, summaries


class CueEnv(gymnasium.Env):
    """A memory task: the first observation shows a cue c in {-1, 1}, later ones show 0; the action at the last step
    (whose observation carries a "last step" flag) earns c * a. Without memory the best is a coin flip."""

    observation_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, length: int = 3) -> None:
        self.length = length

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.cue, self.step_count = float(self.np_random.choice([-1.0, 1.0])), 0
        return np.array([self.cue, 0.0], np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        self.step_count += 1
        done = self.step_count == self.length
        reward = self.cue * float(np.clip(action[0], -1.0, 1.0)) if done else 0.0
        return np.array([0.0, float(self.step_count == self.length - 1)], np.float32), reward, done, False, {}


def cue_success_rate(policy: Any, episodes: int = 200) -> float:
    """Share of episodes whose deterministic last action has the cue's sign (state carried, reset per episode)."""
    env, wins = CueEnv(), 0
    for episode in range(episodes):
        observation, _ = env.reset(seed=10_000 + episode)
        state, start, done, reward = None, np.array([True]), False, 0.0
        while not done:
            action, state = policy.predict(observation[None], state=state, episode_start=start, deterministic=True)
            start = np.array([False])
            observation, reward, done, _, _ = env.step(action[0])
        wins += reward > 0
    return wins / episodes


@pytest.mark.slow
def test_recurrent_ppo_remembers_a_cue_that_the_mlp_cannot() -> None:
    settings = dict(n_steps=32, batch_size=128, learning_rate=1e-3, n_epochs=4, gamma=0.99, seed=0, device="cpu")
    recurrent = RecurrentFormationPPO(
        env=DummyVecEnv([CueEnv] * 16),
        policy_kwargs={"net_arch": {"pi": [32], "pi_recurrent": 32, "vf": [32], "vf_recurrent": 32, "vf_after": []}},
        **settings,
    ).learn(30_000)
    mlp = PPO(
        FormationPolicy, DummyVecEnv([CueEnv] * 16), policy_kwargs={"net_arch": {"pi": [32, 32], "vf": [32, 32]}}, **settings
    ).learn(30_000)
    assert cue_success_rate(recurrent.policy) >= 0.9  # here: 100 %
    assert 0.35 <= cue_success_rate(mlp.policy) <= 0.65  # a coin flip: the last observation holds no cue (here: 50 %)
