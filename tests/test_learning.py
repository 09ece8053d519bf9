"""Learning checks: PPO with our VecEnv, normaliser and policy learns an easy stage-1 task that random actions fail;
the recurrent PPO learns a memory task that the MLP policy cannot."""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
import pytest
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_formation import FormationPolicy, make_formation_vec_env
from sb3_formation.controllers import RandomController
from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.setups import load_setup
from sb3_formation.sb3.recurrent import RecurrentFormationPPO
from sb3_formation.sb3.trained import TrainedPolicy

#: Stage 1 of chapter 5 (centroid term on, shape terms off) made easy: 3 agents, four times the thesis's v_max
#: (6 cm per step, 3 cm per sub-step < R_a), a 1.5 m goal radius, 150-step episodes; centroid-goal start distance 3-6 m.
EASY = {"n_agents": 3, "stage": 1, "v_max": 0.2, "eta_g": 1.5, "max_steps": 150}
ITERATIONS = 130


@pytest.mark.slow
def test_ppo_beats_random_actions_on_an_easy_stage_one() -> None:
    env = make_formation_vec_env("ch5-bearing", n_envs=8, seed=0, **EASY)
    config = env.get_attr("config", indices=[0])[0]
    kwargs = load_setup("ch5-bearing").ppo_kwargs(config, recurrent=False)
    kwargs["learning_rate"] = 3e-4  # the thesis's 5e-5 needs far more than a test's budget
    kwargs["policy_kwargs"]["net_arch"] = dict(pi=[64, 64], vf=[64, 64])  # smaller networks: minutes, not hours
    model = PPO(env=env, seed=0, device="cpu", **kwargs)
    model.learn(ITERATIONS * model.n_steps * env.num_envs)
    trained = TrainedPolicy(model, config, env.state_dict())
    learned = evaluate(trained, episodes=40, stage=1, seed=1000).summary["success_rate"]
    random_rate = evaluate(RandomController(config, seed=0), episodes=40, stage=1, seed=1000).summary["success_rate"]
    assert random_rate <= 0.05  # here: 0 %; the trained policy reached 67.5 % on this machine
    assert learned >= 0.3, f"learned success rate {learned:.0%} vs random {random_rate:.0%}"


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
