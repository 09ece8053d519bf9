"""Training features any recipe can use: schedules as data, a learned log-std, reward normalisation, a steps budget,
periodic evaluation with the best model kept; and the fast recipes, each trained for an iteration."""

from __future__ import annotations

import csv
import json
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import unwrap_vec_wrapper
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sb3_formation import FormationPolicy, make_formation_vec_env
from sb3_formation.cli import main
from sb3_formation.experiment.recipes import (
    RECIPES_FOLDER,
    TrainSettings,
    layered_settings,
    load_recipe,
    load_settings,
    recipe_names,
)
from sb3_formation.experiment.runs import (
    BEST_MODEL,
    FINAL_MODEL,
    FINAL_NORMALIZER,
    latest_checkpoint,
    load_trained,
    reward_normalizer,
    reward_normalizer_file,
    save_model,
)
from sb3_formation.experiment.sections import schedule
from sb3_formation.experiment.training import make_training_env, train
from sb3_formation.sb3.callbacks import ClockedSchedule, TrainingClock
from sb3_formation.sb3.normalization import ScaleNormalizeVecEnv
from sb3_formation.sb3.recurrent import RecurrentFormationPolicy

SMALL = {"net_arch": {"pi": [16], "vf": [16]}}
#: A tiny run of a recipe: 2 teams, 30-step episodes, small networks, few steps per iteration.
TINY = ["--n-envs", "2", "--env", "max_steps=30", "--no-progress"]


def tiny_yaml(tmp_path: Path, **changes: object) -> Path:
    """The fast-ch5-bearing recipe shrunk to seconds, with ``changes`` applied, as a recipe file."""
    values = yaml.safe_load((RECIPES_FOLDER / "fast-ch5-bearing.yaml").read_text())
    values["policy"]["net_arch"] = SMALL["net_arch"]
    values["ppo"] |= {"n_steps": 16, "batch_size": 64, "n_epochs": 2}
    values["env"] |= {"max_steps": 30}
    values["n_envs"] = 2
    values["training"] |= {"steps": 3 * 16 * 12, "eval_every": 1, "eval_episodes": 2}
    values.update(changes)
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(values))
    return path


def test_schedules_are_data() -> None:
    assert schedule(3e-4) == 3e-4
    linear = schedule({"start": 3e-4, "end": 1.5e-5})
    # SB3 schedules take the progress remaining: 1 at the start, 0 at the end of the budget
    assert linear(1.0) == pytest.approx(3e-4) and linear(0.0) == pytest.approx(1.5e-5)
    assert linear(0.5) == pytest.approx((3e-4 + 1.5e-5) / 2) and linear(0.25) == pytest.approx(1.5e-5 + 0.25 * 2.85e-4)
    for bad in (0, -1e-3, "fast", {"start": 1e-3}, {"start": 1e-3, "end": 0}, True, float("nan")):
        with pytest.raises(ValueError, match="must be a number > 0 or"):
            schedule(bad)


def test_a_learned_log_std_trains_and_is_saved(tmp_path: Path) -> None:
    env = make_formation_vec_env("ch5-bearing", n_envs=1, seed=0, max_steps=30)
    model = PPO(FormationPolicy, env, n_steps=16, batch_size=48, n_epochs=3, learning_rate=1e-2, seed=0, device="cpu",
                policy_kwargs={**SMALL, "sigma": 0.5, "learn_sigma": True})  # fmt: skip
    assert model.policy.log_std.requires_grad
    np.testing.assert_allclose(model.policy.log_std.detach().numpy(), np.log(0.5), rtol=1e-6)
    assert any(
        parameter is model.policy.log_std for group in model.policy.optimizer.param_groups for parameter in group["params"]
    )
    model.learn(2 * 16 * env.num_envs)
    learned = model.policy.log_std.detach().clone()
    assert not torch.allclose(learned, torch.full_like(learned, np.log(0.5)))  # it moved
    model.save(tmp_path / "model.zip")
    loaded = PPO.load(tmp_path / "model.zip", device="cpu")
    assert loaded.policy.learn_sigma and torch.equal(loaded.policy.log_std.detach(), learned)
    fixed = PPO(FormationPolicy, env, n_steps=16, batch_size=48, seed=0, device="cpu", policy_kwargs=SMALL)
    fixed.learn(16 * env.num_envs)
    assert not fixed.policy.log_std.requires_grad and torch.allclose(fixed.policy.log_std, torch.full((2,), np.log(0.7)))
    recurrent = RecurrentFormationPolicy(env.observation_space, env.action_space, lambda _: 1e-3, learn_sigma=True)
    assert recurrent.log_std.requires_grad
    env.close()


