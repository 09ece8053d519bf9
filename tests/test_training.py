"""Training runs end to end: thesis PPO settings, the train CLI, run folders, TensorBoard, checkpoints and resuming."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import numpy as np
import pytest
import torch
import yaml
from logged_names import EPISODE_SCALARS
from PIL import Image
from stable_baselines3.common.save_util import load_from_zip_file
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard_events import read_hparams

from sb3_formation.cli import build_parser, main
from sb3_formation.cli.train import settings_of as train_settings
from sb3_formation.controllers import ShrinkingController
from sb3_formation.controllers.residual import ResidualPolicy
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.recipes import TrainSettings, layered_settings, load_recipe, thesis_recipe_for
from sb3_formation.experiment.runs import FINAL_MODEL, STATE_FILE, latest_checkpoint, load_trained
from sb3_formation.experiment.targets import load_policy
from sb3_formation.experiment.training import make_training_env
from sb3_formation.runtime import OnnxPolicy, load_onnx_policy
from sb3_formation.safety import SafetyGains
from sb3_formation.safety.policy import SafePolicy
from sb3_formation.sb3.model_files import read_model_data
from sb3_formation.sb3.onnx_export import export_onnx
from sb3_formation.sb3.policies import FormationPolicy
from sb3_formation.sb3.recurrent import RecurrentFormationPolicy, RecurrentFormationPPO
from sb3_formation.utils.files import folder_lock

#: Tiny runs: one team, episodes of 20 steps, so every iteration of 128 steps ends several team-episodes.
QUICK = ["--n-envs", "1", "--env", "max_steps=20", "--no-progress"]
SCALARS = [*EPISODE_SCALARS, "curriculum/stage"]


def run_cli(*arguments: str, cwd: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "sb3_formation.cli", *arguments],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def only_run_dir(logdir: Path) -> Path:
    runs = [path for path in logdir.iterdir() if path.is_dir()]
    assert len(runs) == 1, runs
    return runs[0]


def test_thesis_recipes_give_the_thesis_ppo_settings() -> None:
    kwargs = layered_settings(recipe="ch5-bearing", recurrent=False).recipe.ppo_kwargs()
    assert kwargs["policy"] is FormationPolicy
    expected = {"n_steps": 128, "batch_size": 512, "n_epochs": 10, "learning_rate": 5e-5, "gamma": 0.995}
    expected.update({"gae_lambda": 0.95, "clip_range": 0.2, "clip_range_vf": 20.0, "target_kl": 0.03})
    assert {name: kwargs[name] for name in expected} == expected
    assert kwargs["policy_kwargs"] == {"sigma": 0.7, "action_scale": 1.0}
    assert load_recipe("ch4-individual").ppo_kwargs()["policy_kwargs"]["action_scale"] == 0.01  # thesis 4.1.2
    assert load_recipe("ch4-team").ppo_kwargs()["policy_kwargs"]["team_size"] == 3
    five = layered_settings(recipe="ch4-team", agents=5).recipe
    assert five.ppo_kwargs()["policy_kwargs"]["team_size"] == 5


def test_reward_and_agents_flags_map_to_recipes() -> None:
    assert thesis_recipe_for("bearing", 6, False) == "ch5-bearing"
    assert thesis_recipe_for("angle", None, False) == "ch4-individual"
    assert thesis_recipe_for("angle", 3, True) == "ch4-team"
    assert thesis_recipe_for("angle", 6, False) == "ch5-angle"
    settings = train_settings(build_parser().parse_args(["train", "--reward", "bearing", "--agents", "6"]))
    assert settings.recipe.name == "ch5-bearing" and settings.recipe.config().n_agents == 6
    assert settings.recipe.stage_iterations() == (5000, 5000, 15000) and settings.recipe.n_envs == 14


def test_the_scenes_flag_sets_the_tasks_scenes() -> None:
    """``train --scenes passage`` trains on the passage family; the recipe's file says so in its env section."""
    settings = train_settings(build_parser().parse_args(["train", "--recipe", "fast-ch5-bearing", "--scenes", "passage"]))
    assert settings.recipe.config().scenes == "passage"
    assert settings.to_dict()["env"]["scenes"] == "passage"
    assert train_settings(build_parser().parse_args(["train", "--recipe", "fast-ch5-bearing"])).recipe.config().scenes == (
        "curriculum"
    )


def test_a_recipe_file_is_changed_by_options_and_unknown_keys_fail(tmp_path: Path) -> None:
    config_file = tmp_path / "run.yaml"
    values = {"base": "ch4-team", "curriculum": {"iterations": [3, 2, 1]}, "env": {"max_steps": 99}, "run": {"seed": 4}}
    config_file.write_text(yaml.safe_dump(values))
    arguments = ["train", "--recipe", str(config_file), "--seed", "7", "--env", "eta_g=0.7"]
    settings = train_settings(build_parser().parse_args(arguments))
    assert (settings.recipe.name, settings.run.seed, settings.recipe.stage_iterations()) == ("run", 7, (3, 2, 1))
    assert settings.recipe.config().max_steps == 99 and settings.recipe.config().eta_g == 0.7
    assert settings.recipe.config().team_reward is True  # the base's task, ch4-team
    config_file.write_text(yaml.safe_dump({"base": "ch4-team", "learning_rate": 1e-3}))
    with pytest.raises(ValueError, match=r"unknown keys \['learning_rate'\]"):
        train_settings(build_parser().parse_args(["train", "--recipe", str(config_file)]))
    config_file.write_text(yaml.safe_dump({"base": "ch4-team", "run": {"sed": 3}}))
    with pytest.raises(ValueError, match=r"run may give seed, seeds, .*: unknown keys \['sed'\]"):
        train_settings(build_parser().parse_args(["train", "--recipe", str(config_file)]))
    with pytest.raises(ValueError, match=r"ppo may give .*: unknown keys \['learning_rat'\]"):
        layered_settings(ppo={"learning_rat": 1e-3})
    with pytest.raises(ValueError, match="unknown FormationConfig field"):
        layered_settings(env={"n_agent": 3})
    with pytest.raises(ValueError, match=r"unknown recipe option\(s\) \['colour'\]"):
        layered_settings(colour="red")


