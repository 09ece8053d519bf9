"""Training runs: run folders, atomic checkpoints, resuming, and loading trained models (the settings of a run are in
:mod:`~sb3_formation.experiment.settings`, its recipe in :mod:`~sb3_formation.experiment.setups`).

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
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.logger import CSVOutputFormat, Logger, TensorBoardOutputFormat
from stable_baselines3.common.save_util import json_to_data

from sb3_formation.env.config import FormationConfig
from sb3_formation.experiment.settings import TrainSettings, load_settings
from sb3_formation.sb3.callbacks import CurriculumCallback, FormationMetricsCallback, ProgressBarCallback
from sb3_formation.sb3.normalization import ScaleNormalizeVecEnv
from sb3_formation.sb3.recurrent import RecurrentFormationPolicy, RecurrentFormationPPO
from sb3_formation.sb3.trained import TrainedPolicy
from sb3_formation.sb3.vec_env import FormationVecEnv
from sb3_formation.utils.files import atomic_directory, atomic_path, atomic_write

MODEL_FILE, NORMALIZER_FILE, STATE_FILE = "model.zip", "normalizer.npz", "state.json"
FINAL_MODEL, FINAL_NORMALIZER = "final_model.zip", "final_normalizer.npz"


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


# Models and checkpoints ----------------------------------------------------------------------------------------


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
        team_observations="team_size" in settings.ppo_kwargs()["policy_kwargs"],
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
    curriculum = CurriculumCallback(settings.resolved_iterations(), settings.resolved_success_threshold())
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
    curriculum = CurriculumCallback(settings.resolved_iterations(), settings.resolved_success_threshold())
    curriculum.load_state_dict(state["curriculum"])
    env = make_training_env(settings, curriculum.stage, checkpoint / NORMALIZER_FILE)
    model = saved_algorithm(checkpoint / MODEL_FILE).load(checkpoint / MODEL_FILE, env=env, device=settings.device)
    model.set_random_seed(int(np.random.SeedSequence([settings.seed, curriculum.iteration]).generate_state(1)[0]))
    _learn(model, settings, run_dir, curriculum)
    return run_dir


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


def load_trained(path: str | os.PathLike[str], device: str = "auto") -> TrainedPolicy:
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
    return TrainedPolicy(model, config, normalizer_state, source=model_path)
