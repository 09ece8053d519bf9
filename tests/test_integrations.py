"""Other libraries take the environment as it is: TorchRL's PettingZoo wrapper (and so BenchMARL), and SB3's
own tools on our VecEnv (EvalCallback with synchronised normaliser statistics, VecNormalize's API)."""

from __future__ import annotations

import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

from sb3_formation import FormationConfig, FormationEnv, make_formation_vec_env
from sb3_formation.env.config import REWARD_INFO_KEYS
from sb3_formation.sb3.normalization import ScaleNormalizeVecEnv

TASKS = ["ch4-individual", "ch4-team", "ch5-angle", "ch5-bearing"]


@pytest.mark.parametrize("preset", TASKS)
def test_torchrl_wraps_checks_and_rolls_out_every_preset(preset: str) -> None:
    """docs/libraries.md: TorchRL's ``PettingZooWrapper`` builds, ``check_env_specs`` passes and a 50-step rollout
    runs; the flat reward terms arrive as one tensor each."""
    from torchrl.envs.libs.pettingzoo import PettingZooWrapper
    from torchrl.envs.utils import check_env_specs

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # TorchRL names the PettingZoo version it was tested with
        env = PettingZooWrapper(FormationEnv(FormationConfig.task(preset, stage=3)), categorical_actions=False, seed=0)
    check_env_specs(env)
    rollout = env.rollout(50)
    n_agents = FormationConfig.task(preset).n_agents
    assert rollout.batch_size == torch.Size([50])
    assert rollout["next", "agent", "reward"].shape == (50, n_agents, 1)
    info = rollout["next", "agent", "info"]
    assert all(info[key].shape == (50, n_agents) for key in REWARD_INFO_KEYS)
    assert torch.isfinite(rollout["next", "agent", "observation"]).all()


def test_eval_callback_evaluates_with_the_training_statistics_frozen(tmp_path: Path) -> None:
    """``ScaleNormalizeVecEnv`` is a ``VecNormalize``, so ``EvalCallback`` synchronises a second
    env's statistics with the training env's (``sync_envs_normalization``) and the frozen copy does not move."""
    train_env = make_formation_vec_env("ch4-individual", n_envs=2, seed=0, max_steps=10)
    eval_env = make_formation_vec_env("ch4-individual", n_envs=1, seed=100, max_steps=10)
    eval_env.training = False
    assert isinstance(train_env, VecNormalize) and not train_env.norm_reward
    model = PPO("MlpPolicy", train_env, n_steps=16, batch_size=48, n_epochs=1, seed=0, device="cpu")
    assert model.get_vec_normalize_env() is train_env
    # evaluated at the last step of the only rollout: nothing updates the training statistics after the copy
    callback = EvalCallback(eval_env, n_eval_episodes=2, eval_freq=16, log_path=str(tmp_path), verbose=0)
    model.learn(16 * train_env.num_envs, callback=callback)
    assert eval_env.obs_rms is not train_env.obs_rms
    assert eval_env.obs_rms.count == train_env.obs_rms.count == 6 * (1 + 16)  # 6 slots: reset, then 16 steps
    assert np.array_equal(eval_env.obs_rms.var, train_env.obs_rms.var)
    assert np.array_equal(
        eval_env.normalize_obs(eval_env.get_original_obs()), train_env.normalize_obs(eval_env.get_original_obs())
    )
    # unnormalize_obs undoes normalize_obs (where nothing was clipped)
    raw = train_env.get_original_obs()
    scaled = train_env.normalize_obs(raw)
    inside = np.abs(scaled) < train_env.clip_obs
    assert np.allclose(train_env.unnormalize_obs(scaled)[inside], raw[inside], rtol=1e-5, atol=1e-6)


