"""Policy targets through one registry: controllers evaluated, rendered, plotted, compared and rolled out like trained
models; a recorded episode drawn from its trajectories file alone."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sb3_formation import FormationEnv, load_policy
from sb3_formation.cli import main
from sb3_formation.controllers import ClassicalController, RandomController, TeamPolicy
from sb3_formation.controllers.residual import ResidualPolicy
from sb3_formation.env.rendering import render_frame
from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.targets import Target
from sb3_formation.experiment.trajectories import Trajectories
from sb3_formation.safety.policy import SafePolicy

QUICK = ["--episodes", "2", "--n-envs", "2", "--no-progress"]


def test_targets_resolve_through_one_registry() -> None:
    policy = load_policy("controller:random", recipe="ch4-team")
    assert isinstance(policy, RandomController) and isinstance(policy, TeamPolicy)
    assert policy.config.n_agents == 3 and policy.config.team_reward  # the ch4-team recipe's task
    assert load_policy("controller:random").config.n_agents == 6  # default recipe: ch5-bearing
    assert Target.parse("controller:random").kind == "controller" and Target.parse("runs/a:b").kind == "model"
    assert Target.parse("runs/a:b").path == Path("runs/a:b") and Target.parse("onnx:p").path == Path("p")
    assert Target.parse("controller:random", "ch4-team").evaluation_folder() == Path("evaluations/controller-random_ch4-team")
    known = "classical, crowd, privileged-planner, random, shrinking"
    with pytest.raises(ValueError, match=f"unknown controller 'pid'; controllers: {known}$"):
        load_policy("controller:pid")
    with pytest.raises(ValueError, match="a recipe applies to controller targets only"):
        load_policy("runs/x", recipe="ch5-bearing")
    with pytest.raises(FileNotFoundError, match="no model at"):
        load_policy("runs/none")


def test_a_controller_is_evaluated_reproducibly_by_seed() -> None:
    policy = load_policy("controller:random", recipe="ch4-individual")
    first = evaluate(policy, episodes=3, stage=1, seed=5, n_envs=2, env_overrides={"max_steps": 20})
    again = evaluate(load_policy("controller:random", recipe="ch4-individual"), 3, 1, 5, 2, env_overrides={"max_steps": 20})
    other = evaluate(policy, episodes=3, stage=1, seed=6, n_envs=2, env_overrides={"max_steps": 20})
    assert first.episodes == again.episodes and first.episodes != other.episodes
    assert first.summary["model"] == {"controller": "RandomController", "gains": {"seed": None}}


@pytest.mark.parametrize("name", ["random", "classical"])
def test_controller_targets_work_with_every_command(name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    short = ["--recipe", "ch4-individual"]
    assert main(["evaluate", f"controller:{name}", *short, *QUICK, "--trajectories", "1"]) == 0
    folder = tmp_path / "evaluations" / f"controller-{name}_ch4-individual"
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["episodes"] == 2 and summary["n_agents"] == 3 and summary["stage"] == 3
    assert main(["plot", "trajectories", f"controller:{name}", *short]) == 0
    assert (folder / "figures" / "trajectory_000.png").stat().st_size > 10_000
    assert main(["render", f"controller:{name}", *short, "--max-steps", "5", "--out", f"{name}.gif"]) == 0
    assert (tmp_path / f"{name}.gif").stat().st_size > 1_000
    # compare reuses the stored evaluation of the same controller under the same protocol
    assert main(["compare", f"controller:{name}", *short, *QUICK, "--out", "bars.png", "--table", "table.md"]) == 0
    assert f"| controller:{name} | 2 |" in (tmp_path / "table.md").read_text()
    assert main(["rollout", f"controller:{name}", *short, "--episodes", "1", "--max-steps", "5", "--out", "f.png"]) == 0
    assert (tmp_path / "f.png").is_file()


def test_safe_targets_put_any_target_behind_the_filter_in_every_command(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``safe:<target>``: the same target behind the safety filter; its evaluations beside the unfiltered ones (folder
    ``-safe``), compared with them, and rendered."""
    monkeypatch.chdir(tmp_path)
    policy = load_policy("safe:controller:classical", recipe="ch4-individual")
    assert isinstance(policy, SafePolicy) and isinstance(policy.policy, ClassicalController)
    assert policy.config.n_agents == 3 and Target.parse("safe:controller:classical").kind == "controller"
    assert isinstance(load_policy("safe:pretrained:ch5-bearing").policy, ResidualPolicy)
    assert Target.parse("safe:controller:random").evaluation_folder() == Path("evaluations/controller-random_ch5-bearing-safe")
    assert Target.parse("safe:runs/a/final_model.zip").evaluation_folder("trap") == Path("runs/a/eval-trap-safe")
    (tmp_path / "runs" / "a").mkdir(parents=True)
    assert Target.parse("safe:runs/a").label == "safe-a"
    assert Target.parse("safe:controller:random").label == "safe:controller:random"
    short = ["--recipe", "ch4-individual", *QUICK]
    for target in ("controller:classical", "safe:controller:classical"):
        assert main(["evaluate", target, *short]) == 0
    plain, safe = (
        json.loads((tmp_path / "evaluations" / f"controller-classical_ch4-individual{suffix}" / "summary.json").read_text())
        for suffix in ("", "-safe")
    )
    assert "min_separation" not in plain and safe["min_separation"] > 0
    assert safe["model"]["policy"] == plain["model"] and safe["model"]["safety"]["gamma"] == 0.5
    assert main(["compare", "controller:classical", "safe:controller:classical", *short, "--table", "table.md"]) == 0
    assert "| safe:controller:classical | 2 |" in (tmp_path / "table.md").read_text()
    assert (
        main(["render", "safe:controller:classical", "--recipe", "ch4-individual", "--max-steps", "5", "--out", "s.gif"]) == 0
    )


