"""Shipped policies: exported from a run, loaded by name, refused in other tasks, and their stored evaluation reproduced."""

from __future__ import annotations

import csv
import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path, PurePosixPath

import numpy as np
import pytest
import tomllib
import torch
import yaml

from sb3_formation import FormationEnv, load_policy
from sb3_formation.cli import main
from sb3_formation.experiment.evaluation import EPISODES_FILE, evaluate
from sb3_formation.experiment.export import export_pretrained
from sb3_formation.experiment.pretrained import (
    CARD_FILE,
    ONNX_FILE,
    PRETRAINED_DIR,
    SUMMARY_PATH,
    load_pretrained,
    numerics_fingerprint,
    pretrained_card,
    pretrained_folder,
    pretrained_names,
)
from sb3_formation.experiment.recipes import RECIPES_FOLDER, load_recipe
from sb3_formation.experiment.runs import FINAL_MODEL, latest_checkpoint
from sb3_formation.experiment.statistics import wilson_interval
from sb3_formation.runtime import OnnxPolicy

THESIS_TASKS = ("ch4-individual", "ch4-team", "ch5-angle", "ch5-bearing")


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished run of a shrunken residual-ch5-bearing recipe, with a 3-episode evaluation protocol."""
    folder = tmp_path_factory.mktemp("pretrained")
    values = yaml.safe_load((RECIPES_FOLDER / "residual-ch5-bearing.yaml").read_text())
    values["policy"]["net_arch"] = {"pi": [16], "vf": [16]}
    values["ppo"] |= {"n_steps": 16, "batch_size": 64, "n_epochs": 2}
    values["n_envs"] = 2
    values["training"] |= {"steps": 2 * 16 * 12, "eval_every": 100}
    values["evaluation"] = {"episodes": 3, "stage": 3}
    setup = folder / "tiny.yaml"
    setup.write_text(yaml.safe_dump(values))
    run = folder / "run"
    assert main(["train", "--recipe", str(setup), "--env", "max_steps=60", "--run-dir", str(run), "--no-progress"]) == 0
    return run


def test_an_exported_policy_is_the_runs_model_trimmed_and_evaluated(tiny_run: Path, tmp_path: Path) -> None:
    folder = export_pretrained(tiny_run, "tiny", root=tmp_path, command="the command")
    assert pretrained_names(tmp_path) == ["tiny"] and pretrained_folder("tiny", tmp_path) == folder
    card = pretrained_card("tiny", tmp_path)
    state = json.loads((latest_checkpoint(tiny_run) / "state.json").read_text())
    assert card["training_seconds"] == round(state["training_seconds"], 1) and card["seed"] == 0
    assert card["training_agent_steps"] == state["num_timesteps"] == 2 * 16 * 12
    assert card["training_command"] == (tiny_run / "command.txt").read_text().strip()
    assert card["export_command"] == "the command" and card["n_agents"] == 6 and card["team_sizes"] == [6]
    assert card["numerics"] == numerics_fingerprint()
    assert card["recipe"] == "tiny" and card["package_version"] == "0.1.0"
    shipped, run = load_pretrained("tiny", root=tmp_path), load_policy(tiny_run)
    # the same weights, without the optimiser's moments: a smaller file
    for mine, theirs in zip(shipped.correction.policy.parameters(), run.correction.policy.parameters()):
        assert torch.equal(mine, theirs)
    assert (folder / FINAL_MODEL).stat().st_size < 0.6 * (tiny_run / FINAL_MODEL).stat().st_size
    # the stored evaluation is of the shipped file, and the run's own model plays the same episodes
    summary = card["summary"]
    digest = hashlib.sha256((folder / FINAL_MODEL).read_bytes()).hexdigest()
    assert summary["model"] == {"file": "pretrained:tiny", "sha256": digest}
    again = evaluate(run, episodes=3, stage=3, seed=0, n_envs=8, record=0)
    assert summary["episodes"] == 3 and summary["success_rate"] == again.summary["success_rate"]
    with open(folder / "eval" / EPISODES_FILE) as stream:
        stored = list(csv.DictReader(stream))
    assert [row["length"] for row in stored] == [str(row["length"]) for row in again.episodes]
    assert [row["return"] for row in stored] == [str(row["return"]) for row in again.episodes]
    # the ONNX export beside the zip acts as the shipped model
    rows = np.stack(list(FormationEnv(shipped.config.replace(stage=3)).reset(seed=1)[0].values()))
    assert np.abs(OnnxPolicy(folder / ONNX_FILE).predict(rows)[0] - shipped.predict(rows)[0]).max() <= 1e-5


def test_export_refuses_bad_input_and_keeps_what_is_shipped(tiny_run: Path, tmp_path: Path) -> None:
    export_pretrained(tiny_run, "kept", root=tmp_path)
    before = (tmp_path / "kept" / FINAL_MODEL).read_bytes()
    with pytest.raises(ValueError, match="a shipped policy's name is letters, digits"):
        export_pretrained(tiny_run, "../kept", root=tmp_path)
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    (unfinished / "config.yaml").write_text((tiny_run / "config.yaml").read_text())
    with pytest.raises(ValueError, match=r"is not a finished run: it lacks final_model\.zip, final_normalizer\.npz"):
        export_pretrained(unfinished, "kept", root=tmp_path)
    assert (tmp_path / "kept" / FINAL_MODEL).read_bytes() == before
    # a shipped name is replaced only when told, and the temporary folder of a killed export is cleared then
    with pytest.raises(ValueError, match=f"pretrained:kept exists in {tmp_path}: give another name, or --replace"):
        export_pretrained(tiny_run, "kept", root=tmp_path)
    assert (tmp_path / "kept" / FINAL_MODEL).read_bytes() == before
    (tmp_path / ".kept.killed0").mkdir()
    export_pretrained(tiny_run, "kept", root=tmp_path, replace=True)
    assert sorted(path.name for path in tmp_path.iterdir() if path.name.startswith(".")) == []
    with pytest.raises(ValueError, match="no shipped policy 'gone'; shipped: kept"):
        load_pretrained("gone", root=tmp_path)
    assert main(["pretrained", "--name", "x"]) == 2  # --export and --name go together


def test_the_four_thesis_tasks_ship_a_policy_trained_for_their_task() -> None:
    assert set(THESIS_TASKS) <= set(pretrained_names())
    for task in THESIS_TASKS:
        card = pretrained_card(task)
        assert load_recipe(card["recipe"]).config() == load_recipe(task).config()
        assert card["summary"]["episodes"] == load_recipe(task).evaluation.episodes
        assert card["summary"]["stage"] == 3 and card["summary"]["seed"] == 0 and card["summary"]["deterministic"]
        # the stored evaluation is of the shipped file, and its rate is that of its stored episodes
        folder = pretrained_folder(task)
        assert card["summary"]["model"]["sha256"] == hashlib.sha256((folder / FINAL_MODEL).read_bytes()).hexdigest()
        with open(folder / "eval" / EPISODES_FILE) as stream:
            successes = [row["success"] == "True" for row in csv.DictReader(stream)]
        assert len(successes) == card["summary"]["episodes"]
        assert sum(successes) == round(card["summary"]["success_rate"] * len(successes))
    for name in pretrained_names():  # each shipped policy (model, ONNX file, evaluation) stays under 2 MiB
        folder = pretrained_folder(name)
        assert sum(path.stat().st_size for path in folder.rglob("*") if path.is_file()) < 2 * 2**20, name


def test_a_shipped_policy_refuses_another_task_or_team_size() -> None:
    policy = load_pretrained("ch5-bearing", recipe="ch5-bearing")  # its own task, named by its recipe
    assert policy.config.n_agents == 6
    with pytest.raises(
        ValueError, match=r"pretrained:ch5-bearing was not trained for recipe ch4-team: n_agents=3 \(trained with 6\)"
    ):
        load_pretrained("ch5-bearing", recipe="ch4-team")
    with pytest.raises(ValueError, match=r"k_angle=0\.3 \(trained with 0\.0\); k_bearing=0\.0 \(trained with 0\.3\)"):
        load_policy("pretrained:ch5-bearing", recipe="ch5-angle")
    with pytest.raises(ValueError, match="n_agents=6 in the model, 4 in the env"):
        evaluate(policy, episodes=1, env_overrides={"n_agents": 4})


def test_the_policy_trained_on_several_team_sizes_takes_any_size_but_no_other_task() -> None:
    assert pretrained_card("mixed-ch5-bearing")["team_sizes"] == [3, 4, 5, 6, 7, 8]
    policy = load_pretrained("mixed-ch5-bearing", recipe="mixed-ch5-bearing")
    result = evaluate(policy, episodes=1, n_envs=1, env_overrides={"n_agents": 10, "max_steps": 5}, record=0)
    assert result.n_agents == 10 and result.episodes[0]["length"] == 5  # a size it never saw
    with pytest.raises(ValueError, match=r"observe_reference_bearings=False \(trained with True\)"):
        load_pretrained("mixed-ch5-bearing", recipe="ch5-bearing")  # the thesis observation lacks the bearings


@pytest.mark.slow
@pytest.mark.parametrize(
    "name",
    [
        *THESIS_TASKS,
        "mixed-ch5-bearing",
        "ch5-bearing-unicycle",
        "scenes-ch5-bearing",
        "talk-scenes-ch5-bearing",
        "robust-scenes-ch5-bearing",
        "moving-scenes-ch5-bearing",
    ],
)
def test_a_shipped_policy_reproduces_its_stored_episodes(name: str, tmp_path: Path) -> None:
    """Its first 20 stored evaluation episodes, replayed on this machine, give the same rows, digit for digit.

    The exporting machine's float kernels are recorded as :func:`numerics_fingerprint` (a fixed numpy and torch
    computation, not this package's code); a CPU that rounds them otherwise plays other episodes from the same
    scenarios, so there 40 replayed episodes must agree with the stored success rate: it lies in their 99.9 % Wilson
    interval."""
    card = pretrained_card(name)
    summary = card["summary"]
    # the stored episodes were played as many teams at a time as the card says (8, the default then, where it does
    # not say): torch may round a batch of another size otherwise on some CPUs
    policy, teams = load_pretrained(name), card.get("evaluation_teams", 8)
    if numerics_fingerprint() != card["numerics"]:  # another CPU
        result = evaluate(policy, episodes=40, stage=summary["stage"], seed=summary["seed"], n_envs=teams, record=0)
        low, high = wilson_interval(sum(bool(row["success"]) for row in result.episodes), 40, z=3.2905)
        assert low <= summary["success_rate"] <= high, (summary["success_rate"], result.summary["success_rate"])
        return
    result = evaluate(policy, episodes=20, stage=summary["stage"], seed=summary["seed"], n_envs=teams, record=0)
    result.save(tmp_path)
    stored = (pretrained_folder(name) / "eval" / EPISODES_FILE).read_text().splitlines()
    assert (tmp_path / EPISODES_FILE).read_text().splitlines() == stored[:21]


def test_shipped_policies_load_in_a_fresh_process_without_network_or_run_folder(tmp_path: Path) -> None:
    script = """
