"""A training run's settings: its recipe (:class:`~sb3_formation.experiment.recipes.Recipe`, what is trained) and its
run options (:class:`RunOptions`: seed, device, workers, folders, checkpoints, progress), kept apart.

A run writes both into its ``config.yaml``: the complete recipe, and the run options under ``run:``
(:meth:`TrainSettings.to_dict`). The same file format is a recipe file, an experiment (``experiments/*.yaml``) and a
run's record, so ``sb3-formation train --config runs/X/config.yaml --seed 1`` trains the run's recipe again.
:func:`layered_settings` layers them as ``sb3-formation train`` does: a recipe (or a file), then options.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from sb3_formation.experiment.recipes import (
    DEFAULT_RECIPE,
    RUN_KEY,
    Recipe,
    load_recipe,
    read_recipe_file,
    recipe_changes,
)
from sb3_formation.utils.checks import check_path, is_count

#: Largest seed: numpy's and PyTorch's generators take seeds in [0, 2**32 - 1].
MAX_SEED = 2**32 - 1


def check_device(device: Any) -> None:
    """Refuse a torch device this machine does not have (``auto`` takes a GPU if there is one, else the CPU).

    :raises ValueError: not a device name, or a GPU that torch does not see here
    """
    try:
        kind = None if device == "auto" else torch.device(device).type
    except (RuntimeError, TypeError):
        raise ValueError(f"device must be auto, cpu, cuda or cuda:<index>, got {device!r}") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: torch sees no CUDA GPU on this machine; use --device auto or cpu")
    if kind not in (None, "cpu", "cuda"):
        raise ValueError(f"device must be auto, cpu, cuda or cuda:<index>, got {device!r}")


def check_seed(name: str, value: Any) -> None:
    """Refuse a seed that is not an integer in [0, :data:`MAX_SEED`].

    :param name: the setting, for the message
    """
    if not (is_count(value) and value <= MAX_SEED):
        raise ValueError(f"{name} must be an integer in [0, 2**32 - 1], got {value!r}")


@dataclass(frozen=True)
class RunOptions:
    """How one run of a recipe is carried out; none of it changes what the recipe means.

    :param seed: seed of PPO and of the teams' scenario generators
    :param seeds: the seeds of an experiment (``sb3-formation sweep`` trains one run per seed; ``train`` uses ``seed``)
    :param device: torch device for PPO (``"auto"``, ``"cpu"``, ``"cuda"``)
    :param workers: processes stepping the teams, this one included (the others are worker processes)
    :param logdir: folder in which run folders are made
    :param checkpoint_every: write a checkpoint every this many iterations
    :param progress_bar: show a progress bar
    :param evaluate: after training, evaluate the final model on the recipe's evaluation protocol into ``eval/``
    """

    seed: int = 0
    seeds: tuple[int, ...] | None = None
    device: str = "auto"
    workers: int = 1
    logdir: str = "runs"
    checkpoint_every: int = 50
    progress_bar: bool = True
    evaluate: bool = False

    def __post_init__(self) -> None:
        check_seed("seed", self.seed)
        if self.seeds is not None:
            if not (isinstance(self.seeds, (list, tuple)) and self.seeds):
                raise ValueError(f"seeds must be a non-empty list of integers, got {self.seeds!r}")
            for seed in self.seeds:
                check_seed("each of seeds", seed)
            object.__setattr__(self, "seeds", tuple(int(seed) for seed in self.seeds))
        check_device(self.device)
        for name in ("workers", "checkpoint_every"):
            if not (is_count(getattr(self, name)) and getattr(self, name) >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {getattr(self, name)!r}")
        if not isinstance(self.logdir, (str, os.PathLike)):
            raise ValueError(f"logdir must be a folder name, got {self.logdir!r}")
        check_path(self.logdir, "logdir")
        for name in ("progress_bar", "evaluate"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")

    @classmethod
    def from_dict(cls, values: dict[str, Any] | None) -> RunOptions:
        """Run options from a ``run:`` block; unknown keys are errors that list the valid ones."""
        values = values or {}
        names = [item.name for item in dataclasses.fields(cls)]
        if not isinstance(values, dict) or set(values) - set(names):
            unknown = sorted(set(values) - set(names)) if isinstance(values, dict) else values
            raise ValueError(f"run: unknown run option(s) {unknown}; valid: {names}")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """The options as plain YAML data."""
        values = dataclasses.asdict(self)
        values["seeds"] = None if self.seeds is None else list(self.seeds)
        values["logdir"] = str(self.logdir)
        return values

    def replace(self, **changes: Any) -> RunOptions:
        """A copy with ``changes`` applied (validated)."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class TrainSettings:
    """Everything a training run needs: what is trained (``recipe``) and how the run is carried out (``run``).

    :param recipe: the resolved recipe
    :param run: the run options
    """

    recipe: Recipe
    run: RunOptions = RunOptions()

    def __post_init__(self) -> None:
        if self.run.workers > self.recipe.n_envs:
            raise ValueError(f"workers={self.run.workers} exceeds n_envs={self.recipe.n_envs}: a worker steps whole teams")

    @classmethod
    def from_dict(cls, values: dict[str, Any], where: str = "settings") -> TrainSettings:
        """Settings from a recipe mapping with an optional ``run:`` block (its ``base:`` already merged in); a mapping
        in the settings format of earlier releases (``recipe:`` and option keys) is read with a ``FutureWarning``.

        :param values: the mapping
        :param where: what it is (e.g. the file), for messages
        """
        if not isinstance(values, dict):
            raise ValueError(f"{where} must hold a recipe mapping, not {type(values).__name__}")
        if "recipe" in values or "preset" in values:
            return _from_settings_format(values, where)
        return cls(Recipe.from_dict(values.get("name", "recipe"), values), RunOptions.from_dict(values.get(RUN_KEY)))

    def replace_run(self, **options: Any) -> TrainSettings:
        """The same recipe with other run options (fields of :class:`RunOptions`)."""
        return TrainSettings(self.recipe, self.run.replace(**options))

    def to_dict(self) -> dict[str, Any]:
        """The complete recipe (:meth:`Recipe.to_dict`) with the run options under ``run:``: a run's ``config.yaml``."""
        return {**self.recipe.to_dict(), RUN_KEY: self.run.to_dict()}