def test_a_runs_config_is_a_complete_recipe_that_other_options_change() -> None:
    resolved = layered_settings(recipe="ch4-individual", env={"max_steps": 50}, seed=3)
    values = yaml.safe_load(yaml.safe_dump(resolved.to_dict()))
    assert values["run"]["seed"] == 3 and "seed" not in values  # run options apart from the recipe
    # every field, not only the changes (ideal disturbances are not written: FormationConfig.to_dict)
    assert set(values["env"]) == {"task", *FormationConfig.field_names()} - {"disturbances"}
    again = TrainSettings.from_dict(values)
    assert again.recipe.to_dict() == resolved.recipe.to_dict() and again.run == resolved.run
    # policy keyword arguments merge into the recipe's, not replacing them (the team critic keeps its team)
    team = layered_settings(recipe="ch4-team").recipe.with_changes({"policy": {"net_arch": {"pi": [8], "vf": [8, 8]}}})
    assert team.ppo_kwargs()["policy_kwargs"]["team_size"] == 3 and team.ppo_kwargs()["policy_kwargs"]["sigma"] == 0.7


def test_recurrent_policy_follows_the_thesis_chapter_unless_told() -> None:
    assert load_recipe("ch5-bearing").recurrent is True  # thesis 5.1.2: recurrent networks
    assert load_recipe("ch5-angle").ppo_kwargs()["policy"] is RecurrentFormationPolicy
    assert load_recipe("ch4-individual").ppo_kwargs()["policy"] is FormationPolicy
    assert layered_settings(recipe="ch5-bearing", recurrent=False).recipe.ppo_kwargs()["policy"] is FormationPolicy
    lstm = layered_settings(recipe="ch4-individual", recurrent=True, cell="lstm").recipe.ppo_kwargs()
    assert lstm["policy"] is RecurrentFormationPolicy and lstm["policy_kwargs"]["cell"] == "lstm"
    assert lstm["policy_kwargs"]["action_scale"] == 0.01
    with pytest.raises(ValueError, match="team critic"):
        layered_settings(recipe="ch4-team", recurrent=True)
    with pytest.raises(ValueError, match="cell"):
        layered_settings(cell="rnn")
    assert load_recipe("ch5-bearing").to_dict()["policy"]["recurrent"] is True
    parser = build_parser()
    assert train_settings(parser.parse_args(["train", "--no-recurrent"])).recipe.recurrent is False
    chosen = train_settings(parser.parse_args(["train", "--recipe", "ch4-team", "--no-recurrent"]))
    assert chosen.recipe.recurrent is False and chosen.recipe.ppo_kwargs()["policy"] is FormationPolicy
    with pytest.raises(ValueError, match="cell 'lstm' applies to recurrent policies only"):
        train_settings(parser.parse_args(["train", "--recipe", "ch5-bearing", "--no-recurrent", "--cell", "lstm"]))
    assert "cell" not in load_recipe("ch4-team").to_dict()["policy"]
    assert layered_settings(recipe="ch5-angle", cell="lstm").recipe.to_dict()["policy"]["cell"] == "lstm"


def test_training_env_is_placed_for_the_curriculum_stage() -> None:
    env = make_training_env(layered_settings(n_envs=2, env={"max_steps": 20}), stage=3)
    env.seed(0)
    env.reset()
    assert env.get_attr("stage") == [3] * 12
    for scenario in env.get_attr("scenario", indices=[0, 6]):
        assert scenario.obstacles[:, 2].tolist() == [0.8, 0.8]  # ch5 stage 3, not stage 1's 2 m obstacles
    env.close()


def test_train_cli_bad_input_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["train", "--recipe", str(tmp_path / "missing.yaml")]) == 2
    assert "missing.yaml" in capsys.readouterr().err
    assert main(["train", "--resume", str(tmp_path)]) == 2
    assert "config.yaml" in capsys.readouterr().err
    assert main(["train", "--resume", str(tmp_path), "--seed", "3"]) == 2
    assert "--seed" in capsys.readouterr().err
    assert main(["train", "--resume", str(tmp_path), "--no-evaluate"]) == 2  # the flag as the user wrote it
    assert "drop --no-evaluate" in capsys.readouterr().err
    assert main(["train", "--trust-pickle", "--logdir", str(tmp_path / "runs")]) == 2
    assert "--trust-pickle applies to --resume" in capsys.readouterr().err
    undecodable = os.fsdecode(b"run-\xff")  # a name the shell passed as bytes: refused before anything is written
    with pytest.raises(SystemExit) as exit_info:  # as the arguments are read
        main(["train", "--run-dir", str(tmp_path / undecodable), "--logdir", str(tmp_path / "runs")])
    assert (
        exit_info.value.code == 2 and "is not valid UTF-8" in capsys.readouterr().err and not (tmp_path / undecodable).exists()
    )
    broken = tmp_path / "broken.yaml"
    broken.write_text("base: [unclosed")
    assert main(["train", "--recipe", str(broken)]) == 2
    assert "broken.yaml is not valid YAML" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["train", "--iterations", "1,2"])
    with pytest.raises(SystemExit):
        main(["train", "--minutes", "soon", "--logdir", str(tmp_path / "runs")])
    assert "argument --minutes: invalid float value: 'soon'" in capsys.readouterr().err
    for minutes in ("0", "inf"):  # numbers, refused by the field they set
        assert main(["train", "--minutes", minutes, "--logdir", str(tmp_path / "runs")]) == 2
        assert f"training: minutes must be a finite number > 0 or null, got {float(minutes)}" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()  # nothing written