def test_a_saved_normaliser_loads_through_vec_normalize_api(tmp_path: Path) -> None:
    """``ScaleNormalizeVecEnv.load(path, venv)`` as ``VecNormalize.load(path, venv)``: frozen by default."""
    env = make_formation_vec_env("ch4-individual", n_envs=1, seed=0)
    env.reset()
    for _ in range(5):
        env.step(np.zeros((env.num_envs, 2)))
    env.save(tmp_path / "normalizer.npz")
    loaded = ScaleNormalizeVecEnv.load(tmp_path / "normalizer.npz", make_formation_vec_env("ch4-individual", normalize=False))
    assert isinstance(loaded, VecNormalize) and not loaded.training
    assert np.array_equal(loaded.obs_rms.var, env.obs_rms.var) and loaded.obs_rms.count == env.obs_rms.count


#: The documentation page whose snippets these tests run (docs/libraries.md, "Using it with other libraries").
LIBRARIES_PAGE = Path(__file__).parents[1] / "docs" / "libraries.md"


def page_snippets(heading: str) -> list[str]:
    """The ```python blocks under a heading (## or deeper) of the libraries page, up to the next heading, in order."""
    text = LIBRARIES_PAGE.read_text()
    body = re.split(rf"\n#{{2,6}} {re.escape(heading)}\n", text, maxsplit=1)[1]
    body = re.split(r"\n#{2,6} ", body, maxsplit=1)[0]  # headings, not comments in code
    return re.findall(r"```python\n(.*?)```", body, flags=re.DOTALL)


def run_snippets(snippets: list[str]) -> dict[str, Any]:
    """Run code blocks, as written, one after another in one namespace, and return it."""
    namespace: dict[str, Any] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        for snippet in snippets:
            exec(snippet, namespace)  # the documentation's own code
    return namespace


def test_the_snippets_for_other_libraries_run_and_say_what_they_measure() -> None:
    """The libraries page's snippets, as written, in one namespace; then what they claim."""
    snippets = page_snippets("In the package's environment")
    assert len(snippets) == 4
    namespace = run_snippets(snippets)
    assert namespace["rollout"]["next", "agent", "reward"].shape == (50, 6, 1)
    train_env, eval_env = namespace["train_env"], namespace["eval_env"]
    assert np.array_equal(eval_env.obs_rms.var, train_env.obs_rms.var)  # synchronised at the last evaluation
    # evaluate_policy scored the three agents of one team-episode: replay it and sum each slot's rewards
    scores, lengths = namespace["scores"], namespace["lengths"]
    env, model = make_formation_vec_env("ch4-individual", n_envs=1, seed=0, max_steps=5), namespace["model"]
    observations, returns = env.reset(), np.zeros(env.num_envs)
    for _ in range(5):
        observations, rewards, dones, infos = env.step(model.predict(observations, deterministic=True)[0])
        returns += rewards
    assert dones.all() and list(lengths) == [5, 5, 5]
    assert np.allclose(scores, returns)  # agent-episodes: one score per agent
    assert "episode" in infos[0] and "episode" not in infos[1]  # the VecEnv's own team-episode record
    assert infos[0]["episode"]["r"] == pytest.approx(returns.mean())
    monitored = VecMonitor(make_formation_vec_env("ch4-individual", n_envs=1, seed=0, max_steps=5))
    monitored.reset()
    for _ in range(5):
        _, _, dones, infos = monitored.step(np.zeros((3, 2)))
    assert all("episode" in info for info in infos)  # VecMonitor: every agent an episode
    # SuperSuit: 2 copies of a 3-agent team, one PPO iteration of 16 steps in each of the 6 slots
    assert namespace["venv"].num_envs == 6 and namespace["ss_model"].num_timesteps == 16 * 6