#: Keys of the settings format of earlier releases that were run options.
_OLD_RUN_KEYS = ("seed", "seeds", "device", "workers", "logdir", "checkpoint_every", "progress_bar")


def _from_settings_format(values: dict[str, Any], where: str) -> TrainSettings:
    """Settings from the format of earlier releases: ``recipe:`` (or ``preset:``) naming a recipe, and top-level keys
    overriding it (a run folder's resolved ``config.yaml``, an old experiment file)."""
    warnings.warn(
        f"{where} is in the settings format of earlier releases (recipe: and options); it is read as that recipe with "
        "changes. Write it as a recipe (base: <recipe> and its sections, run options under run:), as a run's "
        "config.yaml now is",
        FutureWarning,
        stacklevel=3,
    )
    values = dict(values)
    name = values.pop("recipe", values.pop("preset", DEFAULT_RECIPE))
    values.pop("name", None)  # the file's stem (read_recipe_file)
    run = {key: values.pop(key) for key in _OLD_RUN_KEYS if key in values}
    evaluation = values.pop("evaluation", None)
    if evaluation is not None:
        run["evaluate"] = True
        evaluation = {key: value for key, value in evaluation.items() if key != "workers"}
    ppo = dict(values.pop("ppo", None) or {})
    policy = dict(ppo.pop("policy_kwargs", None) or {})
    if policy.pop("team_size", None) is not None:
        policy["team_critic"] = True
    iterations = values.pop("iterations", None)
    if iterations is not None and None in iterations:  # a stage 3 open until a time budget ends: the recipe's counts
        iterations = None
    env = values.pop("env", None) or {}
    agents = env.get("n_agents") if values.get("team_sizes") is None else None  # then: every team of that size
    changes = recipe_changes(env=env, ppo=ppo, iterations=iterations, agents=agents, **values)
    for section, given in (("policy", policy), ("evaluation", evaluation)):
        if given:
            changes[section] = {**changes.get(section, {}), **given}
    return TrainSettings(load_recipe(name).with_changes(changes), RunOptions.from_dict(run))


def read_settings(path: str | os.PathLike[str]) -> TrainSettings:
    """The settings of a YAML file: a recipe file (its ``base:`` chain merged in) with an optional ``run:`` block.

    :raises FileNotFoundError: no such file
    :raises ValueError: not YAML, not a recipe, or invalid run options
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such settings file {path}")
    return TrainSettings.from_dict(read_recipe_file(path), str(path))


def layered_settings(
    config_file: str | os.PathLike[str] | None = None, recipe: str | os.PathLike[str] | None = None, **options: Any
) -> TrainSettings:
    """Settings layered as ``sb3-formation train`` layers them: a recipe (or a settings file), then ``options``.

    :param config_file: a YAML file of settings (a recipe with ``run:`` options: a run's ``config.yaml``, an
        experiment), or ``None``
    :param recipe: a recipe name or file (default: :data:`~sb3_formation.experiment.recipes.DEFAULT_RECIPE`); not with
        ``config_file``
    :param options: run options (fields of :class:`RunOptions`) and recipe changes (arguments of
        :func:`~sb3_formation.experiment.recipes.recipe_changes`: ``env``, ``ppo``, ``agents``, ``iterations``,
        ``n_envs``, ``steps``, ...); ``None`` values are ignored
    :raises ValueError: both a file and a recipe, an unknown option, or invalid values
    """
    if config_file is not None and recipe is not None:
        raise ValueError("give a recipe or a settings file (--config), not both: a settings file holds its recipe")
    if config_file is not None:
        settings = read_settings(config_file)
    else:
        settings = TrainSettings(load_recipe(recipe or DEFAULT_RECIPE), RunOptions())
    run_names = {item.name for item in dataclasses.fields(RunOptions)}
    run = {name: value for name, value in options.items() if name in run_names and value is not None}
    changes = recipe_changes(**{name: value for name, value in options.items() if name not in run_names})
    return TrainSettings(settings.recipe.with_changes(changes), settings.run.replace(**run))


def load_settings(run_dir: str | os.PathLike[str]) -> TrainSettings:
    """The settings a run folder was made with (its ``config.yaml``)."""
    path = Path(run_dir) / "config.yaml"
    if not path.exists():
        raise FileNotFoundError(f"{run_dir} is not a run folder: {path} is missing")
    try:
        return read_settings(path)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path} holds invalid settings: {error}") from None