import socket, sys
def refuse(*args, **kwargs):
    raise OSError("network access attempted")
socket.socket.connect = socket.create_connection = refuse
from sb3_formation import FormationEnv, load_pretrained, pretrained_names
import numpy as np
for name in pretrained_names():
    policy = load_pretrained(name)
    rows = np.stack(list(FormationEnv(policy.config.replace(stage=3)).reset(seed=1)[0].values()))
    actions, _ = policy.predict(rows)
    assert actions.shape == (policy.config.n_agents, 2) and np.isfinite(actions).all()
    print(name)
"""
    done = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == pretrained_names()
    assert list(tmp_path.iterdir()) == []  # it wrote nothing where it ran


def test_pretrained_targets_work_with_every_command(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["pretrained"]) == 0
    listing = capsys.readouterr().out
    for name in pretrained_names():
        rate = pretrained_card(name)["summary"]["success_rate"]
        assert f"| pretrained:{name} | {pretrained_card(name)['recipe']} |" in listing and f"| {rate:.1%} (" in listing
    assert "| pretrained:ch5-bearing | residual-ch5-bearing | 6 | stage 3 |" in listing
    assert "| pretrained:scenes-ch5-bearing | residual-scenes-ch5-bearing | 6 | mixed scenes |" in listing
    quick = ["--episodes", "2", "--n-envs", "2", "--no-progress"]
    assert main(["evaluate", "pretrained:ch5-bearing", *quick, "--trajectories", "1"]) == 0
    folder = tmp_path / "evaluations" / "pretrained-ch5-bearing_residual-ch5-bearing"
    summary = json.loads((folder / "summary.json").read_text())
    stored = pretrained_card("ch5-bearing")["summary"]
    assert summary["model"]["sha256"] == stored["model"]["sha256"] and summary["episodes"] == 2
    assert main(["plot", "trajectories", "pretrained:ch5-bearing"]) == 0
    assert (folder / "figures" / "trajectory_000.png").stat().st_size > 10_000
    assert main(["render", "pretrained:ch5-bearing", "--max-steps", "5", "--out", "shipped.gif"]) == 0
    assert (tmp_path / "shipped.gif").stat().st_size > 1_000
    table = ["--table", "table.md", "--out", "bars.png"]
    assert main(["compare", "pretrained:ch5-bearing", "controller:classical", "--recipe", "ch5-bearing", *quick, *table]) == 0
    assert "| pretrained:ch5-bearing | 2 |" in (tmp_path / "table.md").read_text()
    assert main(["evaluate", "pretrained:ch5-bearing", "--recipe", "ch4-team", *quick]) == 2
    rows = np.stack(list(FormationEnv(load_recipe("ch5-bearing").config(stage=3)).reset(seed=2)[0].values()))
    assert np.isfinite(load_policy("pretrained:ch5-bearing").predict(rows)[0]).all()


def test_every_file_of_the_shipped_policies_is_package_data() -> None:
    """The wheel takes what pyproject.toml's package-data globs name (checked by building one: it held every file)."""
    globs = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    package = PRETRAINED_DIR.parent

    def packaged(file: PurePosixPath) -> bool:  # setuptools' globs: each * stays within one folder
        return any(file.match(glob) and len(file.parts) == len(PurePosixPath(glob).parts) for glob in globs["sb3_formation"])

    files = [PurePosixPath(path.relative_to(package).as_posix()) for path in PRETRAINED_DIR.rglob("*") if path.is_file()]
    assert files and all(packaged(file) for file in files)
    assert not packaged(PurePosixPath("pretrained/x/eval/figures/a.png"))  # deeper files would be left out