#: Bad settings of ``train`` (flags, or a recipe file's text), each with the words its
#: one-line error must hold. None of them may leave a folder behind.
BAD_TRAIN_INPUT = [
    (["--workers", "5", "--n-envs", "2"], None, "workers=5 exceeds n_envs=2"),
    (["--seed", "99999999999"], None, "run: seed must be an integer in [0, 2**32 - 1], got 99999999999"),
    (["--device", "tpu9"], None, "device must be auto, cpu, cuda or cuda:<index>, got 'tpu9'"),
    (["--success-threshold", "-3"], None, "success_threshold must be a number in [0, 1]"),
    (["--iterations", "-1,2,3"], None, "curriculum: iterations must be three integers >= 0, not all 0, got (-1, 2, 3)"),
    (["--iterations", "1,2"], None, "argument --iterations: expected 3 comma-separated integers, got '1,2'"),
    (["--env", "v_max=[1,"], None, "argument --env: the value of v_max is not valid YAML"),
    (["--env", "v_max=true"], None, "FormationConfig.v_max=True is invalid: it must be a finite number > 0"),
    ([], "base: ch5-bearing\nrun: {seed: -5}", "seed must be an integer in [0, 2**32 - 1], got -5"),
    (
        [],
        "base: ch5-bearing\nrun: {seeds: [1, 4294967296]}",
        "each of seeds must be an integer in [0, 2**32 - 1], got 4294967296",
    ),
    ([], "base: ch5-bearing\nppo: {policy_kwargs: {sigma: 1}}", "policy keyword arguments go under policy:"),
    ([], "base: ch5-bearing\nppo: 7", "ppo must be a mapping, got 7"),
    ([], "base: ch5-bearing\nenv: 5", "env must be a mapping, got 5"),
    ([], "base: ch5-bearing\ncurriculum: {iterations: 5}", "iterations must be three integers >= 0, not all 0, got 5"),
    ([], "base: ch5-bearing\ncurriculum: {iterations: [0, 0, 0]}", "iterations must be three integers >= 0, not all 0"),
    ([], "base: 5", "recipe must be a recipe name or the path of a recipe YAML file, got 5"),
    ([], "base: ch5-bearing\ncurriculum: {success_threshold: true}", "success_threshold must be a number in [0, 1]"),
    ([], "base: ch5-bearing\nppo: {n_epochs: 0}", "ppo: n_epochs must be an integer >= 1, got 0"),
    ([], "base: bad.yaml", "base 'bad.yaml' makes a cycle of recipes"),
    (["--env", "world_width=1e308"], None, "FormationConfig.world_width=1e+308 is invalid: it must be at most 10000 m"),
    (["--env", "v_max=1.0e6"], None, "need 37,500,000 Pymunk sub-steps per step"),
    ([], "base: ch5-bearing\nppo: {gamma: 2}", "gamma must be a number in (0, 1], got 2"),
    ([], "base: ch5-bearing\nppo: {batch_size: 1}", "batch_size must be an integer >= 2"),
    ([], "base: ch5-bearing\nppo: {n_steps: 0}", "n_steps must be an integer >= 1, got 0"),
]


@pytest.mark.parametrize(("flags", "yaml_text", "message"), BAD_TRAIN_INPUT)
def test_bad_train_settings_are_one_line_errors_before_anything_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flags: list[str], yaml_text: str | None, message: str
) -> None:
    arguments = ["train", "--logdir", str(tmp_path / "runs"), *flags]
    if yaml_text is not None:
        (tmp_path / "bad.yaml").write_text(yaml_text + "\n")
        arguments += ["--recipe", str(tmp_path / "bad.yaml")]
    try:
        code = main(arguments)
    except SystemExit as error:  # argparse's own errors
        code = error.code
    assert code == 2
    error = capsys.readouterr().err
    assert message in error and "Traceback" not in error
    assert not (tmp_path / "runs").exists()


def test_numbers_are_read_as_users_write_them() -> None:
    """PyYAML reads ``3e-4`` as a string; recipe files and ``--env`` read it as a number."""
    settings = train_settings(build_parser().parse_args(["train", "--env", "v_max=5e-2", "--env", "dt=1E-1"]))
    assert settings.recipe.config().v_max == 0.05 and settings.recipe.config().dt == 0.1
    assert layered_settings(None, ppo={"learning_rate": 3e-4}).recipe.ppo_kwargs()["learning_rate"] == 3e-4