def test_reward_normalisation_divides_by_the_running_return_std(tmp_path: Path) -> None:
    """The rewards PPO sees are the env's divided by sqrt(var + 1e-8) of the discounted returns seen so far (SB3's
    VecNormalize, recomputed here with numpy), and the statistics survive a save and a resume."""
    settings = layered_settings(recipe=str(tiny_yaml(tmp_path)), n_envs=1)
    env = make_training_env(settings, stage=3)
    rewards = reward_normalizer(env)
    assert rewards is not None and not rewards.norm_obs and rewards.gamma == 0.99
    env.seed(0)
    env.reset()
    returns, raw_returns = np.zeros(env.num_envs), []
    for _ in range(20):
        _, normalised, dones, _ = env.step(np.zeros((env.num_envs, 2), np.float32))
        raw = rewards.get_original_reward()
        returns = returns * 0.99 + raw
        raw_returns.append(returns.copy())
        expected = np.clip(raw / np.sqrt(np.var(np.concatenate(raw_returns)) + 1e-8), -10, 10)
        np.testing.assert_allclose(normalised, expected, rtol=1e-4, atol=1e-6)
        returns[dones] = 0.0
    model = PPO(FormationPolicy, env, n_steps=8, batch_size=24, seed=0, device="cpu", policy_kwargs=SMALL)
    save_model(model, env, tmp_path, FINAL_MODEL, FINAL_NORMALIZER)
    saved = np.load(tmp_path / reward_normalizer_file(FINAL_NORMALIZER))
    # SB3 starts the statistics with a prior of 1e-4 samples of variance 1: a relative difference of about 1e-6 here
    assert float(saved["var"]) == pytest.approx(np.var(np.concatenate(raw_returns)), rel=1e-5)
    assert float(saved["count"]) == pytest.approx(len(np.concatenate(raw_returns)) + 1e-4)  # SB3 starts at 1e-4
    resumed = make_training_env(settings, stage=3, normalizer_path=tmp_path / FINAL_NORMALIZER)
    assert reward_normalizer(resumed).ret_rms.var == pytest.approx(float(saved["var"]))
    env.close()
    resumed.close()


def test_centred_observations_train_save_and_act_as_the_training_normaliser(tmp_path: Path) -> None:
    training = {**load_recipe("fast-ch5-bearing").training.to_dict(), "center_observations": True, "steps": 16 * 12}
    training["eval_every"] = None
    settings = layered_settings(recipe=str(tiny_yaml(tmp_path, training=training)), progress_bar=False)
    env = make_training_env(settings, stage=3)
    assert unwrap_vec_wrapper(env, ScaleNormalizeVecEnv).center
    folder = train(settings, command="test", run_dir=tmp_path / "run")
    policy = load_trained(folder)
    state = policy.normalizer_state
    assert bool(state["center"])
    raw = np.random.default_rng(0).normal(state["mean"], np.sqrt(state["var"]), size=(6, state["mean"].size))
    raw[:, state["binary_mask"]] = 1.0
    scale = np.sqrt(state["var"] + state["epsilon"])
    expected = np.where(state["binary_mask"], raw, np.clip((raw - state["mean"]) / scale, -10, 10)).astype(np.float32)
    actions = policy.predict(raw, deterministic=True)[0]
    np.testing.assert_array_equal(actions, policy.policy.predict(expected, deterministic=True)[0])


