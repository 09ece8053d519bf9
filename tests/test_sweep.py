"""Recipe files and sweeps: every recipe file of recipes/ validates, the quick ones train end to end, and a real local Ray
sweep trains, skips finished trials when restarted after a kill, reports a broken trial and aggregates over seeds."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from terminal import default_ctrl_c

from sb3_formation.cli import main
from sb3_formation.experiment.recipes import load_recipe, load_settings
from sb3_formation.experiment.runs import FINAL_MODEL
from sb3_formation.experiment.statistics import wilson_interval
from sb3_formation.experiment.sweep import aggregate, sweep
from sb3_formation.sb3.metrics import EPISODE_METRICS
from sb3_formation.viz.plots import save_sweep_curves

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
THESIS = {  # thesis 4.3-4.4 and 5.3-5.4: iterations per stage, parallel teams, seeds, evaluation episodes
    "thesis-ch4-individual": ((10000, 10000, 20000), 12, 4, 500),
    "thesis-ch4-team": ((10000, 10000, 20000), 12, 4, 500),
    "thesis-ch5-angle": ((5000, 5000, 15000), 14, 3, 200),
    "thesis-ch5-bearing": ((5000, 5000, 15000), 14, 3, 200),
}


def test_every_thesis_recipe_file_has_a_quick_twin_and_the_thesis_budget() -> None:
    names = sorted(path.stem for path in RECIPES.glob("*.yaml"))
    shipped = [
        "pretrained-mixed-ch5-bearing",
        "pretrained-ch5-bearing-unicycle",
        "pretrained-scenes-ch5-bearing",
        "pretrained-talk-scenes-ch5-bearing",
        "pretrained-robust-scenes-ch5-bearing",
        "pretrained-moving-scenes-ch5-bearing",
    ]
    pretrained = [name.replace("thesis-", "pretrained-") for name in THESIS] + shipped
    assert names == sorted([*THESIS, *(name.replace("thesis-", "quick-") for name in THESIS), *pretrained])
    for name, (iterations, teams, seeds, episodes) in THESIS.items():
        settings = load_settings(RECIPES / f"{name}.yaml")
        recipe = settings.recipe
        base = load_recipe(name.removeprefix("thesis-"))
        assert {
            key: value for key, value in recipe.to_dict().items() if key not in ("name", "curriculum", "n_envs", "evaluation")
        } == {
            key: value for key, value in base.to_dict().items() if key not in ("name", "curriculum", "n_envs", "evaluation")
        }  # the thesis recipe, with the thesis's budget
        assert recipe.stage_iterations() == iterations and recipe.n_envs == teams
        assert len(settings.run.seeds) == seeds and recipe.evaluation.episodes == episodes and settings.run.evaluate
        assert recipe.evaluation.stage == 3
        assert recipe.recurrent == name.startswith("thesis-ch5")  # thesis 5.1.2: recurrent networks
        kwargs = recipe.ppo_kwargs()
        thesis_ppo = base.ppo.to_dict()  # the thesis's PPO settings (thesis 4.3, 5.3)
        assert {key: kwargs[key] for key in thesis_ppo} == thesis_ppo and thesis_ppo["learning_rate"] == 5e-5
        quick = load_settings(RECIPES / f"{name.replace('thesis-', 'quick-')}.yaml")
        assert quick.recipe.ppo == recipe.ppo and sum(quick.recipe.stage_iterations()) <= 3


def test_recipe_file_errors_name_the_file_and_the_setting(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"no recipe file .*missing\.yaml"):
        load_settings(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("base: ch5-bearing\nevaluation: {episodes: 5, colour: red}\n")
    with pytest.raises(ValueError, match=r"recipe 'bad': evaluation needs episodes .*: unknown keys \['colour'\]"):
        load_settings(bad)
    bad.write_text("base: ch5-bearing\nrun: {seeds: []}\n")
    with pytest.raises(ValueError, match="seeds must be a non-empty list"):
        load_settings(bad)


def test_aggregate_is_the_mean_and_std_over_seeds() -> None:
    def summary(successes: int, angle: float | None) -> dict:
        means = {name: None if angle is None else 1.0 for name in EPISODE_METRICS} | {"angle_error_deg": angle}
        return {
            "success_rate": successes / 10,
            "success_rate_ci95": list(wilson_interval(successes, 10)),
            "successful_episodes": {name: {"mean": mean, "std": 0.0} for name, mean in means.items()},
        }

    table = aggregate([summary(1, 30.0), summary(3, 20.0), summary(0, None)])
    assert table["success_rate"]["mean"] == pytest.approx(4 / 30)
    assert table["success_rate"]["std"] == pytest.approx(np.std([0.1, 0.3, 0.0]))
    # the seed without successful episodes has no angle error: mean and std over the other two
    assert table["angle_error_deg"] == {"mean": 25.0, "std": 5.0, "seeds": 2}


@pytest.mark.slow
@pytest.mark.parametrize("name", [name.replace("thesis-", "quick-") for name in THESIS])
def test_quick_recipes_train_and_evaluate(name: str, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    assert main(["train", "--recipe", str(RECIPES / f"{name}.yaml"), "--run-dir", str(run_dir)]) == 0
    summary = json.loads((run_dir / "eval" / "summary.json").read_text())
    assert summary["episodes"] == 4 and summary["stage"] == 3
    assert (run_dir / FINAL_MODEL).is_file() and (run_dir / "eval" / "trajectories.npz").is_file()


# A real local Ray sweep --------------------------------------------------------------------------------------------

TINY = {
    "base": "ch4-individual",
    "curriculum": {"iterations": [1, 0, 12]},
    "n_envs": 1,
    "env": {"max_steps": 30},
    "policy": {"net_arch": {"pi": [16], "vf": [16]}},
    "evaluation": {"episodes": 2, "stage": 3, "seed": 0, "n_envs": 2},
    "run": {"seeds": [0, 1], "progress_bar": False, "checkpoint_every": 1, "evaluate": True},
}


def wait_for(predicate, timeout: float = 300.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.2)


@pytest.mark.slow
def test_ray_sweep_skips_finished_trials_after_a_kill_and_aggregates(tmp_path: Path) -> None:
    recipe_file = tmp_path / "tiny.yaml"
    recipe_file.write_text(yaml.safe_dump(TINY))
    logdir = tmp_path / "logs"
    command = [sys.executable, "-m", "sb3_formation.cli", "sweep", str(recipe_file), "--logdir", str(logdir)]
    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True, "preexec_fn": default_ctrl_c}
    process = subprocess.Popen([*command, "--max-concurrent", "1"], **pipes)
    first = logdir / "tiny" / "seed_0"
    # the second trial has started (its config.yaml is its first file): the sweep is killed while it runs
    wait_for(lambda: (logdir / "tiny" / "seed_1" / "config.yaml").exists())
    process.send_signal(signal.SIGINT)
    process.communicate(timeout=120)
    finished_at = os.stat(first / FINAL_MODEL).st_mtime_ns
    assert (first / "eval" / "summary.json").exists() and not (logdir / "tiny" / "aggregate.json").exists()

    result = sweep(recipe_file, logdir=logdir)
    save_sweep_curves(result)
    assert result.trials[0]["status"] == "skipped"  # finished before the kill: not trained again
    assert os.stat(first / FINAL_MODEL).st_mtime_ns == finished_at
    assert result.trials[1]["status"] == "trained" and not result.failed
    summaries = [json.loads((logdir / "tiny" / f"seed_{seed}" / "eval" / "summary.json").read_text()) for seed in (0, 1)]
    assert [yaml.safe_load((logdir / "tiny" / f"seed_{s}" / "config.yaml").read_text())["run"]["seed"] for s in (0, 1)] == [
        0,
        1,
    ]
    aggregated = json.loads((logdir / "tiny" / "aggregate.json").read_text())
    assert aggregated["seeds"] == [0, 1]
    rates = [summary["success_rate"] for summary in summaries]
    assert aggregated["all"]["success_rate"]["mean"] == pytest.approx(np.mean(rates))
    lengths = [summary["all_episodes"]["length"]["mean"] for summary in summaries]
    assert aggregated["all"]["length"] == {
        "mean": pytest.approx(np.mean(lengths)),
        "std": pytest.approx(np.std(lengths)),
        "seeds": 2,
    }
    table = (logdir / "tiny" / "aggregate.md").read_text()
    assert "| tiny | all episodes | 2 |" in table and "| tiny | successful episodes | 2 |" in table
    assert (logdir / "tiny" / "training_curves.png").stat().st_size > 10_000
    assert not math.isnan(aggregated["all"]["angle_error_deg"]["mean"])


@pytest.mark.slow
def test_ray_sweep_reports_a_broken_trial_and_finishes_the_others(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    recipe_file = tmp_path / "tiny.yaml"
    recipe_file.write_text(yaml.safe_dump(TINY))
    broken = tmp_path / "logs" / "tiny" / "seed_1" / "checkpoints" / "iteration_000001"
    broken.mkdir(parents=True)  # a checkpoint whose model file is not a model: resuming it must fail
    (broken / "state.json").write_text(json.dumps({"num_timesteps": 384, "curriculum": {}}))
    (broken / "model.zip").write_text("not a zip file")
    (broken.parents[1] / "config.yaml").write_text(yaml.safe_dump({**TINY, "seed": 1}))
    code = main(["sweep", str(recipe_file), "--logdir", str(tmp_path / "logs")])
    assert code == 1
    error = capsys.readouterr().err
    assert "trial seed 1 failed" in error
    assert (tmp_path / "logs" / "tiny" / "seed_0" / "eval" / "summary.json").is_file()  # the other trial completed
    assert json.loads((tmp_path / "logs" / "tiny" / "aggregate.json").read_text())["seeds"] == [0]
