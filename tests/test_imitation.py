"""Imitation pretraining: behaviour cloning with DAgger relabelling, the critic warm-up, and its place in train/resume."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from stable_baselines3 import PPO

from sb3_formation.controllers import ClassicalController
from sb3_formation.env.config import FormationConfig
from sb3_formation.experiment.recipes import layered_settings, load_recipe
from sb3_formation.experiment.runs import load_trained
from sb3_formation.experiment.training import IMITATION_FILE, resume, train
from sb3_formation.sb3.imitation import ImitationSettings, actor_parameters, pretrain_actor
from sb3_formation.sb3.normalization import ScaleNormalizeVecEnv
from sb3_formation.sb3.policies import FormationPolicy
from sb3_formation.sb3.vec_env import FormationVecEnv

CONFIG = FormationConfig.task("ch5-bearing", stage=3, max_steps=60)


def tiny_imitation_recipe(tmp_path: Path, **imitation: object) -> Path:
    """fast-ch5-bearing shrunk to seconds, its actor first pretrained on controller:classical, as a recipe file."""
    values = {
        "base": "fast-ch5-bearing",
        "imitation": {"controller": "classical", "rounds": 2, "steps": 20, "epochs": 2, "batch_size": 64, "critic_warmup": 2},
        "policy": {"net_arch": {"pi": [16], "vf": [16]}},
        "ppo": {"n_steps": 16, "batch_size": 64, "n_epochs": 2},
        "n_envs": 2,
        "training": {"steps": 4 * 16 * 12, "eval_every": None},
    }
    values["imitation"] |= imitation
    path = tmp_path / "imitate.yaml"
    path.write_text(yaml.safe_dump(values))
    return path


def test_the_actor_is_frozen_while_the_critic_warms_up(tmp_path: Path) -> None:
    recipe = tiny_imitation_recipe(tmp_path)
    snapshots = []

    def run(iterations: int) -> dict[str, torch.Tensor]:
        settings = layered_settings(recipe=str(recipe), steps=iterations * 16 * 12, env={"max_steps": 40}, progress_bar=False)
        folder = train(settings, command="test", run_dir=tmp_path / f"run{iterations}")
        snapshots.append(json.loads((folder / IMITATION_FILE).read_text()))
        return {name: value.clone() for name, value in load_trained(folder).policy.state_dict().items()}

    first, warm, moved = run(1), run(2), run(3)  # the same seed: the same pretraining
    assert snapshots[0] == snapshots[1] == snapshots[2]
    actor = {"mlp_extractor.policy_net.0.weight", "action_net.weight", "action_net.bias", "log_std"}
    for name in actor:
        assert torch.equal(first[name], warm[name]), name  # iterations 1 and 2 warm the critic up
        assert not torch.equal(warm[name], moved[name]), name  # the third moves the actor
    assert not torch.equal(first["value_net.weight"], warm["value_net.weight"])


def test_a_run_killed_before_its_first_checkpoint_is_trained_again_on_resume(tmp_path: Path) -> None:
    settings = layered_settings(recipe=str(tiny_imitation_recipe(tmp_path)), steps=16 * 12, progress_bar=False)
    first = train(settings, command="test", run_dir=tmp_path / "first")
    killed = tmp_path / "killed"  # what a kill during pretraining leaves: settings and command, no checkpoint
    killed.mkdir()
    for name in ("config.yaml", "command.txt"):
        (killed / name).write_text((first / name).read_text())
    assert resume(killed) == killed
    trained, again = load_trained(first), load_trained(killed)
    for name, value in trained.policy.state_dict().items():
        assert torch.equal(value, again.policy.state_dict()[name]), name
    (killed / "checkpoints").rename(tmp_path / "gone")  # a folder whose final model exists is not trained again
    with pytest.raises(FileNotFoundError, match="no complete checkpoint"):
        resume(killed)


def test_imitation_recipes_are_checked(tmp_path: Path) -> None:
    recipe = load_recipe(tiny_imitation_recipe(tmp_path, learning_rate=3e-3))
    controller, settings = recipe.teacher(recipe.config()), recipe.imitation_settings()
    assert isinstance(controller, ClassicalController) and settings == ImitationSettings(2, 20, 2, 64, 3e-3, 2)
    assert recipe.to_dict()["imitation"] == {"controller": "classical", "gains": {}, **vars(settings)}  # read back as given
    with pytest.raises(
        ValueError, match=r"imitation needs controller and may give gains, rounds, .*: unknown keys \['round'\]"
    ):
        recipe.with_changes({"imitation": {"round": 3}})
    with pytest.raises(ValueError, match="imitation: rounds must be an integer >= 1, got 0"):
        recipe.with_changes({"imitation": {"rounds": 0}})
    with pytest.raises(ValueError, match="unknown controller 'pid'"):
        recipe.with_changes({"imitation": {"controller": "pid"}})
    for change in ({"policy": {"recurrent": True}}, {"residual": {"controller": "classical", "scale": 0.3}}):
        with pytest.raises(ValueError, match="not recurrent, not residual"):
            recipe.with_changes(change)


def test_the_actor_parameters_are_the_actor_layers_its_head_and_a_learned_log_std() -> None:
    venv = FormationVecEnv(CONFIG, n_envs=1)
    for learn_sigma, count in ((True, 7), (False, 6)):  # 2 x (weight, bias) layers, the head's (weight, bias), log-std
        policy = PPO(FormationPolicy, venv, n_steps=8, policy_kwargs={"learn_sigma": learn_sigma}).policy
        parameters = actor_parameters(policy)
        assert len(parameters) == count and not any(p is q for p in parameters for q in policy.value_net.parameters())


def teacher_flight(teacher: ClassicalController, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Raw observations of two teams flown by ``teacher`` from scenario seed ``seed`` on, and its actions on them."""
    venv = FormationVecEnv(CONFIG, n_envs=2)
    venv.seed(seed)
    observations, rows, labels = venv.reset(), [], []
    for _ in range(steps):
        actions = teacher.predict(observations)[0]
        rows.append(observations)
        labels.append(actions)
        observations, *_ = venv.step(actions)
    return np.concatenate(rows), np.concatenate(labels)


@pytest.mark.slow
def test_imitation_pretraining_lowers_the_actors_error_against_the_teacher_on_held_out_states() -> None:
    teacher = ClassicalController(CONFIG)
    held_out, labels = teacher_flight(teacher, 200, seed=123)  # scenarios the pretraining never flies
    venv = FormationVecEnv(CONFIG, n_envs=2)
    env = ScaleNormalizeVecEnv(venv, venv.agent_observation_dim, venv.binary_observation_mask, center=True)
    kwargs = {"net_arch": {"pi": [64, 64], "vf": [16]}}
    model = PPO(FormationPolicy, env, n_steps=16, batch_size=64, seed=0, policy_kwargs=kwargs)

    def error() -> float:
        observations = torch.as_tensor(env.normalize_obs(held_out))
        with torch.no_grad():
            actions = model.policy.get_distribution(observations).mode()
        return float(((actions - torch.as_tensor(labels)) ** 2).mean())

    before = error()  # SB3's near-zero first actions: about the labels' own mean square
    assert before == pytest.approx(float((labels**2).mean()), rel=0.05)
    settings = ImitationSettings(rounds=2, steps=100, epochs=200, batch_size=256, learning_rate=1e-3)
    records = pretrain_actor(model, teacher, settings, seed=0)
    assert [record["states"] for record in records] == [1200, 2400]  # 100 steps x 12 slots per round
    assert error() < 0.5 * before