def test_a_steps_budget_sets_the_last_stage_and_repeats_by_seed(tmp_path: Path) -> None:
    budget = ["--steps", str(3 * 16 * 12 + 1)]  # three iterations of 16 steps x 12 slots, and one step more
    setup = str(tiny_yaml(tmp_path, training={"normalize_reward": True}))
    runs = []
    for name in ("a", "b"):
        assert main(["train", "--recipe", setup, *budget, "--run-dir", str(tmp_path / name), *TINY]) == 0
        runs.append(load_trained(tmp_path / name))
    config = yaml.safe_load((tmp_path / "a" / "config.yaml").read_text())
    assert config["training"]["steps"] == 3 * 16 * 12 + 1
    assert load_settings(tmp_path / "a").recipe.stage_iterations() == (0, 0, 4)  # rounded up to whole iterations
    assert runs[0].model.num_timesteps == 4 * 16 * 12
    for first, second in zip(runs[0].model.policy.parameters(), runs[1].model.policy.parameters()):
        assert torch.equal(first, second)  # the same seed gives the same model


def test_a_steps_budget_spreads_a_curriculum_in_its_proportions() -> None:
    # thesis 5.3: 5000 : 5000 : 15000 iterations; 128 steps x 8 teams x 3 agents = 3072 agent-steps per iteration
    common = {"n_envs": 8, "env": {"n_agents": 3}}
    thesis = layered_settings(recipe="ch5-bearing", steps=600_000, **common)
    assert thesis.recipe.stage_iterations() == (39, 39, 118)  # 600,000 / 3072 = 195.3 -> 196 iterations: 20/20/60 %
    written = yaml.safe_load(yaml.safe_dump(thesis.to_dict()))  # the curriculum's proportions and the budget
    assert written["curriculum"]["iterations"] == [5000, 5000, 15000] and written["training"]["steps"] == 600_000
    assert TrainSettings.from_dict(written).recipe.stage_iterations() == (39, 39, 118)
    assert layered_settings(recipe="ch5-bearing", steps=3072, **common).recipe.stage_iterations() == (0, 0, 1)
    given = layered_settings(recipe="ch5-bearing", iterations=(1, 1, 3), steps=10 * 3072, **common)
    assert given.recipe.stage_iterations() == (2, 2, 6)  # given iterations are proportions too
    resolved = layered_settings(recipe="ch5-bearing", iterations=(39, 39, 118), steps=600_000, **common)
    assert resolved.recipe.stage_iterations() == (39, 39, 118)  # a run's config.yaml resolves to itself on --resume
    fast = layered_settings(recipe="fast-ch5-bearing", steps=600_000, **common)  # stage 3 only: 6144 per iteration
    assert fast.recipe.stage_iterations() == (0, 0, 98)


def test_a_clocked_schedule_follows_whichever_budget_is_further_along(monkeypatch: pytest.MonkeyPatch) -> None:
    now = [100.0]
    monkeypatch.setattr("sb3_formation.sb3.callbacks.time.monotonic", lambda: now[0])
    clock = TrainingClock(budget=60.0, spent=15.0)  # 15 s spent in an earlier session
    clock.start()
    now[0] += 15.0  # 30 s of 60: half the time budget left
    linear = ClockedSchedule(schedule({"start": 3e-4, "end": 1e-5}), clock)
    assert linear(1.0) == pytest.approx(1e-5 + 0.5 * 2.9e-4)  # the clock is further along than the steps
    assert linear(0.25) == pytest.approx(1e-5 + 0.25 * 2.9e-4)  # the steps are further along than the clock
    assert not clock.exhausted
    now[0] += 30.0
    assert clock.exhausted and clock.seconds == pytest.approx(60.0) and linear(1.0) == pytest.approx(1e-5)
    clock.stop()
    now[0] += 100.0  # not counted after stop()
    assert clock.seconds == pytest.approx(60.0)
    plain = pickle.loads(pickle.dumps(linear))  # saved with a model, it is the schedule without the clock
    assert not isinstance(plain, ClockedSchedule) and plain(1.0) == pytest.approx(3e-4)
    with pytest.raises(ValueError, match="time budget must be > 0"):
        TrainingClock(budget=0.0)


