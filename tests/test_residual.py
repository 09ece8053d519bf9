"""Residual policies: the controller's action plus a bounded learned correction, in training and in evaluation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from PIL import Image

from sb3_formation.cli import main
from sb3_formation.controllers import ClassicalController, ShrinkingController
from sb3_formation.controllers.base import AgentStep, Policy, no_messages
from sb3_formation.controllers.residual import ResidualAdapter, ResidualPolicy, add_correction
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.recipes import RECIPES_FOLDER, Recipe, load_recipe
from sb3_formation.experiment.targets import load_policy
from sb3_formation.sb3.residual import ResidualVecEnv
from sb3_formation.sb3.vec_env import FormationVecEnv

CH5 = FormationConfig.task("ch5-bearing", stage=3)


class ConstantPolicy(Policy):
    """A correction that is the same action for every row."""

    def __init__(self, config: FormationConfig, action: tuple[float, float]) -> None:
        self.config, self.action = config, np.asarray(action, dtype=np.float32)

    def fit(self, config: FormationConfig) -> ConstantPolicy:
        return self

    def _agent_step(self, observations, agents, state, episode_start, received, deterministic):
        rows = len(np.asarray(observations).reshape(-1, np.shape(observations)[-1]))
        return AgentStep(np.tile(self.action, (rows, 1)), None, no_messages(rows))


def test_a_correction_is_bounded_and_the_sum_clipped() -> None:
    base = np.array([[0.5, -0.9], [0.0, 0.95]])
    # corrections are clipped to [-1, 1] first (as the env clips actions), then scaled by 0.3, then the sum clipped
    corrected = add_correction(base, np.array([[1.0, -1.0], [-4.0, 0.5]]), 0.3)
    np.testing.assert_allclose(corrected, [[0.8, -1.0], [-0.3, 1.0]], atol=1e-7)
    with pytest.raises(ValueError, match="residual scale must be a number in \\(0, 2\\]"):
        ResidualPolicy(ClassicalController(CH5), ConstantPolicy(CH5, (0, 0)), 0.0)


@pytest.mark.parametrize("kind", [ClassicalController, ShrinkingController])
def test_a_zero_correction_acts_exactly_as_the_controller(kind: type) -> None:
    """Also for a controller with memory: the residual policy carries it in its state and resets it at episode starts."""
    controller = kind(CH5)
    zero = ResidualPolicy(controller, ConstantPolicy(CH5, (0.0, 0.0)), 0.3)
    shifted = ResidualPolicy(controller, ConstantPolicy(CH5, (0.5, 0.0)), 0.3)
    env = FormationEnv(CH5)
    rows = np.stack(list(env.reset(seed=2)[0].values()))
    memory = zero_state = shifted_state = None
    for _ in range(40):
        actions, memory = controller.predict(rows, memory)
        zero_actions, zero_state = zero.predict(rows, zero_state)
        shifted_actions, shifted_state = shifted.predict(rows, shifted_state)
        np.testing.assert_array_equal(zero_actions, actions)
        np.testing.assert_allclose(shifted_actions, np.clip(actions + np.array([0.15, 0.0]), -1, 1), atol=1e-6)
        rows, *_ = env.step_array(actions)
    # evaluated episodes are the controller's, bit for bit
    protocol = {"episodes": 3, "stage": 3, "seed": 5, "n_envs": 2, "env_overrides": {"max_steps": 150}, "record": 0}
    assert evaluate(zero, **protocol).episodes == evaluate(controller, **protocol).episodes


def test_the_adapter_serves_a_team_or_one_agent_and_resets_the_memory_of_the_rows_that_start_an_episode() -> None:
    """The same adapter acts for a whole team (rows in team order) and for each agent alone (its row and its index),
    each caller carrying its own memory; a row flagged as starting an episode acts as with no memory at all."""
    config = CH5.replace(scenes="passage")
    adapter = ResidualAdapter(ShrinkingController(config), 0.3)
    env = FormationEnv(config)
    rows = np.stack(list(env.reset(seed=2)[0].values()))
    correction = np.tile([0.2, 0.0], (6, 1))
    starts = np.arange(6) < 3  # agents 0-2 start an episode, 3-5 go on
    memory, own_memories, forgetful = None, [None] * 6, 0
    for _ in range(80):
        fresh = adapter.corrected(rows, correction)[0]  # no memory: every row starts an episode
        restarted = adapter.corrected(rows, correction, memory, starts)[0]
        actions, memory = adapter.corrected(rows, correction, memory)
        np.testing.assert_array_equal(restarted[:3], fresh[:3])
        np.testing.assert_array_equal(restarted[3:], actions[3:])
        forgetful += not np.array_equal(actions, fresh)
        for agent in range(6):
            alone, own_memories[agent] = adapter.corrected(
                rows[[agent]], correction[[agent]], own_memories[agent], agents=np.array([agent])
            )
            np.testing.assert_array_equal(alone[0], actions[agent])
        rows, *_ = env.step_array(actions)
    assert forgetful > 20  # 37 of the 80 steps: the memory changes the actions, so the reset is what made them agree


def test_the_training_env_carries_a_controllers_memory_and_resets_it_when_an_episode_ends() -> None:
    """With zero corrections the residual VecEnv steps as the shrinking controller does when its memory is carried
    from step to step and reset where an episode ended (SB3's predict contract), through two episodes of a passage."""
    config = CH5.replace(scenes="passage", max_steps=60)
    controller = ShrinkingController(config)
    residual = ResidualVecEnv(FormationVecEnv(config, n_envs=2), controller, 0.3)
    plain = FormationVecEnv(config, n_envs=2)
    residual.seed(3)
    plain.seed(3)
    observations, expected = residual.reset(), plain.reset()
    memory, starts, forgetful = None, np.ones(12, dtype=bool), 0
    for _ in range(130):  # episodes end at steps 60 and 120
        np.testing.assert_array_equal(observations, expected)
        actions, memory = controller.predict(expected, memory, starts)
        forgetful += not np.array_equal(actions, controller.predict(expected)[0])  # memory changes the actions
        observations, *_ = residual.step(np.zeros((12, 2), dtype=np.float32))
        expected, _, starts, _ = plain.step(actions)
    assert forgetful > 60
    residual.close()
    plain.close()


def test_the_training_env_adds_the_controller_to_the_agent_action() -> None:
    """Stepping the residual VecEnv with zero corrections replays the controller's team, slot by slot."""
    controller = ClassicalController(CH5)
    venv = ResidualVecEnv(FormationVecEnv(CH5, n_envs=2, team_observations=True), controller, 0.3)
    venv.seed(11)
    observations = venv.reset()
    env = FormationEnv(CH5)
    rows = np.stack(list(env.reset(seed=11 + 6)[0].values()))  # team 1's seed: 11 + 1 * n_agents
    for _ in range(25):
        np.testing.assert_array_equal(observations[6:12, : rows.shape[1]], rows)
        observations, *_ = venv.step(np.zeros((12, 2), dtype=np.float32))
        rows, *_ = env.step_array(controller.predict(rows)[0])
    venv.close()


def test_in_teams_of_several_sizes_each_team_gets_the_controller_of_its_size() -> None:
    config = CH5.replace(observe_reference_bearings=True)
    controller = ClassicalController(config)
    venv = ResidualVecEnv(FormationVecEnv(config, n_envs=2, team_sizes=[3, 4]), controller, 0.3)
    venv.seed(11)
    observations = venv.reset()
    square = config.replace(n_agents=4)
    env = FormationEnv(square)
    rows = np.stack(list(env.reset(seed=11 + 3)[0].values()))  # team 1 (4 agents) starts at slot 3
    for _ in range(25):
        np.testing.assert_array_equal(observations[3:7], rows)
        observations, *_ = venv.step(np.zeros((7, 2), dtype=np.float32))
        rows, *_ = env.step_array(ClassicalController(square).predict(rows)[0])
    with pytest.raises(ValueError, match=r"actions must have shape \(7, 2\), one row per slot, got \(2, 7\)"):
        venv.step(np.zeros((2, 7)))  # the correction is checked before the controller's action is added
    venv.close()


def test_a_residual_setup_trains_saves_and_loads_as_a_residual_policy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # compare writes the controller's evaluation under evaluations/
    values = yaml.safe_load((RECIPES_FOLDER / "residual-ch5-bearing.yaml").read_text())
    values["policy"]["net_arch"] = {"pi": [16], "vf": [16]}
    values["ppo"] |= {"n_steps": 16, "batch_size": 64, "n_epochs": 2}
    values["n_envs"] = 2
    values["training"] |= {"steps": 2 * 16 * 12, "eval_every": 1, "eval_episodes": 2}
    setup = tmp_path / "residual.yaml"
    setup.write_text(yaml.safe_dump(values))
    run = tmp_path / "run"
    assert main(["train", "--recipe", str(setup), "--env", "max_steps=40", "--run-dir", str(run), "--no-progress"]) == 0
    # compare takes runs and controllers together: --recipe is the controllers' recipe
    quick = ["--episodes", "2", "--n-envs", "2", "--no-progress", "--out", str(tmp_path / "c.png")]
    assert main(["compare", str(run), "controller:classical", "--recipe", "ch5-bearing", *quick]) == 0
    policy = load_policy(run)
    assert isinstance(policy, ResidualPolicy) and policy.scale == 0.3 and isinstance(policy.base, ClassicalController)
    # with the correction's mean set to zero the trained policy acts as the controller
    with torch.no_grad():
        for parameter in policy.correction.policy.action_net.parameters():
            parameter.zero_()
    env = FormationEnv(policy.config.replace(stage=3))
    rows = np.stack(list(env.reset(seed=4)[0].values()))
    for _ in range(20):
        actions = policy.predict(rows)[0]
        np.testing.assert_array_equal(actions, policy.base.predict(rows)[0])
        rows, *_ = env.step_array(actions)


def test_a_policy_trained_on_several_team_sizes_acts_in_teams_of_any_size(tmp_path: Path) -> None:
    values = {  # the shipped recipe, shrunk: a recipe that names it as its base
        "base": "mixed-ch5-bearing",
        "policy": {"net_arch": {"pi": [16], "vf": [16]}},
        "ppo": {"n_steps": 16, "batch_size": 16, "n_epochs": 1},
        "n_envs": 2,
        "team_sizes": [3, 4],
        "training": {"steps": 16 * 7, "eval_every": None},
    }
    setup = tmp_path / "mixed.yaml"
    setup.write_text(yaml.safe_dump(values))
    run = tmp_path / "run"
    assert main(["train", "--recipe", str(setup), "--env", "max_steps=30", "--run-dir", str(run), "--no-progress"]) == 0
    policy = load_policy(run)
    assert policy.correction.team_sizes == (3, 4) and policy.correction.any_team_size
    for n in (3, 7):  # a size it was trained on and one it never saw
        result = evaluate(policy, episodes=2, n_envs=2, env_overrides={"n_agents": n}, record=0)
        assert result.n_agents == n and len(result.episodes) == 2
    gif = tmp_path / "five.gif"
    assert main(["render", str(run), "--agents", "5", "--max-steps", "4", "--out", str(gif)]) == 0
    with Image.open(gif) as image:
        assert image.n_frames == 5  # the first observation and 4 steps
    assert main(["render", str(run), "--agents", "2", "--out", str(tmp_path / "two.gif")]) == 2  # the size reaches the env
    assert not (tmp_path / "two.gif").exists()
    one_size = tmp_path / "one-size"
    assert (
        main(
            [
                "train",
                "--recipe",
                str(setup),
                "--agents",
                "4",
                "--env",
                "max_steps=30",
                "--run-dir",
                str(one_size),
                "--no-progress",
            ]
        )
        == 0
    )
    single = load_policy(one_size)
    assert single.correction.team_sizes == (4,) and not single.correction.any_team_size
    with pytest.raises(ValueError, match="n_agents=4 in the model, 7 in the env"):
        evaluate(single, episodes=1, env_overrides={"n_agents": 7})


def test_residual_recipes_are_checked() -> None:
    setup = load_recipe("residual-ch5-bearing")
    values = setup.to_dict()
    with pytest.raises(ValueError, match="residual needs controller and scale"):
        Recipe.from_dict({**values, "residual": {"controller": "classical"}})
    with pytest.raises(ValueError, match="unknown controller 'pid'"):
        Recipe.from_dict({**values, "residual": {"controller": "pid", "scale": 0.3}})
    with pytest.raises(ValueError, match="unknown gains \\['k_gaol'\\]"):
        Recipe.from_dict({**values, "residual": {"controller": "classical", "scale": 0.3, "gains": {"k_gaol": 1}}})
    with pytest.raises(
        ValueError, match="residual: the residual scale must be a number in \\(0, 2\\] \\(a fraction of F_max\\), got 3"
    ):
        Recipe.from_dict({**values, "residual": {"controller": "classical", "scale": 3}})
    with pytest.raises(ValueError, match="controller 'privileged-planner' reads the map \\(privileged\\)"):
        Recipe.from_dict({**values, "residual": {"controller": "privileged-planner", "scale": 0.3}})