def test_a_recorded_episode_is_drawn_from_its_file_without_the_policy(tmp_path: Path) -> None:
    """render_frame of a state rebuilt from trajectories.npz equals the env's own frame at that step, replayed from the
    recorded actions (a state is all rendering needs; recordings hold no lidar readings)."""
    policy = RandomController(load_policy("controller:random", recipe="ch4-individual").config)
    result = evaluate(policy, episodes=1, stage=3, seed=2, n_envs=1, env_overrides={"max_steps": 12}, record=1)
    result.save(tmp_path)
    trajectories = Trajectories.load(tmp_path / "trajectories.npz")
    env = FormationEnv(trajectories.config, render_mode="rgb_array")
    env.reset(seed=int(trajectories.seeds[0]))
    for step in range(int(trajectories.lengths[0]) + 1):
        if step:
            env.step_array(trajectories.actions[0, step])
        drawn = render_frame(trajectories.team_state(0, step), trajectories.config)
        np.testing.assert_array_equal(drawn, env.render())
    with pytest.raises(ValueError, match="lidar"):
        render_frame(trajectories.team_state(0, 0), trajectories.config, draw_lidar=True)
    with pytest.raises(IndexError):
        trajectories.team_state(0, int(trajectories.lengths[0]) + 1)


def test_a_target_is_parsed_once_into_one_value() -> None:
    """``safe:`` any number of times is one filter, in the folder of ``safe:<target>`` (inside the target's own folder,
    not the working folder); the parsed value is what every command is given."""
    once, twice = Target.parse("safe:runs/a/final_model.zip"), Target.parse("safe:safe:runs/a/final_model.zip")
    assert once == twice == Target("model", "runs/a/final_model.zip", safe=True)
    assert twice.evaluation_folder() == once.evaluation_folder() == Path("runs/a/eval-safe")
    assert str(twice) == "safe:safe:runs/a/final_model.zip" and str(Target("controller", "random", True)) == (
        "safe:controller:random"
    )
    assert Target.parse("safe:safe:controller:random").evaluation_folder() == Path(
        "evaluations/controller-random_ch5-bearing-safe"
    )
    policy = load_policy("safe:safe:controller:classical", recipe="ch4-individual")
    assert isinstance(policy, SafePolicy) and isinstance(policy.policy, ClassicalController)
    assert Target.parse(once) is once and Target.parse(once, "ch4-team").recipe == "ch4-team"
    assert [Target.parse(text).kind for text in ("x.onnx", "onnx:x", "pretrained:a", "model:x", "runs/x")] == [
        "onnx",
        "onnx",
        "pretrained",
        "model",
        "model",
    ]
    assert Target.parse("runs/x").with_recipe("ch4-team").recipe is None
    with pytest.raises(ValueError, match="names no file"):
        _ = Target.parse("controller:random").path
    with pytest.raises(ValueError, match="unknown kind of target 'robot'"):
        Target("robot", "x")


def test_a_target_names_its_recipe_and_protocol(tmp_path: Path) -> None:
    """A controller is evaluated in the recipe named for it, a model file of no run in none; command-line changes of
    the protocol are validated by the evaluation section."""
    controller = Target.parse("controller:random", "ch4-team")
    recipe = controller.task_recipe()
    assert recipe is not None and recipe.name == "ch4-team"
    assert controller.protocol() == recipe.evaluation
    assert controller.protocol(episodes=3, stage=None).episodes == 3
    assert controller.protocol(stage=None).stage == recipe.evaluation.stage
    with pytest.raises(ValueError, match="evaluation: stage must be 1, 2 or 3, got 4"):
        controller.protocol(stage=4)
    loose = Target.parse(tmp_path / "model.zip")
    assert loose.run_folder is None and loose.task_recipe() is None
    assert loose.protocol(episodes=2).episodes == 2
    with pytest.raises(ValueError, match="belongs to no run folder whose recipe gives the number of episodes"):
        loose.protocol()
