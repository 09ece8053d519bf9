"""Learning check: PPO with our VecEnv, normaliser and policy learns an easy stage-1 task that random actions fail."""

from __future__ import annotations

import pytest
from stable_baselines3 import PPO

from sb3_formation import FormationEnv, make_formation_vec_env
from sb3_formation.evaluation import evaluate
from sb3_formation.rollout import random_policy, run_episode
from sb3_formation.training import TrainedModel, thesis_ppo_kwargs

#: Stage 1 of chapter 5 (centroid term on, shape terms off) made easy: 3 agents, four times the thesis's v_max
#: (6 cm per step, 3 cm per sub-step < R_a), a 1.5 m goal radius, 150-step episodes; centroid-goal start distance 3-6 m.
EASY = {"n_agents": 3, "stage": 1, "v_max": 0.2, "eta_g": 1.5, "max_steps": 150}
ITERATIONS = 130


@pytest.mark.slow
def test_ppo_beats_random_actions_on_an_easy_stage_one() -> None:
    env = make_formation_vec_env("ch5-bearing", n_envs=8, seed=0, **EASY)
    kwargs = thesis_ppo_kwargs("ch5-bearing", n_agents=3)
    kwargs["learning_rate"] = 3e-4  # the thesis's 5e-5 needs far more than a test's budget
    kwargs["policy_kwargs"]["net_arch"] = dict(pi=[64, 64], vf=[64, 64])  # smaller networks: minutes, not hours
    model = PPO(env=env, seed=0, device="cpu", **kwargs)
    model.learn(ITERATIONS * model.n_steps * env.num_envs)
    config = env.get_attr("config", indices=[0])[0]
    trained = TrainedModel(model, config, env.state_dict(), team_observations=False)
    learned = evaluate(trained, episodes=40, stage=1, seed=1000).summary["success_rate"]

    random_env = FormationEnv(config)
    policy = random_policy(random_env, seed=0)
    random_successes = [run_episode(random_env, policy, seed=1000 + episode)["success"] for episode in range(40)]
    random_rate = sum(random_successes) / len(random_successes)
    assert random_rate <= 0.05  # here: 0 %; the trained policy reached 67.5 % on this machine
    assert learned >= 0.3, f"learned success rate {learned:.0%} vs random {random_rate:.0%}"