def test_damaged_files_of_a_run_are_one_line_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An empty normaliser (for ``evaluate``, and a checkpoint's for ``--resume``) and a damaged
    ``config.yaml`` are named in one line; nothing saved is touched."""
    run_dir = tmp_path / "run"
    arguments = ["train", "--recipe", "ch4-individual", "--iterations", "1,1,0", "--n-envs", "2", "--no-progress"]
    assert main([*arguments, "--env", "max_steps=20", "--run-dir", str(run_dir)]) == 0
    capsys.readouterr()
    (run_dir / "final_normalizer.npz").write_bytes(b"")
    assert main(["evaluate", str(run_dir), "--episodes", "1", "--no-progress"]) == 2
    assert f"{run_dir / 'final_normalizer.npz'} is not a normaliser file (empty or damaged" in capsys.readouterr().err
    for name in (FINAL_MODEL, "final_normalizer.npz"):
        (run_dir / name).unlink()
    checkpoint = latest_checkpoint(run_dir)
    (checkpoint / "normalizer.npz").write_bytes(b"")
    assert main(["train", "--resume", str(run_dir)]) == 2
    assert f"{checkpoint / 'normalizer.npz'} is not a ScaleNormalizeVecEnv file (empty or" in capsys.readouterr().err
    for text, message in [("recipe: [oops", "config.yaml is not valid YAML"), ("- 1", "must hold a recipe mapping")]:
        (run_dir / "config.yaml").write_text(text)
        assert main(["train", "--resume", str(run_dir)]) == 2
        error = capsys.readouterr().err
        assert message in error and len(error.strip().splitlines()) == 1
    assert not (run_dir / FINAL_MODEL).exists() and (checkpoint / "model.zip").stat().st_size > 0


@pytest.mark.slow
def test_train_run_folder_and_tensorboard(tmp_path: Path) -> None:
    arguments = ["train", "--recipe", "ch5-bearing", "--iterations", "1,1,1", "--checkpoint-every", "1", "--logdir", "runs"]
    process = run_cli(*arguments, *QUICK, cwd=tmp_path)
    _, stderr = process.communicate(timeout=300)
    assert process.returncode == 0, stderr
    run_dir = only_run_dir(tmp_path / "runs")
    assert run_dir.name.startswith("ch5-bearing_6a_s0_")
    for name in ("config.yaml", "command.txt", "final_model.zip", "final_normalizer.npz"):
        assert (run_dir / name).is_file(), name
    assert (run_dir / "command.txt").read_text().startswith("sb3-formation train --recipe ch5-bearing --iterations 1,1,1 ")
    assert yaml.safe_load((run_dir / "config.yaml").read_text())["env"]["max_steps"] == 20
    state = json.loads((latest_checkpoint(run_dir) / STATE_FILE).read_text())
    assert state["num_timesteps"] == 3 * 128 * 6 and state["curriculum"]["stage"] == 3
    # a checkpoint holds the model after its iteration's update (SB3 counts one update per epoch)
    assert sorted(path.name for path in (run_dir / "checkpoints").iterdir()) == [f"iteration_00000{k}" for k in (1, 2, 3)]
    updates = [
        load_from_zip_file(run_dir / "checkpoints" / f"iteration_00000{k}" / "model.zip")[0]["_n_updates"] for k in (1, 2, 3)
    ]
    assert 1 <= updates[0] < updates[1] < updates[2]
    events = EventAccumulator(str(run_dir / "tensorboard"))
    events.Reload()
    scalars = set(events.Tags()["scalars"])
    assert set(SCALARS) <= scalars, set(SCALARS) - scalars
    assert [event.value for event in events.Scalars("curriculum/stage")] == [1.0, 2.0, 3.0]  # stage of each iteration
    assert all(event.value == 20.0 for event in events.Scalars("episode/length"))  # no success in 20 steps
    hparams = read_hparams(run_dir / "tensorboard")
    assert "episode/success_rate" in hparams["metrics"] and hparams["hparams"]["name"] == "ch5-bearing"
    assert hparams["hparams"]["env/n_agents"] == 6 and hparams["hparams"]["curriculum/iterations"] == "[1, 1, 1]"
    assert hparams["hparams"]["run/seed"] == 0


@pytest.mark.slow
def test_team_critic_run_trains_and_evaluates(tmp_path: Path) -> None:
    process = run_cli(
        "train", "--reward", "angle", "--team-reward", "--iterations", "1,0,1", "--logdir", "runs", *QUICK, cwd=tmp_path
    )
    _, stderr = process.communicate(timeout=300)
    assert process.returncode == 0, stderr
    run_dir = only_run_dir(tmp_path / "runs")
    assert run_dir.name.startswith("ch4-team_3a_")
    out = tmp_path / "evaluation"
    assert main(["evaluate", str(run_dir), "--episodes", "3", "--n-envs", "2", "--out", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["episodes"] == 3 and summary["stage"] == 3


def read_lines_until(stream: IO[str] | None, predicate: Callable[[str], bool], timeout: float = 240.0) -> bool:
    """Read ``stream`` (in a thread) until a line fulfils ``predicate``: whether one did within ``timeout`` s (a hang
    guard) before the stream ended. The rest of the stream is left to ``communicate``."""
    assert stream is not None
    ended, found = threading.Event(), []

    def read() -> None:
        for line in iter(stream.readline, ""):
            if predicate(line):
                found.append(line)
                break
        ended.set()

    threading.Thread(target=read, daemon=True).start()
    ended.wait(timeout)
    return bool(found)


def wait_for(predicate, timeout: float = 240.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.2)


@pytest.mark.slow
def test_killed_recurrent_run_resumes_evaluates_and_renders(tmp_path: Path) -> None:
    """`train --reward bearing --agents 6` trains the recurrent policy (chapter 5) through checkpoints, a SIGKILL and a
    resume with the same stage, timesteps and statistics; the result is evaluated and rendered."""
    arguments = ["train", "--reward", "bearing", "--agents", "6", "--iterations", "2,2,4", "--checkpoint-every", "1"]
    arguments += ["--logdir", "runs", *QUICK]
    process = run_cli(*arguments, cwd=tmp_path)
    wait_for(lambda: (tmp_path / "runs").exists() and any((tmp_path / "runs").iterdir()))
    run_dir = only_run_dir(tmp_path / "runs")
    wait_for(lambda: latest_checkpoint(run_dir) is not None and latest_checkpoint(run_dir).name >= "iteration_000003")
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=30)
    killed_at = json.loads((latest_checkpoint(run_dir) / STATE_FILE).read_text())
    assert not (run_dir / "final_model.zip").exists()
    resumed = run_cli("train", "--resume", str(run_dir), cwd=tmp_path)
    _, stderr = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, stderr
    final = json.loads((latest_checkpoint(run_dir) / STATE_FILE).read_text())
    slots, steps_per_iteration = 6, 128 * 6
    assert final["curriculum"]["iteration"] == 8 and final["curriculum"]["stage"] == 3
    # a restart from scratch would add 8 iterations to what the killed run had done; a resume adds the rest
    assert final["num_timesteps"] == 8 * steps_per_iteration
    assert (
        killed_at["curriculum"]["iteration"] >= 3
        and killed_at["num_timesteps"] == killed_at["curriculum"]["iteration"] * steps_per_iteration
    )
    # normaliser statistics continue: two resets of every slot (start, resume) plus one row per slot and step
    with np.load(run_dir / "final_normalizer.npz") as statistics:
        assert float(statistics["count"]) == slots * (2 + 8 * 128)
    assert yaml.safe_load((run_dir / "config.yaml").read_text())["policy"]["recurrent"] is True
    trained = load_trained(run_dir, device="cpu")
    assert isinstance(trained.model, RecurrentFormationPPO) and trained.model.policy.cell == "gru"
    assert main(["evaluate", str(run_dir), "--episodes", "2", "--n-envs", "2", "--no-progress"]) == 0
    assert json.loads((run_dir / "eval" / "summary.json").read_text())["episodes"] == 2
    assert main(["render", str(run_dir), "--max-steps", "4", "--out", str(tmp_path / "episode.gif")]) == 0
    assert Image.open(tmp_path / "episode.gif").n_frames == 5


def train_shrunk_through_a_kill(tmp_path: Path, recipe: str, max_steps: int, policy: dict[str, Any] | None = None) -> Path:
    """Train ``recipe`` shrunk (small nets, short rollouts, one team, episodes of ``max_steps``; ``policy`` replaces the
    policy section's small MLP) for 8 iterations into ``tmp_path/run``, SIGKILL it after its third checkpoint, resume
    it, and check that it finished with the budget's timesteps; return the run folder."""
    setup = tmp_path / "shrunk.yaml"
    setup.write_text(
        yaml.safe_dump(
            {
                "base": recipe,
                "policy": policy or {"net_arch": {"pi": [16], "vf": [16]}},
                "ppo": {"n_steps": 32, "batch_size": 96, "n_epochs": 1},
                "n_envs": 1,
                "training": {"steps": 8 * 32 * 6, "eval_every": None},
            }
        )
    )
    arguments = ["train", "--recipe", str(setup), "--env", f"max_steps={max_steps}", "--checkpoint-every", "1"]
    process = run_cli(*arguments, "--no-progress", "--no-evaluate", "--run-dir", "run", cwd=tmp_path)
    run_dir = tmp_path / "run"
    wait_for(lambda: latest_checkpoint(run_dir) is not None and latest_checkpoint(run_dir).name >= "iteration_000003")
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=30)
    killed_at = json.loads((latest_checkpoint(run_dir) / STATE_FILE).read_text())
    assert not (run_dir / FINAL_MODEL).exists() and 3 <= killed_at["curriculum"]["iteration"] < 8
    resumed = run_cli("train", "--resume", str(run_dir), cwd=tmp_path)
    _, stderr = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, stderr
    final = json.loads((latest_checkpoint(run_dir) / STATE_FILE).read_text())
    assert final["curriculum"]["iteration"] == 8 and final["num_timesteps"] == 8 * 32 * 6
    return run_dir


@pytest.mark.slow
def test_the_scene_recipe_trains_through_a_kill_and_resumes(tmp_path: Path) -> None:
    """residual-scenes-ch5-bearing (shrunk: small nets, short rollouts, one team, episodes of 60 steps) trains its one
    stage, PPO on the correction of controller:shrinking in the scene families with the geodesic goal term, through a
    SIGKILL after a checkpoint, and a resume finishes it with the budget's timesteps; it loads as that residual policy."""
    run_dir = train_shrunk_through_a_kill(tmp_path, "residual-scenes-ch5-bearing", max_steps=60)
    policy = load_policy(run_dir)
    assert isinstance(policy, ResidualPolicy) and isinstance(policy.base, ShrinkingController)
    assert policy.config.scenes == "mixed" and policy.config.goal_progress == "geodesic"
    # decentralised: each agent's action and memory come from its own rows; other agents' rows replaced by noise, and
    # the map (only the training reward reads it) changes nothing
    env = FormationEnv(policy.config.replace(scenes="corridor"))
    rows = np.stack(list(env.reset(seed=5)[0].values()))
    state, rng = None, np.random.default_rng(0)
    for _ in range(60):
        actions, next_state = policy.predict(rows, state)
        others = rows.copy()
        others[1:] = rng.normal(0.0, 1.0, others[1:].shape)
        alone, alone_state = policy.predict(others, state)
        np.testing.assert_array_equal(alone[0], actions[0])
        np.testing.assert_array_equal(alone_state[1][0], next_state[1][0])
        rows, state = env.step_array(actions)[0], next_state


@pytest.mark.slow
def test_a_policy_with_memory_and_messages_trains_through_a_kill_and_resumes(tmp_path: Path) -> None:
    """The thesis's recurrent ch5-bearing recipe (shrunk) with messages of 4 values trains through a SIGKILL and a
    resume; the run loads as that policy and plays episodes."""
    arch = {"pi": [16], "pi_recurrent": 8, "vf": [16], "vf_recurrent": 8, "vf_after": []}
    run_dir = train_shrunk_through_a_kill(tmp_path, "ch5-bearing", 40, {"net_arch": arch, "message_size": 4})
    trained = load_trained(run_dir, device="cpu")
    assert isinstance(trained.model, RecurrentFormationPPO)
    assert trained.policy.message_size == 4 and trained.policy.memory and trained.policy.cell == "gru"
    summary = evaluate(trained, episodes=2, n_envs=2, record=0, env_overrides={"max_steps": 40})
    assert [row["length"] for row in summary.episodes] == [40, 40]


@pytest.mark.slow
def test_the_shielded_recipe_trains_through_a_kill_resumes_and_exports_its_filter(tmp_path: Path) -> None:
    """fast-ch5-bearing-shielded (shrunk) trains behind the safety filter through a SIGKILL and a resume; TensorBoard
    has the filter's metrics; the run loads behind its filter, and its exported ONNX runtime filters like it (1e-6)."""
    run_dir = train_shrunk_through_a_kill(tmp_path, "fast-ch5-bearing-shielded", max_steps=40)
    events = EventAccumulator(str(run_dir / "tensorboard"))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"safety/changed_fraction", "safety/change_mean", "safety/infeasible_steps", "safety/min_separation"} <= tags
    policy = load_policy(run_dir)
    assert isinstance(policy, SafePolicy) and policy.filter.gains == SafetyGains()
    runtime = load_onnx_policy(export_onnx(policy, tmp_path / "shielded.onnx"), threads=1)
    assert isinstance(runtime, SafePolicy) and runtime.filter.gains == SafetyGains()
    env = FormationEnv(policy.config.replace(scenes="clutter"))
    rows = np.stack(list(env.reset(seed=2)[0].values()))
    layout = env.observation_layout
    rows[:, layout["lidar_obstacles"]] = np.minimum(rows[:, layout["lidar_obstacles"]], 0.005)  # walls 7.5 mm away all round
    filtered, _ = policy.predict(rows)
    exported, _ = runtime.predict(rows)
    unfiltered, _ = policy.policy.predict(rows)
    np.testing.assert_allclose(exported, filtered, rtol=0, atol=1e-6)
    assert np.abs(filtered - unfiltered).max() > 0.01  # the filter acted
    # behind safe: it is filtered once, with its own gains
    assert SafePolicy(runtime).filter.gains == SafetyGains() and isinstance(SafePolicy(runtime).policy, OnnxPolicy)


