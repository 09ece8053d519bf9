"""Loading a model never runs code from the file: model files are read as JSON and tensors, a file that
needs unpickling is refused unless trusted, resuming rebuilds the model from the run's recipe, and a normaliser of
another task is refused."""

from __future__ import annotations

import base64
import csv
import io
import json
import operator
import pathlib
import pickle
import shutil
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.save_util import load_from_zip_file

from sb3_formation import FormationEnv
from sb3_formation.cli import build_parser, main
from sb3_formation.experiment.pretrained import PRETRAINED_DIR, load_pretrained, pretrained_names
from sb3_formation.experiment.recipes import RECIPES_FOLDER
from sb3_formation.experiment.runs import FINAL_MODEL, FINAL_NORMALIZER, latest_checkpoint, load_trained
from sb3_formation.sb3.model_files import class_reference, plain_schedule, schedule_from_text
from sb3_formation.sb3.policies import FormationPolicy


class Touch:
    """Unpickled, it creates the file ``marker``: what a hostile pickle could do instead."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return pathlib.Path.touch, (pathlib.Path(self.marker),)


class Payload:
    """Unpickled, it touches ``marker`` and then is ``value``: a file that loads as before, having run code."""

    def __init__(self, marker: Path, value: Any) -> None:
        self.marker, self.value = marker, value

    def __reduce__(self) -> tuple[Any, ...]:
        return operator.getitem, ((Touch(self.marker), self.value), 1)


def serialized(value: Any, beside: dict[str, Any]) -> dict[str, Any]:
    """An entry of a model file's data as SB3 writes an object it pickles: the pickle, and plain text beside it."""
    return {":type:": str(type(value)), ":serialized:": base64.b64encode(pickle.dumps(value)).decode(), **beside}


def rewrite_member(path: Path, member: str, content: bytes) -> None:
    """Replace a member of the model file at ``path``."""
    with zipfile.ZipFile(path) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    members[member] = content
    with zipfile.ZipFile(path, "w") as archive:
        for name, value in members.items():
            archive.writestr(name, value)


def rewrite_data(path: Path, change: Callable[[dict[str, Any]], None]) -> None:
    """Change the ``data`` JSON of the model file at ``path`` in place."""
    with zipfile.ZipFile(path) as archive:
        data = json.loads(archive.read("data"))
    change(data)
    rewrite_member(path, "data", json.dumps(data).encode())


def hide_in_policy_kwargs(marker: Path) -> Callable[[dict[str, Any]], None]:
    """A change of a model file's data: its policy keyword arguments become a pickle that touches ``marker``."""

    def change(data: dict[str, Any]) -> None:
        data["policy_kwargs"] = serialized(Payload(marker, data["policy_kwargs"]), data["policy_kwargs"])

    return change


def one_line(text: str) -> str:
    assert len(text.strip().splitlines()) == 1, text
    return text


def tiny_run(folder: Path, policy: dict[str, Any]) -> Path:
    """A finished tiny run (3 iterations, a checkpoint after each) with a linear learning rate, in ``folder``."""
    values = yaml.safe_load((RECIPES_FOLDER / "ch4-individual.yaml").read_text())
    values["policy"] |= policy
    values["ppo"] |= {"n_steps": 16, "batch_size": 48, "n_epochs": 2, "learning_rate": {"start": 1e-3, "end": 1e-4}}
    values["n_envs"], values["curriculum"]["iterations"] = 2, [1, 1, 1]
    values["evaluation"] = {"episodes": 2, "stage": 3}
    (folder / "tiny.yaml").write_text(yaml.safe_dump(values))
    arguments = ["train", "--recipe", str(folder / "tiny.yaml"), "--env", "max_steps=20", "--checkpoint-every", "1"]
    assert main([*arguments, "--no-evaluate", "--no-progress", "--run-dir", str(folder / "run")]) == 0
    return folder / "run"


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny run of the MLP policy."""
    return tiny_run(tmp_path_factory.mktemp("safe"), {"net_arch": {"pi": [16], "vf": [16]}})


@pytest.fixture(scope="module")
def recurrent_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny run of the recurrent policy."""
    widths = {"pi": [8], "vf": [8], "pi_recurrent": 8, "vf_recurrent": 8, "pi_after": [], "vf_after": []}
    return tiny_run(tmp_path_factory.mktemp("recurrent"), {"recurrent": True, "net_arch": widths})


def model_copy(run: Path, folder: Path) -> Path:
    """The run's final model and normaliser copied into ``folder``; the model's path."""
    folder.mkdir()
    for name in (FINAL_MODEL, FINAL_NORMALIZER):
        shutil.copyfile(run / name, folder / name)
    return folder / FINAL_MODEL


