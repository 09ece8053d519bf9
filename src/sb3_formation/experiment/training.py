"""Training runs: thesis PPO settings, run folders, atomic checkpoints, resuming, and loading trained models.

A run folder ``runs/<preset>_<n>a_s<seed>_<timestamp>/`` holds ``config.yaml`` (the resolved settings),
``command.txt``, ``tensorboard/`` (events), ``checkpoints/iteration_<k>/`` (``model.zip``, ``normalizer.npz``,
``state.json``) and, at the end, ``final_model.zip`` with ``final_normalizer.npz``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import sys
import time
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.logger import CSVOutputFormat, Logger, TensorBoardOutputFormat
from stable_baselines3.common.save_util import json_to_data

from sb3_formation.env.config import PRESETS, FormationConfig
from sb3_formation.sb3.callbacks import (
    THESIS_STAGE_ITERATIONS,
    CurriculumCallback,
    FormationMetricsCallback,
    ProgressBarCallback,
)
from sb3_formation.sb3.normalization import ScaleNormalizeVecEnv
from sb3_formation.sb3.policies import FormationPolicy
from sb3_formation.sb3.recurrent import CELLS, RecurrentFormationPolicy, RecurrentFormationPPO
from sb3_formation.sb3.vec_env import THESIS_TEAMS, FormationVecEnv
from sb3_formation.utils.files import atomic_directory, atomic_path, atomic_write

#: The thesis's PPO settings (thesis 4.3 and 5.3; design.md "Policy and PPO"). SB3 stops an epoch loop early when the
#: approximate KL divergence exceeds 1.5 x target_kl (RLlib, the thesis's tool, stopped at target_kl itself).
THESIS_PPO: dict[str, Any] = {
    "n_steps": 128,  # soft horizon H_s
    "batch_size": 512,  # mini-batch size
    "n_epochs": 10,
    "learning_rate": 5e-5,
    "gamma": 0.995,
    "gae_lambda": 0.95,
    "clip_range": 0.2,  # epsilon_p
    "clip_range_vf": 20.0,  # epsilon_v
    "target_kl": 0.03,
}

MODEL_FILE, NORMALIZER_FILE, STATE_FILE = "model.zip", "normalizer.npz", "state.json"
FINAL_MODEL, FINAL_NORMALIZER = "final_model.zip", "final_normalizer.npz"


def thesis_ppo_kwargs(preset: str, n_agents: int | None = None, recurrent: bool = False, cell: str = "gru") -> dict[str, Any]:
    """Keyword arguments of ``PPO`` (or, with ``recurrent``, :class:`RecurrentFormationPPO`) for a thesis preset.

    The policy is :class:`FormationPolicy` (or :class:`RecurrentFormationPolicy`, thesis figs 5.1 and 5.2) with sigma
    0.7, the actor output scaled by 0.01 for ``ch4-individual`` (thesis 4.1.2) and the team critic of fig. 4.3 for
    presets with the team reward (MLP only).

    :param preset: a thesis preset name
    :param n_agents: team size (default: the preset's); the team critic needs it
    :param recurrent: the recurrent actor and critic of chapter 5
    :param cell: recurrent cell, ``"gru"`` or ``"lstm"``
    """
    config = FormationConfig.preset(preset, **({} if n_agents is None else {"n_agents": n_agents}))
    policy_kwargs: dict[str, Any] = {"sigma": 0.7, "action_scale": 0.01 if preset == "ch4-individual" else 1.0}
    if recurrent:
        if config.team_reward:
            raise ValueError(f"{preset} uses the team critic, which has no recurrent version: train it without recurrent")
        if cell not in CELLS:
            raise ValueError(f"cell must be one of {CELLS}, got {cell!r}")
        return {"policy": RecurrentFormationPolicy, **THESIS_PPO, "policy_kwargs": {**policy_kwargs, "cell": cell}}
    if config.team_reward:
        policy_kwargs["team_size"] = config.n_agents
    return {"policy": FormationPolicy, **THESIS_PPO, "policy_kwargs": policy_kwargs}


def saved_algorithm(path: Path) -> type[PPO]:
    """The PPO class of a saved model, from the policy class recorded in its zip file."""
    try:
        with zipfile.ZipFile(path) as archive:
            data = json_to_data(archive.read("data").decode())
    except (zipfile.BadZipFile, KeyError, ValueError) as error:
        raise ValueError(f"{path} is not a model saved by Stable-Baselines3: {error}") from error
    if not isinstance(data.get("policy_class"), type):
        raise ValueError(f"{path} is not a model saved by Stable-Baselines3: it names no policy class")
    return algorithm_for(data["policy_class"])


def algorithm_for(policy: type) -> type[PPO]:
    """The PPO class that trains ``policy``: :class:`RecurrentFormationPPO` for a recurrent policy, else SB3's ``PPO``."""
    return RecurrentFormationPPO if issubclass(policy, RecurrentFormationPolicy) else PPO


@dataclass
class TrainSettings:
    """Everything a training run needs; the ``sb3-formation train`` options and the keys of its YAML file.

    :param preset: thesis preset name
    :param iterations: PPO iterations of curriculum stages 1, 2, 3 (default: the thesis's for the preset's chapter)
    :param n_envs: parallel teams (default: the thesis's, 12 or 14)
    :param workers: worker processes stepping the teams
    :param seed: seed of PPO and of the teams' scenario generators
    :param device: torch device for PPO (``"auto"``, ``"cpu"``, ``"cuda"``)
    :param logdir: folder in which run folders are made
    :param checkpoint_every: write a checkpoint every this many iterations
    :param success_threshold: end curriculum stages 1-2 early at this rolling success rate (``None``: never)
    :param progress_bar: show a progress bar
    :param seeds: the seeds of an experiment (``sb3-formation sweep`` trains one run per seed; ``train`` uses ``seed``)
    :param evaluation: evaluate the final model with these :func:`~sb3_formation.evaluation.evaluate` settings
        (``episodes``, ``stage``, ``seed``, ``n_envs``, ``workers``, ``deterministic``, ``record``) into ``eval/``
    :param recurrent: recurrent actor and critic (default: as in the thesis, for chapter-5 presets only)
    :param cell: recurrent cell, ``"gru"`` (the default) or ``"lstm"``; only for recurrent policies
    :param env: :class:`FormationConfig` fields overriding the preset's (e.g. ``n_agents``)
    :param ppo: ``PPO`` keyword arguments overriding the thesis's (e.g. ``learning_rate``)
    """

    preset: str = "ch5-bearing"
    iterations: tuple[int, int, int] | None = None
    n_envs: int | None = None
    workers: int = 1
    seed: int = 0
    device: str = "auto"
    logdir: str = "runs"
    checkpoint_every: int = 50
    success_threshold: float | None = None
    progress_bar: bool = True
    seeds: list[int] | None = None
    evaluation: dict[str, Any] | None = None
    recurrent: bool | None = None
    cell: str | None = None
    env: dict[str, Any] = field(default_factory=dict)
    ppo: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; valid presets: {sorted(PRESETS)}")
        self.config()  # validates the env overrides
        if self.iterations is not None:
            self.iterations = tuple(int(value) for value in self.iterations)
            if len(self.iterations) != 3 or min(self.iterations) < 0 or sum(self.iterations) < 1:
                raise ValueError(f"iterations must be three integers >= 0 (stages 1, 2, 3), got {self.iterations!r}")
        for name in ("workers", "checkpoint_every") + (("n_envs",) if self.n_envs is not None else ()):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        unknown = sorted(set(self.ppo) - PPO_OVERRIDABLE)
        if unknown:
            raise ValueError(f"unknown ppo setting(s) {unknown}; valid: {sorted(PPO_OVERRIDABLE)}")
        if self.seeds is not None:
            self.seeds = list(self.seeds)
            if not self.seeds or not all(isinstance(seed, int) and not isinstance(seed, bool) for seed in self.seeds):
                raise ValueError(f"seeds must be a non-empty list of integers, got {self.seeds!r}")
        if self.evaluation is not None:
            unknown = sorted(set(self.evaluation) - EVALUATION_KEYS) if isinstance(self.evaluation, dict) else None
            if unknown is None or unknown:
                raise ValueError(f"evaluation must map some of {sorted(EVALUATION_KEYS)} to values, got {self.evaluation!r}")
        if self.recurrent not in (None, True, False):
            raise ValueError(f"recurrent must be true, false or null (the preset's default), got {self.recurrent!r}")
        self.ppo_kwargs()  # validates recurrent, cell and the policy
        if self.cell is not None and not self.resolved_recurrent():
            raise ValueError(f"cell {self.cell!r} applies to recurrent policies only; this run's policy is an MLP")
        if "max_sequence_length" in self.ppo and not self.resolved_recurrent():
            raise ValueError("ppo: max_sequence_length applies to recurrent policies only; this run's policy is an MLP")

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """Names of the settings (the valid top-level keys of a YAML file)."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TrainSettings:
        """Settings from a mapping (e.g. a YAML file); unknown keys are errors that list the valid ones."""
        unknown = sorted(set(values) - set(cls.field_names()))
        if unknown:
            raise ValueError(f"unknown setting(s) {unknown}; valid: {list(cls.field_names())}")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """Every setting resolved (thesis defaults filled in, every env field and PPO setting) as plain YAML data."""
        values = dataclasses.asdict(self)
        values["iterations"] = list(self.resolved_iterations())
        values["n_envs"] = self.resolved_n_envs()
        values["recurrent"] = self.resolved_recurrent()
        values["cell"] = (self.cell or "gru") if values["recurrent"] else None
        values["env"] = _plain(dataclasses.asdict(self.config()))
        values["ppo"] = _plain({name: value for name, value in self.ppo_kwargs().items() if name != "policy"})
        values["ppo"]["policy_kwargs"].pop("cell", None)  # written once, as the top-level cell
        return values

    def config(self) -> FormationConfig:
        """The task configuration of this run."""
        return FormationConfig.preset(self.preset, **self.env)

    def resolved_iterations(self) -> tuple[int, int, int]:
        """Iterations per stage, the thesis's unless given."""
        return self.iterations if self.iterations is not None else THESIS_STAGE_ITERATIONS[self.config().layout]

    def resolved_n_envs(self) -> int:
        """Number of teams, the thesis's unless given."""
        return self.n_envs if self.n_envs is not None else THESIS_TEAMS[self.config().layout]

    def resolved_recurrent(self) -> bool:
        """Whether the policy is recurrent: as given, else the thesis's choice (chapter 5 only)."""
        return self.recurrent if self.recurrent is not None else self.config().layout == "ch5"

    def ppo_kwargs(self) -> dict[str, Any]:
        """``PPO`` keyword arguments: the thesis's for the preset, then the overrides."""
        kwargs = thesis_ppo_kwargs(self.preset, self.config().n_agents, self.resolved_recurrent(), self.cell or "gru")
        overrides = dict(self.ppo)
        kwargs["policy_kwargs"] = {**kwargs["policy_kwargs"], **overrides.pop("policy_kwargs", {})}
        kwargs.update(overrides)
        return kwargs


def _plain(value: Any) -> Any:
    """Tuples to lists, recursively, so that YAML writes plain lists."""
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return value


def reduce_to_overrides(values: dict[str, Any]) -> dict[str, Any]:
    """A settings mapping whose ``env:`` and ``ppo:`` keep only what differs from its own preset's defaults.

    A run's ``config.yaml`` holds every resolved value; reduced, it can be reused with another preset or team size
    (``--config old/config.yaml --reward bearing``) without pinning the old preset's coefficients.
    """
    preset = values.get("preset", TrainSettings.preset)
    if preset not in PRESETS:
        return values  # reported by TrainSettings
    env = dict(values.get("env") or {})
    defaults = _plain(dataclasses.asdict(FormationConfig.preset(preset)))
    env = {name: value for name, value in env.items() if name not in defaults or defaults[name] != _plain(value)}
    n_agents = env.get("n_agents", defaults["n_agents"])
    ppo = dict(values.get("ppo") or {})
    recurrent = values.get("recurrent")
    if recurrent is None:
        recurrent = FormationConfig.preset(preset).layout == "ch5"
    try:
        thesis_kwargs = thesis_ppo_kwargs(preset, n_agents, bool(recurrent), values.get("cell") or "gru")
    except ValueError:
        return values  # reported by TrainSettings
    thesis = _plain({name: value for name, value in thesis_kwargs.items() if name != "policy"})
    policy_kwargs = {
        name: value
        for name, value in (ppo.pop("policy_kwargs", None) or {}).items()
        if thesis["policy_kwargs"].get(name) != _plain(value)
    }
    ppo = {name: value for name, value in ppo.items() if name not in thesis or thesis[name] != _plain(value)}
    if policy_kwargs:
        ppo["policy_kwargs"] = policy_kwargs
    return {**values, "env": env, "ppo": ppo}


#: Keys of a run's ``evaluation:`` settings (arguments of :func:`~sb3_formation.evaluation.evaluate`).
EVALUATION_KEYS = frozenset({"episodes", "stage", "seed", "n_envs", "workers", "deterministic", "record"})

#: PPO settings a run may override (``ppo:`` in YAML).
PPO_OVERRIDABLE = frozenset(
    set(THESIS_PPO) | {"ent_coef", "vf_coef", "max_grad_norm", "normalize_advantage", "policy_kwargs", "max_sequence_length"}
)


# Atomic files and checkpoints ----------------------------------------------------------------------------------------


def save_model(model: PPO, normalizer: ScaleNormalizeVecEnv, folder: Path, model_file: str, normalizer_file: str) -> None:
    """Save a model and its normaliser statistics into ``folder``, each through a temporary file and a rename."""
    with atomic_path(folder / model_file) as temporary:
        model.save(temporary)
    normalizer.save(folder / normalizer_file)


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The most advanced complete checkpoint of a run, or ``None``."""
    folders = sorted((run_dir / "checkpoints").glob("iteration_*"), key=lambda path: int(path.name.split("_")[1]))
    complete = [folder for folder in folders if (folder / STATE_FILE).exists()]
    return complete[-1] if complete else None


class CheckpointCallback(BaseCallback):
    """Write a checkpoint every ``every`` iterations, and stop training cleanly when a stop is requested.

    A checkpoint is a folder ``checkpoints/iteration_<k>`` written atomically (see :func:`atomic_directory`) after the
    k-th PPO update, holding the model (with its optimiser state), the normaliser statistics and ``state.json``
    (curriculum state and timestep count). Only the ``keep`` most recent are kept. When a stop is requested the
    rollout under way is dropped: the checkpoint holds the state after the last completed iteration.

    :param run_dir: the run folder
    :param curriculum: the run's curriculum callback (its state goes into each checkpoint)
    :param every: iterations between checkpoints
    :param keep: checkpoints kept on disk
    """

    def __init__(self, run_dir: Path, curriculum: CurriculumCallback, every: int, keep: int = 3) -> None:
        super().__init__()
        self.run_dir = run_dir
        self.curriculum = curriculum
        self.every = every
        self.keep = keep
        self.stop_requested = False

    def _on_step(self) -> bool:
        return not self.stop_requested

    def _on_rollout_start(self) -> None:
        # a rollout starts after the previous iteration's update (SB3 calls train() after the rollout-end callbacks)
        iteration = self.curriculum.iteration
        if iteration > 0 and iteration % self.every == 0:
            self.save()

    def save(self) -> Path:
        """Write a checkpoint of the state after the last completed iteration and return its folder."""
        iteration = self.curriculum.iteration
        self.model.num_timesteps = iteration * self.model.n_steps * self.model.get_env().num_envs  # drop a partial rollout
        target = self.run_dir / "checkpoints" / f"iteration_{iteration:06d}"
        with atomic_directory(target) as folder:
            save_model(self.model, self.model.get_env(), folder, MODEL_FILE, NORMALIZER_FILE)
            state = {"num_timesteps": self.model.num_timesteps, "curriculum": self.curriculum.state_dict()}
            (folder / STATE_FILE).write_text(json.dumps(state, indent=2))
        for old in sorted((self.run_dir / "checkpoints").glob("iteration_*"))[: -self.keep]:
            shutil.rmtree(old, ignore_errors=True)
        return target


@contextmanager
def stop_on_signals(checkpoint: CheckpointCallback) -> Iterator[None]:
    """While active, SIGINT (Ctrl-C) and SIGTERM ask training to stop after the current step (then it checkpoints)."""

    def request_stop(signum: int, frame: Any) -> None:
        checkpoint.stop_requested = True

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


# Runs ---------------------------------------------------------------------------------------------------------------


def make_training_env(settings: TrainSettings, stage: int, normalizer_path: Path | None = None) -> ScaleNormalizeVecEnv:
    """The normalised VecEnv of a run, its teams placed for ``stage`` (with saved normaliser statistics to resume)."""
    config = settings.config().replace(stage=stage)
    venv = FormationVecEnv(
        config,
        n_envs=settings.resolved_n_envs(),
        team_observations=config.team_reward,
        n_workers=settings.workers,
    )
    if normalizer_path is None:
        return ScaleNormalizeVecEnv(venv, venv.agent_observation_dim, venv.binary_observation_mask)
    dim, mask = venv.agent_observation_dim, venv.binary_observation_mask
    return ScaleNormalizeVecEnv.load(normalizer_path, venv, training=True, agent_obs_dim=dim, binary_mask=mask)


def new_run_dir(settings: TrainSettings) -> Path:
    """A fresh folder ``<logdir>/<preset>_<n>a_s<seed>_<timestamp>`` (``-2``, ``-3``, ... if taken)."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    base = Path(settings.logdir) / f"{settings.preset}_{settings.config().n_agents}a_s{settings.seed}_{stamp}"
    base.parent.mkdir(parents=True, exist_ok=True)
    for suffix in range(1, 1000):
        run_dir = base if suffix == 1 else base.with_name(f"{base.name}-{suffix}")
        try:
            run_dir.mkdir()
        except FileExistsError:
            continue
        return run_dir
    raise FileExistsError(f"no free run folder name next to {base}")


def train(settings: TrainSettings, command: str | None = None, run_dir: str | os.PathLike[str] | None = None) -> Path:
    """Run the whole curriculum of ``settings`` in a new run folder and return the folder.

    :param settings: the run's settings
    :param command: the command line to record in ``command.txt`` (default: this process's)
    :param run_dir: the run folder (created if needed; default: a new ``<logdir>/<preset>_<n>a_s<seed>_<time>``)
    """
    if run_dir is None:
        run_dir = new_run_dir(settings)
    else:
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write(run_dir / "config.yaml", yaml.safe_dump(settings.to_dict(), sort_keys=False))
    atomic_write(run_dir / "command.txt", (command or " ".join(sys.argv)) + "\n")
    curriculum = CurriculumCallback(settings.resolved_iterations(), settings.success_threshold)
    env = make_training_env(settings, curriculum.stage)
    kwargs = settings.ppo_kwargs()
    model = algorithm_for(kwargs["policy"])(env=env, seed=settings.seed, device=settings.device, verbose=0, **kwargs)
    model.formation_config = dataclasses.asdict(settings.config())
    _learn(model, settings, run_dir, curriculum)
    return run_dir


def resume(run_dir: str | os.PathLike[str]) -> Path:
    """Continue a run from its latest checkpoint: same curriculum stage, timestep count, normaliser and optimiser.

    The random generators are re-seeded from the run's seed and the checkpoint's iteration, so resuming the same
    checkpoint twice gives the same continuation.
    """
    run_dir = Path(run_dir)
    settings = load_settings(run_dir)
    checkpoint = latest_checkpoint(run_dir)
    if checkpoint is None:
        raise FileNotFoundError(f"{run_dir} has no complete checkpoint under checkpoints/ to resume from")
    for leftover in (run_dir / "checkpoints").glob(".iteration_*"):  # folders of a write that was killed
        shutil.rmtree(leftover, ignore_errors=True)
    state = json.loads((checkpoint / STATE_FILE).read_text())
    curriculum = CurriculumCallback(settings.resolved_iterations(), settings.success_threshold)
    curriculum.load_state_dict(state["curriculum"])
    env = make_training_env(settings, curriculum.stage, checkpoint / NORMALIZER_FILE)
    model = saved_algorithm(checkpoint / MODEL_FILE).load(checkpoint / MODEL_FILE, env=env, device=settings.device)
    model.set_random_seed(int(np.random.SeedSequence([settings.seed, curriculum.iteration]).generate_state(1)[0]))
    _learn(model, settings, run_dir, curriculum)
    return run_dir


def load_settings(run_dir: Path) -> TrainSettings:
    """The settings a run folder was made with."""
    path = run_dir / "config.yaml"
    if not path.exists():
        raise FileNotFoundError(f"{run_dir} is not a run folder: {path} is missing")
    return TrainSettings.from_dict(yaml.safe_load(path.read_text()))


def _learn(model: PPO, settings: TrainSettings, run_dir: Path, curriculum: CurriculumCallback) -> None:
    folder = run_dir / "tensorboard"
    folder.mkdir(exist_ok=True)
    # one CSV per session (SB3's CSV writer truncates its file); TensorBoard appends events to the same folder
    csv_name = "progress.csv" if curriculum.iteration == 0 else f"progress_from_iteration_{curriculum.iteration}.csv"
    model.set_logger(Logger(str(folder), [TensorBoardOutputFormat(str(folder)), CSVOutputFormat(str(folder / csv_name))]))
    checkpoint = CheckpointCallback(run_dir, curriculum, settings.checkpoint_every)
    callbacks: list[BaseCallback] = [curriculum, FormationMetricsCallback(settings.to_dict()), checkpoint]
    remaining = curriculum.total_iterations - curriculum.iteration
    if settings.progress_bar:
        callbacks.append(ProgressBarCallback(curriculum.total_iterations, curriculum, curriculum.iteration))
    steps_per_iteration = model.n_steps * model.get_env().num_envs
    with stop_on_signals(checkpoint):
        if remaining > 0:
            model.learn(
                total_timesteps=remaining * steps_per_iteration,
                callback=CallbackList(callbacks),
                reset_num_timesteps=False,
                progress_bar=False,
            )
        checkpoint.save()
    if checkpoint.stop_requested:
        print(f"stopped by a signal; checkpoint {latest_checkpoint(run_dir)}; continue with --resume {run_dir}")
    else:
        save_model(model, model.get_env(), run_dir, FINAL_MODEL, FINAL_NORMALIZER)
    model.get_env().close()


# Loading trained models -----------------------------------------------------------------------------------------------


@dataclass
class TrainedModel:
    """A trained model with what it needs to act: its task configuration and normaliser statistics."""

    model: PPO
    config: FormationConfig
    normalizer_state: dict[str, np.ndarray]
    team_observations: bool
    source: Path | None = None  #: the model file it was loaded from


def load_trained(path: str | os.PathLike[str], device: str = "auto") -> TrainedModel:
    """Load a run folder (its final model, else its latest checkpoint) or a model ``.zip`` with its normaliser beside.

    :param path: a run folder, or a model file whose normaliser is ``normalizer.npz`` / ``final_normalizer.npz``
        in the same folder
    :param device: torch device
    """
    path = Path(path)
    if path.is_dir():
        if (path / FINAL_MODEL).exists():
            model_path, normalizer_path = path / FINAL_MODEL, path / FINAL_NORMALIZER
        else:
            checkpoint = latest_checkpoint(path)
            if checkpoint is None:
                raise FileNotFoundError(f"{path} holds no {FINAL_MODEL} and no checkpoint")
            model_path, normalizer_path = checkpoint / MODEL_FILE, checkpoint / NORMALIZER_FILE
    elif path.is_file():
        model_path = path
        candidates = [path.with_name(FINAL_NORMALIZER), path.with_name(NORMALIZER_FILE)]
        normalizer_path = next((candidate for candidate in candidates if candidate.exists()), candidates[0])
    else:
        raise FileNotFoundError(f"no model at {path}: give a run folder or a model .zip")
    if not normalizer_path.exists():
        raise FileNotFoundError(f"the normaliser statistics of {model_path} are missing: expected {normalizer_path}")
    model = saved_algorithm(model_path).load(model_path, device=device)
    stored = getattr(model, "formation_config", None)
    if stored is None:
        raise ValueError(f"{model_path} was not saved by sb3-formation: it carries no formation_config")
    config = FormationConfig(**{**stored, "stage_disabled_terms": tuple(tuple(t) for t in stored["stage_disabled_terms"])})
    try:
        with np.load(normalizer_path, allow_pickle=False) as data:
            normalizer_state = {key: data[key] for key in data.files}
    except (zipfile.BadZipFile, ValueError, OSError) as error:
        raise ValueError(f"{normalizer_path} is not a normaliser file: {error}") from error
    team_observations = getattr(model.policy, "team_size", None) is not None
    return TrainedModel(model, config, normalizer_state, team_observations, source=model_path)