def test_a_minutes_budget_replaces_the_setup_budget_and_ends_training(tmp_path: Path) -> None:
    setup = str(tiny_yaml(tmp_path))
    settings = layered_settings(recipe=setup, minutes=0.5)
    assert settings.recipe.stage_iterations() == (0, 0, None) and settings.recipe.training.steps is None
    capped = layered_settings(recipe=setup, minutes=0.5, steps=16 * 12)  # both: whichever runs out first
    assert capped.recipe.stage_iterations() == (0, 0, 1) and capped.recipe.training.steps == 16 * 12
    for bad in (0, -1.0, True, "5", float("inf"), float("nan")):
        with pytest.raises(ValueError, match="minutes must be a finite number > 0"):
            layered_settings(recipe=setup, minutes=bad)
    with pytest.raises(ValueError, match="iterations must be three integers"):
        layered_settings(recipe=setup, iterations=(0, 0, None))  # open-ended only with a time budget
    run = tmp_path / "run"
    # 0.06 s: spent within the first iterations (or, on a loaded machine, before the first), so training ends there
    assert main(["train", "--recipe", setup, "--minutes", "0.001", "--run-dir", str(run), *TINY]) == 0
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["training"]["minutes"] == 0.001 and config["training"]["steps"] is None
    checkpoint = latest_checkpoint(run)
    state = json.loads((checkpoint / "state.json").read_text())
    iterations = state["curriculum"]["iteration"]
    assert state["training_seconds"] >= 0.06  # the open-ended stage 3 ended because the time was up
    assert load_trained(run).model.num_timesteps == iterations * 16 * 2 * 6
    if iterations >= 1:
        with open(run / "tensorboard" / "progress.csv") as stream:
            rates = [float(row["train/learning_rate"]) for row in csv.DictReader(stream) if row["train/learning_rate"]]
        # the steps give no progress (stage 3 is open-ended): only the clock moved the rate down from its start, at
        # most to the floor of 1.5e-5 (reached, up to rounding, once the time is up)
        floor = 1.5e-5 - 1e-12
        assert len(rates) == iterations and all(floor <= rate < 2.9e-4 for rate in rates)
    assert main(["train", "--resume", str(run)]) == 0  # the clock continues: no time left
    assert [path.name for path in (run / "checkpoints").iterdir()] == [checkpoint.name]
    assert load_settings(run).recipe.stage_iterations() == (0, 0, None)
    # the run's settings with a steps budget added: the budget sets the open-ended stage 3
    assert layered_settings(run / "config.yaml", steps=16 * 12).recipe.stage_iterations() == (0, 0, 1)