def test_a_model_that_needs_unpickling_is_refused_unless_trusted(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    marker = tmp_path / "ran"
    model = model_copy(run, tmp_path / "copy")
    rewrite_data(model, hide_in_policy_kwargs(marker))
    with pytest.raises(ValueError, match="needs unpickling") as refused:
        load_trained(model)
    assert str(model) in one_line(str(refused.value)) and "policy_kwargs" in str(refused.value)
    arguments = ["evaluate", str(model), "--episodes", "1", "--n-envs", "1", "--no-progress"]
    assert main(arguments) == 2
    error = one_line(capsys.readouterr().err)
    assert error.startswith(f"sb3-formation: error: {model} needs unpickling") and "--trust-pickle" in error
    assert not marker.exists()
    assert main([*arguments, "--trust-pickle"]) == 0  # the user vouches for the file: SB3's load runs its pickles
    assert marker.exists() and f"trusting {model}: unpickling policy_class, " in capsys.readouterr().err
    marker.unlink()
    assert load_trained(model, trusted=True).config.n_agents == 3 and marker.exists()


@pytest.mark.parametrize(
    "command",
    [["evaluate", "--episodes", "1"], ["render", "--max-steps", "2"], ["compare", "--episodes", "1"], ["rollout"]],
)
def test_every_command_that_loads_a_model_refuses_it_unless_told(
    command: list[str], run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    marker = tmp_path / "ran"
    model = model_copy(run, tmp_path / "copy")
    rewrite_data(model, hide_in_policy_kwargs(marker))
    assert main([command[0], str(model), *command[1:]]) == 2
    assert "needs unpickling" in one_line(capsys.readouterr().err) and not marker.exists()
    arguments = build_parser().parse_args([command[0], str(model), *command[1:], "--trust-pickle"])
    assert arguments.trust_pickle is True


def test_pickles_of_what_safe_loading_does_not_need_are_never_run(run: Path, tmp_path: Path) -> None:
    """The tester's file: a pickle anywhere in ``data`` ran on loading; now only plain values are read."""
    marker = tmp_path / "ran"
    model = model_copy(run, tmp_path / "copy")

    def change(data: dict[str, Any]) -> None:  # the pickles replaced, the text beside them kept
        for name in ("learning_rate", "observation_space", "ep_info_buffer", "lr_schedule", "clip_range"):
            data[name][":serialized:"] = serialized(Payload(marker, None), {})[":serialized:"]

    rewrite_data(model, change)
    loaded, reference = load_trained(model), load_trained(run)
    assert not marker.exists()
    assert loaded.model.learning_rate(0.5) == reference.model.learning_rate(0.5) == pytest.approx(5.5e-4)
    rows = np.random.default_rng(0).uniform(-1.0, 1.0, (6, loaded.model.observation_space.shape[0]))
    assert np.array_equal(loaded.predict(rows)[0], reference.predict(rows)[0])


def test_tensors_are_read_as_weights_only(run: Path, tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    model = model_copy(run, tmp_path / "copy")
    stream = io.BytesIO()
    torch.save({"log_std": Payload(marker, torch.zeros(2))}, stream)
    rewrite_member(model, "policy.pth", stream.getvalue())
    with pytest.raises(ValueError, match="holds tensors that cannot be read as weights only") as refused:
        load_trained(model)
    assert str(model) in one_line(str(refused.value)) and not marker.exists()


def test_only_this_packages_policy_classes_are_read_without_trust(run: Path, tmp_path: Path) -> None:
    model = model_copy(run, tmp_path / "copy")

    def change(data: dict[str, Any]) -> None:
        data["policy_class"] = serialized(ActorCriticPolicy, {"__module__": ActorCriticPolicy.__module__})

    rewrite_data(model, change)
    with pytest.raises(ValueError, match=r"policy_class \(stable_baselines3.common.policies.ActorCriticPolicy; allowed"):
        load_trained(model)
    reference = base64.b64encode(pickle.dumps(FormationPolicy)).decode()
    assert class_reference(reference) == "sb3_formation.sb3.policies.FormationPolicy"
    assert class_reference(base64.b64encode(pickle.dumps(Touch(tmp_path / "x"))).decode()) is None  # calls something


def test_schedules_are_read_from_plain_text_only() -> None:
    text = "FloatSchedule(LinearSchedule(start=0.001, end=0.0001, end_fraction=1.0))"
    assert schedule_from_text(text)(0.5) == pytest.approx(5.5e-4)
    assert plain_schedule({":type:": "<class 'x.ConstantSchedule'>", ":serialized:": "", "val": 0.2})(0.3) == 0.2
    hostile_texts = ["__import__('os').system('true')", "LinearSchedule(start=open('f'), end=1, end_fraction=1)"]
    for hostile in [*hostile_texts, "FloatSchedule(" * 100_000 + ")" * 100_000]:
        assert schedule_from_text(hostile) is None


def test_resuming_never_unpickles_the_checkpoint(run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    marker = tmp_path / "ran"
    copy = shutil.copytree(run, tmp_path / "run")
    for name in (FINAL_MODEL, FINAL_NORMALIZER):
        (copy / name).unlink()
    rewrite_data(latest_checkpoint(copy) / "model.zip", hide_in_policy_kwargs(marker))
    files = {path: path.read_bytes() for path in copy.rglob("*") if path.is_file()}
    assert main(["train", "--resume", str(copy)]) == 2
    error = one_line(capsys.readouterr().err)
    assert f"{latest_checkpoint(copy) / 'model.zip'} needs unpickling" in error
    assert not marker.exists() and {path: path.read_bytes() for path in copy.rglob("*") if path.is_file()} == files
    assert main(["train", "--resume", str(copy), "--trust-pickle"]) == 0
    assert marker.exists() and (copy / FINAL_MODEL).is_file()


def progress_rows(run_dir: Path) -> list[dict[str, str]]:
    """The logged values of a resumed session but its wall-clock times."""
    with open(next((run_dir / "tensorboard").glob("progress_from_iteration_*.csv"))) as stream:
        return [{key: value for key, value in row.items() if not key.startswith("time/")} for row in csv.DictReader(stream)]


def same(first: Any, second: Any) -> bool:
    """Whether two state dicts (nested mappings and lists of tensors and numbers) are equal, bit for bit."""
    if isinstance(first, dict):
        return isinstance(second, dict) and sorted(first) == sorted(second) and all(same(first[k], second[k]) for k in first)
    if isinstance(first, (list, tuple)):
        return len(first) == len(second) and all(same(a, b) for a, b in zip(first, second))
    return torch.equal(first, second) if isinstance(first, torch.Tensor) else first == second


@pytest.mark.parametrize("kind", ["run", "recurrent_run"])
def test_a_safe_resume_continues_exactly_as_sb3s_load(kind: str, request: pytest.FixtureRequest, tmp_path: Path) -> None:
    """The model rebuilt from the recipe with the checkpoint's tensors and counters trains on bit for bit as the
    model SB3's ``load`` gave (``--trust-pickle``), logging the same values (episode windows included); a checkpoint
    of an earlier version, without the plain episode windows, continues the same model."""
    start = shutil.copytree(request.getfixturevalue(kind), tmp_path / "start")
    for name in (FINAL_MODEL, FINAL_NORMALIZER):
        (start / name).unlink()
    shutil.rmtree(latest_checkpoint(start))
    safe, trusted, old = (shutil.copytree(start, tmp_path / name) for name in ("safe", "trusted", "old"))
    rewrite_data(latest_checkpoint(old) / "model.zip", lambda data: data.pop("episode_windows"))
    for folder in (safe, old):
        assert main(["train", "--resume", str(folder)]) == 0
    assert main(["train", "--resume", str(trusted), "--trust-pickle"]) == 0
    ours, theirs, older = (load_from_zip_file(folder / FINAL_MODEL)[1] for folder in (safe, trusted, old))
    assert same(ours, theirs) and same(older["policy"], theirs["policy"])
    assert progress_rows(safe) == progress_rows(trusted) and progress_rows(safe)[0]["rollout/ep_rew_mean"]


def test_a_normaliser_of_another_task_is_refused(run: Path, tmp_path: Path) -> None:
    model = model_copy(run, tmp_path / "copy")
    shutil.copyfile(PRETRAINED_DIR / "mixed-ch5-bearing" / FINAL_NORMALIZER, model.with_name(FINAL_NORMALIZER))
    with pytest.raises(ValueError, match="is not the normaliser of") as refused:
        load_trained(model)
    assert "215 features, the task's have 211" in one_line(str(refused.value))


@pytest.mark.parametrize("name", pretrained_names())
def test_shipped_policies_load_safely_and_act_as_sb3s_load(name: str) -> None:
    safe, trusted = load_pretrained(name), load_pretrained(name, trusted=True)  # residual: a controller and a model
    acting = safe
    safe, trusted = (getattr(policy, "correction", policy) for policy in (safe, trusted))
    ours, theirs = safe.policy.state_dict(), trusted.policy.state_dict()
    assert sorted(ours) == sorted(theirs) and all(torch.equal(ours[key], theirs[key]) for key in ours)
    assert type(safe.model) is type(trusted.model) and safe.model.num_timesteps == trusted.model.num_timesteps
    assert safe.model.observation_space.shape == trusted.model.observation_space.shape
    assert str(safe.model.clip_range) == str(trusted.model.clip_range)
    assert safe.model.learning_rate(0.3) == trusted.model.learning_rate(0.3)
    env = FormationEnv(safe.config.replace(stage=3))
    observations, _ = env.reset(seed=0)
    rows = np.stack([observations[agent] for agent in env.possible_agents])
    assert np.array_equal(safe.predict(rows)[0], trusted.predict(rows)[0]) and np.isfinite(acting.predict(rows)[0]).all()