@pytest.mark.integrations
def test_the_snippets_for_rllib_and_video_recording_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """In ``make test-integrations``'s environment: RLlib trains one shared module for one
    iteration on the PettingZoo env, its wrapper renders, and SB3's ``VecVideoRecorder`` writes the episode's frames."""
    pytest.importorskip("ray.rllib", reason="RLlib is in the integrations extra: make test-integrations runs this")
    pytest.importorskip("moviepy", reason="moviepy is in the integrations extra: make test-integrations runs this")
    import imageio.v3 as iio
    import ray
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    monkeypatch.chdir(tmp_path)  # the video goes to ./videos
    rllib_snippet, video_snippet = page_snippets("In a separate environment: RLlib and SB3's `VecVideoRecorder`")
    try:
        namespace = run_snippets([rllib_snippet])
    finally:
        ray.shutdown()
    sampled = namespace["result"]["env_runners"]
    assert sampled["num_env_steps_sampled_lifetime"] == 600
    assert sampled["num_agent_steps_sampled_lifetime"] == {f"agent_{i}": 600 for i in range(6)}
    assert set(namespace["result"]["learners"]) == {"shared", "__all_modules__"}  # one shared module, updated
    wrapped = ParallelPettingZooEnv(FormationEnv(FormationConfig.task("ch5-bearing", stage=3), render_mode="rgb_array"))
    wrapped.reset(seed=0)
    frame = wrapped.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3

    run_snippets([video_snippet])
    frames = list(iio.imiter(tmp_path / "videos" / "ch5-bearing-step-0-to-step-200.mp4", plugin="FFMPEG"))
    first_frames = []
    for seed in (0, 1):
        env = make_formation_vec_env("ch5-bearing", n_envs=1, stage=3, seed=seed, render_mode="rgb_array", normalize=False)
        env.reset()
        first_frames.append(env.render())
    assert len(frames) == 200 and frames[0].shape == first_frames[0].shape  # one team: the plain view
    # the video opens on the reset frame of seed 0 (up to its compression: mean 1.7 of 255 measured), not of seed 1 (9.6)
    own, other = (np.abs(frames[0].astype(float) - first).mean() for first in first_frames)
    assert own < 3 < other


@pytest.mark.integrations
def test_benchmarl_trains_mappo_on_the_formation_task_for_two_iterations(tmp_path: Path) -> None:
    """In ``make test-integrations``'s environment: BenchMARL 1.5.2 (TorchRL 0.11, torch and
    torchvision 2.14.1 / 0.29.1) trains MAPPO with one shared policy on teams of six; episodes end and are counted, and
    the policy's weights change."""
    pytest.importorskip("benchmarl", reason="BenchMARL is in the integrations extra: make test-integrations runs this")
    from benchmarl.algorithms import MappoConfig
    from benchmarl.experiment import Experiment, ExperimentConfig
    from benchmarl.models.mlp import MlpConfig

    from sb3_formation.experiment.benchmarl_task import FormationTask

    config = ExperimentConfig.get_from_yaml()
    config.max_n_iters, config.max_n_frames = 2, None
    config.on_policy_collected_frames_per_batch, config.on_policy_n_envs_per_worker = 200, 2
    config.on_policy_n_minibatch_iters, config.on_policy_minibatch_size = 2, 50
    config.evaluation, config.render, config.loggers, config.create_json = False, False, ["csv"], False
    config.save_folder, config.checkpoint_at_end = str(tmp_path), False
    task = FormationTask.CH5_BEARING.get_task({"stage": 3, "max_steps": 60})  # 100 steps per env: episodes end
    experiment = Experiment(
        task=task,
        algorithm_config=MappoConfig.get_from_yaml(),
        model_config=MlpConfig.get_from_yaml(),
        critic_model_config=MlpConfig.get_from_yaml(),
        seed=0,
        config=config,
    )
    assert experiment.group_map == {"agent": [f"agent_{i}" for i in range(6)]}
    before = [parameter.detach().clone() for parameter in experiment.policy.parameters()]
    experiment.run()
    assert experiment.n_iters_performed == 2 and experiment.total_frames == 400
    assert any(not torch.equal(old, new) for old, new in zip(before, experiment.policy.parameters()))
    returns = list(tmp_path.rglob("collection_agent_reward_episode_reward_mean.csv"))
    assert returns, sorted(path.name for path in tmp_path.rglob("*.csv"))
    values = [float(line.split(",")[1]) for line in returns[0].read_text().split()]
    assert len(values) == 2 and all(np.isfinite(values))