def test_a_minutes_budget_spreads_a_curriculum_over_the_time(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Stages 1 and 2 end at their shares of the time (as 500 : 500 : 1500 iterations: 20 % and 40 %), not after 500
    iterations each, which the 3 s budget could never reach."""
    assert layered_settings(recipe=str(tiny_yaml(tmp_path)), minutes=1).recipe.stage_time_shares() == (
        0.0,
        0.0,
    )  # stage 3 only
    setup = str(tiny_yaml(tmp_path, curriculum={"iterations": [500, 500, 1500], "success_threshold": None}))
    assert layered_settings(recipe=setup, minutes=1).recipe.stage_time_shares() == (0.2, 0.4)
    assert (
        layered_settings(recipe=setup, minutes=1, steps=16 * 12 * 1200).recipe.stage_time_shares() is None
    )  # iterations count
    # with a budget, iterations given are proportions too
    assert layered_settings(recipe=setup, minutes=1, iterations=(1, 1, 2)).recipe.stage_time_shares() == (0.25, 0.5)
    assert layered_settings(recipe="ch5-bearing").recipe.stage_time_shares() is None
    run = tmp_path / "run"
    assert main(["train", "--recipe", setup, "--minutes", "0.05", "--run-dir", str(run), *TINY]) == 0
    assert "stages 1, 2 end at 20%, 40% of the time, stage 3 until the time is up" in capsys.readouterr().out
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["curriculum"]["iterations"] == [500, 500, 1500] and config["training"]["minutes"] == 0.05
    assert load_settings(run).recipe.stage_time_shares() == (0.2, 0.4)
    state = json.loads((latest_checkpoint(run) / "state.json").read_text())
    assert state["curriculum"]["stage"] == 3 and state["curriculum"]["iteration"] < 500
    accumulator = EventAccumulator(str(run / "tensorboard"))
    accumulator.Reload()
    stages = [event.value for event in accumulator.Scalars("curriculum/stage")]
    assert stages == sorted(stages) and stages[-1] == 3


def test_periodic_evaluation_logs_eval_scalars_and_keeps_the_best_model(tmp_path: Path) -> None:
    run = tmp_path / "run"
    assert main(["train", "--recipe", str(tiny_yaml(tmp_path)), "--run-dir", str(run), *TINY]) == 0
    accumulator = EventAccumulator(str(run / "tensorboard"))
    accumulator.Reload()
    tags = accumulator.Tags()["scalars"]
    for tag in ("eval/success_rate", "eval/angle_error_deg", "eval/collisions_agent", "eval/length"):
        assert tag in tags
    rates = [event.value for event in accumulator.Scalars("eval/success_rate")]
    angles = [event.value for event in accumulator.Scalars("eval/angle_error_deg")]
    assert len(rates) == 3  # after each of the three iterations
    best = json.loads((run / "best_evaluation.json").read_text())
    scores = [(rate, -angle) for rate, angle in zip(rates, angles)]
    assert (best["success_rate"], -best["angle_error_deg"]) == pytest.approx(max(scores), rel=1e-6)
    assert (run / BEST_MODEL).is_file() and (run / "best_normalizer.npz").is_file()
    assert main(["evaluate", str(run / BEST_MODEL), "--episodes", "2", "--n-envs", "2", "--no-progress"]) == 0


@pytest.mark.slow
@pytest.mark.parametrize("name", [name for name in recipe_names() if name.startswith("fast-")])
def test_each_fast_setup_trains_an_iteration_and_records_its_changes(name: str, tmp_path: Path) -> None:
    setup, thesis = load_recipe(name), load_recipe(name.removeprefix("fast-").removesuffix("-shielded"))
    assert setup.config() == thesis.config()  # the task is the thesis's
    assert setup.evaluation == thesis.evaluation  # and so is the evaluation protocol
    run = tmp_path / "run"
    arguments = ["train", "--recipe", name, "--run-dir", str(run), "--steps", "1", "--n-envs", "1", "--no-progress"]
    assert main([*arguments, "--env", "max_steps=40"]) == 0
    config = yaml.safe_load((run / "config.yaml").read_text())
    training = config["training"]
    assert config["curriculum"]["iterations"] == [0, 0, 1] and training["normalize_reward"] and training["eval_every"] == 25
    ppo = config["ppo"]
    assert ppo["learning_rate"] == {"start": 3e-4, "end": 1.5e-5} and (ppo["n_steps"], ppo["gamma"]) == (256, 0.99)
    assert config["policy"]["learn_sigma"] is True and config["policy"]["net_arch"]["pi"] == [256, 256]
    assert (run / FINAL_MODEL).is_file() and (run / "final_reward_normalizer.npz").is_file()
    assert (run / BEST_MODEL).is_file()  # the last iteration is evaluated too