@pytest.mark.slow
def test_sigterm_checkpoints_and_stops(tmp_path: Path) -> None:
    process = run_cli(
        "train", "--iterations", "1,1,200", "--checkpoint-every", "100", "--logdir", "runs", *QUICK, cwd=tmp_path
    )
    wait_for(lambda: (tmp_path / "runs").exists() and any((tmp_path / "runs").iterdir()))
    run_dir = only_run_dir(tmp_path / "runs")
    wait_for(
        lambda: (
            (run_dir / "tensorboard" / "progress.csv").exists()
            and len((run_dir / "tensorboard" / "progress.csv").read_text().splitlines()) >= 4
        )
    )  # three rollouts logged: two iterations complete (a stop during the third's update drops it)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM == 143  # the conventional code of a SIGTERM-ended command
    assert f"sb3-formation: stopped by SIGTERM; checkpoint runs/{run_dir.name}/checkpoints/iteration_" in stderr
    checkpoint = latest_checkpoint(run_dir)
    state = json.loads((checkpoint / STATE_FILE).read_text())
    assert 2 <= state["curriculum"]["iteration"] < 202 and state["curriculum"]["stage"] == 3
    assert not (run_dir / "final_model.zip").exists()
    assert not [path for path in (run_dir / "checkpoints").iterdir() if path.name.startswith(".")]  # no half-written folder
    assert os.path.getsize(checkpoint / "model.zip") > 0