def test_a_thesis_recipe_run_with_a_fixed_sigma_is_exported(tmp_path: Path) -> None:
    """The thesis's recipes keep sigma fixed: the log-std is not trained, and the export's fresh optimiser must not
    take it either."""
    run = tmp_path / "run"
    arguments = ["train", "--recipe", "ch4-individual", "--iterations", "1,0,0", "--n-envs", "2", "--no-progress"]
    assert main([*arguments, "--no-evaluate", "--env", "max_steps=20", "--run-dir", str(run)]) == 0
    assert not load_policy(run).policy.log_std.requires_grad
    folder = export_pretrained(run, "fixed", root=tmp_path / "shipped")
    assert pretrained_card("fixed", folder.parent)["recipe"] == "ch4-individual"


def test_the_listing_shows_a_policy_that_never_succeeded(tiny_run: Path, tmp_path: Path, capsys) -> None:
    export_pretrained(tiny_run, "tiny", root=tmp_path)
    summary = pretrained_card("tiny", tmp_path)["summary"]
    assert summary["success_rate"] == 0 and summary["successful_episodes"]["length"]["mean"] is None
    assert main(["pretrained", "--into", str(tmp_path)]) == 0
    assert "| pretrained:tiny | tiny | 6 | stage 3 | 0.0% (0.0%-56.1%) | - | - | " in capsys.readouterr().out


@pytest.fixture(scope="module")
def exported(tiny_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``tiny_run`` exported as a shipped policy ``tiny`` (its folder)."""
    return export_pretrained(tiny_run, "tiny", root=tmp_path_factory.mktemp("shipped"))


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        ({"card": lambda card: {key: value for key, value in card.items() if key != "recipe"}}, "records no 'recipe'"),
        ({"card": lambda card: card | {"training_seconds": "12 min"}}, "'training_seconds' must be a number of seconds"),
        ({"card": lambda card: card | {"team_sizes": ["six"]}}, "'team_sizes' must be a list of integers"),
        ({"card": lambda card: ["not", "a", "card"]}, "it must hold a JSON object"),
        ({"summary": lambda summary: summary | {"success_rate": "96%"}}, "success_rate must be a number in [0, 1]"),
        ({"summary": lambda summary: summary | {"scenes": "moon"}}, "scenes must be one of"),
        ({"summary": lambda summary: summary | {"all_episodes": {}}}, "all_episodes must be a mapping of the metrics"),
        ({"text": '{"recipe": "ch5-bearing", "n_agents": 6,'}, "is damaged (not JSON"),
    ],
)
def test_a_damaged_card_or_summary_is_named_in_one_line(
    damage: dict, message: str, exported: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``pretrained --into`` a folder whose ``card.json`` lacks a key or whose ``card.json`` / ``eval/summary.json``
    holds values of another kind: one line naming the file (not a KeyError, "unsupported operand type(s) for /" or
    "Unknown format code '%'")."""
    folder = tmp_path / "tiny"
    shutil.copytree(exported, folder)
    card_file, summary_file = folder / CARD_FILE, folder / SUMMARY_PATH
    if "card" in damage:
        card_file.write_text(json.dumps(damage["card"](json.loads(card_file.read_text()))))
    if "summary" in damage:
        summary_file.write_text(json.dumps(damage["summary"](json.loads(summary_file.read_text()))))
    if "text" in damage:
        card_file.write_text(damage["text"])
    capsys.readouterr()
    assert main(["pretrained", "--into", str(tmp_path)]) == 2
    error = capsys.readouterr().err
    named = summary_file if "summary" in damage else card_file
    assert error.count("\n") == 1 and f"{named}" in error and message in error and "Traceback" not in error, error