@pytest.mark.slow
def test_ctrl_c_with_workers_checkpoints_and_stops(tmp_path: Path) -> None:
    """Ctrl-C reaches the whole process group; the workers ignore it and the parent stops cleanly."""
    arguments = ["train", "--iterations", "1,1,200", "--checkpoint-every", "100", "--workers", "2", "--n-envs", "2"]
    process = subprocess.Popen(
        [sys.executable, "-m", "sb3_formation.cli", *arguments, "--logdir", "runs", "--env", "max_steps=20", "--no-progress"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    wait_for(lambda: (tmp_path / "runs").exists() and any((tmp_path / "runs").iterdir()))
    run_dir = only_run_dir(tmp_path / "runs")
    progress = run_dir / "tensorboard" / "progress.csv"
    wait_for(lambda: progress.exists() and len(progress.read_text().splitlines()) >= 4)  # two iterations complete
    os.killpg(process.pid, signal.SIGINT)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGINT == 130, stderr
    assert "Traceback" not in stderr and f"continue with --resume runs/{run_dir.name}" in stderr
    state = json.loads((latest_checkpoint(run_dir) / STATE_FILE).read_text())
    assert state["curriculum"]["iteration"] >= 2
    assert state["num_timesteps"] == state["curriculum"]["iteration"] * 128 * 12  # the interrupted rollout is dropped


def test_resuming_a_finished_run_says_so_and_rewrites_a_lost_final_model(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """With no iterations left the run is finished; a final model lost in a kill while it was
    written comes back from the last checkpoint."""
    run_dir = tmp_path / "run"
    arguments = ["train", "--recipe", "ch4-individual", "--iterations", "1,1,0", "--n-envs", "2", "--no-progress"]
    assert main([*arguments, "--env", "max_steps=20", "--run-dir", str(run_dir)]) == 0
    model = (run_dir / FINAL_MODEL).read_bytes()
    capsys.readouterr()
    assert main(["train", "--resume", str(run_dir)]) == 0
    assert f"{run_dir} is finished (2 iterations, final_model.zip written): nothing to resume" in capsys.readouterr().out
    assert (run_dir / FINAL_MODEL).read_bytes() == model
    # a new run into the same folder is refused before anything is written
    files = {path: path.read_bytes() for path in run_dir.rglob("*") if path.is_file()}
    again = ["train", "--recipe", "ch5-bearing", "--iterations", "0,0,1", "--n-envs", "1", "--run-dir", str(run_dir)]
    assert main(again) == 2
    message = f"{run_dir} is not empty (a run is there already): continue it with --resume {run_dir}"
    assert message in capsys.readouterr().err
    assert {path: path.read_bytes() for path in run_dir.rglob("*") if path.is_file()} == files
    # ... and a run folder another process trains in is locked: neither a resume nor a new run may enter it
    empty = tmp_path / "empty"
    with folder_lock(run_dir, "run folder"), folder_lock(empty, "run folder"):
        assert main(["train", "--resume", str(run_dir)]) == 2
        assert f"run folder {run_dir} is in use by another process (pid {os.getpid()})" in capsys.readouterr().err
        assert main([*again[:-1], str(empty)]) == 2
        assert f"run folder {empty} is in use by another process (pid {os.getpid()})" in capsys.readouterr().err
    assert {path: path.read_bytes() for path in run_dir.rglob("*") if path.is_file()} == files
    assert [path.name for path in empty.iterdir()] == [".lock"]
    (run_dir / FINAL_MODEL).unlink()
    (run_dir / "final_normalizer.npz").unlink()
    assert main(["train", "--resume", str(run_dir)]) == 0
    (tmp_path / "before.zip").write_bytes(model)
    before = load_from_zip_file(tmp_path / "before.zip")[1]["policy"]
    after = load_from_zip_file(run_dir / FINAL_MODEL)[1]["policy"]
    assert sorted(before) == sorted(after) and all((before[name] == after[name]).all() for name in before)
    assert load_trained(run_dir, device="cpu").config.n_agents == 3


def test_resume_recovers_a_checkpoint_caught_in_a_folder_swap_and_leaves_it_alone(tmp_path: Path) -> None:
    """A kill between the two renames of a checkpoint's swap leaves it only in a hidden folder;
    resuming puts it back, and does not rewrite the checkpoint it starts from (which reopened that window)."""
    run_dir = tmp_path / "run"
    arguments = ["train", "--recipe", "ch4-individual", "--iterations", "1,1,1", "--n-envs", "2", "--no-progress"]
    assert main([*arguments, "--checkpoint-every", "1", "--env", "max_steps=20", "--run-dir", str(run_dir)]) == 0
    checkpoints = run_dir / "checkpoints"
    aside = checkpoints / ".iteration_000002.old.k1ll"  # what atomic_directory leaves between its renames
    aside.mkdir()
    (checkpoints / "iteration_000002").rename(aside / "iteration_000002")
    shutil.rmtree(checkpoints / "iteration_000003")
    for name in (FINAL_MODEL, "final_normalizer.npz"):
        (run_dir / name).unlink()
    assert latest_checkpoint(run_dir) == checkpoints / "iteration_000002"
    assert sorted(path.name for path in checkpoints.iterdir()) == ["iteration_000001", "iteration_000002"]
    loaded = (checkpoints / "iteration_000002" / "model.zip").stat()
    assert main(["train", "--resume", str(run_dir)]) == 0
    again = (checkpoints / "iteration_000002" / "model.zip").stat()
    assert (again.st_ino, again.st_mtime_ns) == (loaded.st_ino, loaded.st_mtime_ns)
    assert (run_dir / FINAL_MODEL).is_file() and latest_checkpoint(run_dir).name == "iteration_000003"
    # determinism: resuming the same checkpoint again gives the same model, bit for bit
    first = load_from_zip_file(run_dir / FINAL_MODEL)[1]["policy"]
    shutil.rmtree(checkpoints / "iteration_000003")
    for name in (FINAL_MODEL, "final_normalizer.npz"):
        (run_dir / name).unlink()
    assert main(["train", "--resume", str(run_dir)]) == 0
    second = load_from_zip_file(run_dir / FINAL_MODEL)[1]["policy"]
    assert sorted(first) == sorted(second) and all(first[name].equal(second[name]) for name in first)


def test_resume_refuses_a_config_whose_recipe_was_edited_since_the_checkpoint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Edits of ``env:`` (as of ``ppo:`` and ``policy:``) in a run's ``config.yaml`` are named and nothing is touched."""
    run_dir = tmp_path / "run"
    arguments = ["train", "--recipe", "ch4-individual", "--iterations", "1,1,0", "--n-envs", "2", "--no-progress"]
    assert main([*arguments, "--env", "max_steps=20", "--run-dir", str(run_dir)]) == 0
    (run_dir / FINAL_MODEL).unlink()  # a run killed while its final model was written: there is work to resume
    original = (run_dir / "config.yaml").read_text()
    edited = yaml.safe_load(original)
    v_max = edited["env"]["v_max"]
    edited["env"] |= {"max_steps": 30, "v_max": v_max / 2}
    (run_dir / "config.yaml").write_text(yaml.safe_dump(edited))
    files = {path: path.read_bytes() for path in run_dir.rglob("*") if path.is_file()}
    capsys.readouterr()
    assert main(["train", "--resume", str(run_dir), "--no-progress"]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "no longer holds the recipe iteration_000002 was trained with" in error
    assert "env.max_steps: 20 in the checkpoint, 30 in config.yaml" in error
    assert f"env.v_max: {v_max!r} in the checkpoint, {v_max / 2!r} in config.yaml" in error
    assert {path: path.read_bytes() for path in run_dir.rglob("*") if path.is_file()} == files
    (run_dir / "config.yaml").write_text(original)
    assert main(["train", "--resume", str(run_dir), "--no-progress"]) == 0
    assert (run_dir / FINAL_MODEL).is_file()


def test_a_damaged_state_json_is_named_on_resume(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A truncated or edited ``state.json`` of the checkpoint a resume starts from is a one-line error naming the file
    (not json's "Expecting ',' delimiter"), and nothing is touched."""
    run_dir = tmp_path / "run"
    arguments = ["train", "--recipe", "ch4-individual", "--iterations", "1,1,0", "--n-envs", "2", "--no-progress"]
    assert main([*arguments, "--env", "max_steps=20", "--run-dir", str(run_dir), "--checkpoint-every", "1"]) == 0
    (run_dir / FINAL_MODEL).unlink()  # a run killed while its final model was written: there is work to resume
    state_file = latest_checkpoint(run_dir) / STATE_FILE
    original = state_file.read_text()
    edited = json.loads(original) | {"curriculum": "stage 2"}
    for damaged in (original[: len(original) // 2], json.dumps(edited), "[]"):
        state_file.write_text(damaged)
        files = {path: path.read_bytes() for path in run_dir.rglob("*") if path.is_file()}
        capsys.readouterr()
        assert main(["train", "--resume", str(run_dir), "--no-progress"]) == 2
        error = capsys.readouterr().err
        assert error.count("\n") == 1 and f"{state_file} is damaged" in error and "Traceback" not in error, error
        assert {path: path.read_bytes() for path in run_dir.rglob("*") if path.is_file()} == files


@pytest.mark.slow
def test_sigterm_during_a_long_ppo_update_stops_before_the_next_mini_batch(tmp_path: Path) -> None:
    """The first iteration's update of 10^6 epochs would run for many minutes: SIGTERM inside it drops that iteration
    and checkpoints the state before it, as a stop during a rollout does, within the hang guard."""
    long_update = {"base": "ch4-individual", "ppo": {"n_steps": 16, "batch_size": 16, "n_epochs": 1_000_000}}
    (tmp_path / "long.yaml").write_text(yaml.safe_dump(long_update))
    process = run_cli("train", "--recipe", "long.yaml", "--iterations", "0,0,2", "--run-dir", "run", *QUICK, cwd=tmp_path)
    said = read_lines_until(process.stdout, lambda line: "PPO update under way" in line)  # the rollout is over
    assert said, process.communicate(timeout=60)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)  # a hang guard: the update itself would take far longer
    assert process.returncode == 143, stderr
    message = "sb3-formation: stopped by SIGTERM; checkpoint run/checkpoints/iteration_000000; continue with --resume run"
    assert stderr.strip().splitlines()[-1] == message, stderr
    state = json.loads((tmp_path / "run" / "checkpoints" / "iteration_000000" / STATE_FILE).read_text())
    assert state["num_timesteps"] == 0 and state["curriculum"]["iteration"] == 0
    assert read_model_data(tmp_path / "run" / "checkpoints" / "iteration_000000" / "model.zip")["_n_updates"] == 0


RUNS = ("whole", "stopped")


def test_a_stop_inside_an_update_checkpoints_the_state_before_it_bit_for_bit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SIGTERM at the second mini-batch of the second iteration's update: the checkpoint written is the state after
    the first iteration (model, optimiser, normalisers, curriculum, counters), byte for byte as an unstopped run's."""
    recipe = {
        "base": "ch4-individual",
        "ppo": {"n_steps": 16, "batch_size": 16, "n_epochs": 3},
        "training": {"normalize_reward": True},
    }
    (tmp_path / "short.yaml").write_text(yaml.safe_dump(recipe))
    arguments = ["train", "--recipe", str(tmp_path / "short.yaml"), "--iterations", "0,0,3", "--checkpoint-every", "1"]
    assert main([*arguments, "--no-evaluate", "--run-dir", str(tmp_path / "whole"), *QUICK]) == 0
    steps, adam_step = [], torch.optim.Adam.step

    def sigterm_at_the_eleventh_step(self: torch.optim.Adam, *args: Any, **kwargs: Any) -> Any:
        steps.append(1)
        if len(steps) == 11:  # 48 samples (16 steps of 3 agents): 3 mini-batches x 3 epochs an update; the second's 2nd
            os.kill(os.getpid(), signal.SIGTERM)
        return adam_step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", sigterm_at_the_eleventh_step)
    assert main([*arguments, "--no-evaluate", "--run-dir", str(tmp_path / "stopped"), *QUICK]) == 143
    assert len(steps) == 11  # the twelfth step was never taken
    assert latest_checkpoint(tmp_path / "stopped").name == "iteration_000001"
    whole, stopped = (tmp_path / run / "checkpoints" / "iteration_000001" for run in RUNS)
    for name in ("normalizer.npz", "reward_normalizer.npz"):
        assert (whole / name).read_bytes() == (stopped / name).read_bytes(), name
    states = [json.loads((folder / STATE_FILE).read_text()) | {"training_seconds": 0} for folder in (whole, stopped)]
    assert states[0] == states[1]  # all but the wall time
    models = [load_from_zip_file(folder / "model.zip") for folder in (whole, stopped)]
    assert models[0][0]["_n_updates"] == models[1][0]["_n_updates"] == 3
    for part in ("policy", "policy.optimizer"):
        assert str(models[0][1][part]) == str(models[1][1][part]), part
