"""Run folders and their artefacts: file names, saving a model with its normalisers, finding checkpoints, and loading
a trained model as a :class:`~sb3_formation.sb3.trained.TrainedPolicy`.

A run folder ``runs/<recipe>_<n>a_s<seed>_<timestamp>/`` holds ``config.yaml`` (the resolved settings),
``command.txt``, ``tensorboard/`` (events), ``checkpoints/iteration_<k>/`` (``model.zip``, ``normalizer.npz``, with
reward normalisation ``reward_normalizer.npz``, and ``state.json``), at the end ``final_model.zip`` with
``final_normalizer.npz`` (and ``final_reward_normalizer.npz``), and with periodic evaluation ``best_model.zip`` with
``best_normalizer.npz``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper, VecNormalize, unwrap_vec_wrapper

from sb3_formation.controllers.base import TeamPolicy
from sb3_formation.experiment.recipes import read_safety_gains, residual_policy
from sb3_formation.safety.policy import SafePolicy
from sb3_formation.sb3.model_files import (
    load_model,
    read_model_data,
    record_episode_windows,
    recorded_config,
)
from sb3_formation.sb3.normalization import STATE_KEYS, ScaleNormalizeVecEnv
from sb3_formation.sb3.trained import TrainedPolicy, normalizer_mismatch
from sb3_formation.utils.checks import is_count, is_number
from sb3_formation.utils.files import atomic_path, read_arrays, read_json, restore_directory

MODEL_FILE, NORMALIZER_FILE, STATE_FILE = "model.zip", "normalizer.npz", "state.json"
FINAL_MODEL, FINAL_NORMALIZER = "final_model.zip", "final_normalizer.npz"


BEST_MODEL, BEST_NORMALIZER = "best_model.zip", "best_normalizer.npz"
#: Keys of a reward normaliser's file: the running statistics of the discounted return (SB3's ``VecNormalize.ret_rms``).
REWARD_STATE_KEYS = ("mean", "var", "count")


def reward_normalizer_file(normalizer_file: str) -> str:
    """The reward normaliser's file beside an observation normaliser's (``normalizer.npz`` -> ``reward_normalizer.npz``)."""
    return f"{normalizer_file.removesuffix('normalizer.npz')}reward_normalizer.npz"


def save_model(model: PPO, env: VecEnv, folder: Path, model_file: str, normalizer_file: str) -> None:
    """Save a model and the normalisers of its env into ``folder``, each through a temporary file and a rename.

    :param env: the training env: a :class:`ScaleNormalizeVecEnv`, possibly under SB3's ``VecNormalize`` (reward
        normalisation), whose return statistics then go to :func:`reward_normalizer_file`
    """
    record_episode_windows(model)  # as plain data, for a resume that unpickles nothing
    with atomic_path(folder / model_file) as temporary:
        model.save(temporary)
    cast(ScaleNormalizeVecEnv, unwrap_vec_wrapper(env, ScaleNormalizeVecEnv)).save(folder / normalizer_file)  # see :param env:
    rewards = reward_normalizer(env)
    if rewards is not None:
        statistics = {key: np.asarray(getattr(rewards.ret_rms, key), dtype=np.float64) for key in REWARD_STATE_KEYS}
        with atomic_path(folder / reward_normalizer_file(normalizer_file)) as temporary, open(temporary, "wb") as stream:
            np.savez(stream, **cast("dict[str, Any]", statistics))  # numpy's stubs read the keys as options


def reward_normalizer(env: VecEnv) -> VecNormalize | None:
    """The ``VecNormalize`` that divides ``env``'s rewards, if any (:class:`ScaleNormalizeVecEnv` is a ``VecNormalize``
    for observations only)."""
    while isinstance(env, VecEnvWrapper):
        if isinstance(env, VecNormalize) and env.norm_reward:
            return env
        env = env.venv
    return None


def normalize_rewards(env: VecEnv, gamma: float, path: Path | None = None) -> VecNormalize:
    """SB3's ``VecNormalize`` over ``env``, for rewards only (observations are already scaled), with the return
    statistics saved at ``path`` if given.

    :param gamma: discount of the returns whose running std divides the rewards (PPO's gamma)
    """
    wrapper = VecNormalize(env, norm_obs=False, norm_reward=True, gamma=gamma)
    if path is not None:
        if not path.is_file():
            raise FileNotFoundError(f"the reward normaliser statistics are missing: expected {path}")
        data = read_arrays(path, "a reward normaliser file", REWARD_STATE_KEYS)
        statistics = RunningMeanStd(shape=())
        statistics.mean, statistics.var = (np.asarray(data[key]) for key in REWARD_STATE_KEYS[:2])
        statistics.count = float(data[REWARD_STATE_KEYS[2]])
        wrapper.ret_rms = statistics
    return wrapper


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The most advanced complete checkpoint of a run, or ``None`` (a checkpoint a kill left renamed aside in the
    middle of its replacement is put back first)."""
    for aside in (run_dir / "checkpoints").glob(".iteration_*.old.*"):
        for folder in aside.glob("iteration_*"):
            restore_directory(run_dir / "checkpoints" / folder.name)
    folders = sorted((run_dir / "checkpoints").glob("iteration_*"), key=lambda path: int(path.name.split("_")[1]))
    complete = [folder for folder in folders if (folder / STATE_FILE).exists()]
    return complete[-1] if complete else None


#: What a checkpoint's ``state.json`` records, and of what kind (``recipe`` is compared with ``config.yaml`` on resume).
STATE_KEYS_OF_CHECKPOINT: dict[str, tuple[str, Callable[[Any], bool]]] = {
    "num_timesteps": ("an integer >= 0", is_count),
    "curriculum": (
        "a mapping of stage, iteration, stage_iteration and successes",
        lambda value: (
            isinstance(value, dict)
            and all(is_count(value.get(key)) for key in ("stage", "iteration", "stage_iteration"))
            and isinstance(value.get("successes"), list)
        ),
    ),
    "training_seconds": ("a number of seconds >= 0", lambda value: is_number(value) and value >= 0),
}


def read_state(checkpoint: Path) -> dict[str, Any]:
    """The ``state.json`` of a checkpoint folder (counters, curriculum, training seconds, recipe).

    :raises ValueError: the file is not JSON (a truncated copy, an edit) or lacks an entry, naming the file
    """
    path = checkpoint / STATE_FILE
    state = read_json(path)
    if not isinstance(state, dict):
        raise ValueError(f"{path} is damaged: it must hold a JSON object")
    for key, (expected, valid) in STATE_KEYS_OF_CHECKPOINT.items():
        if (key in state or key != "training_seconds") and not valid(state.get(key)):  # (early runs recorded no time)
            raise ValueError(
                f"{path} is damaged: {key!r} must be {expected}, got {state.get(key)!r:.60}; delete {checkpoint} to "
                "resume from the checkpoint before it"
            )
    return state


def load_trained(path: str | os.PathLike[str], device: str = "auto", trusted: bool | None = None) -> TeamPolicy:
    """Load a run folder (its final model, else its latest checkpoint) or a model ``.zip`` with its normaliser beside,
    as a :class:`TrainedPolicy` (a :class:`~sb3_formation.controllers.residual.ResidualPolicy` around one when the
    model is a correction of a controller; behind the safety filter, :class:`~sb3_formation.safety.policy.SafePolicy`,
    when it was trained behind it).

    :param path: a run folder, or a model file whose normaliser is ``normalizer.npz`` / ``final_normalizer.npz``
        in the same folder
    :param device: torch device
    :param trusted: unpickle what the model file needs (SB3's ``load``, which runs code from the file); by default
        (``None``: unless inside :func:`~sb3_formation.sb3.model_files.trust_pickle`) only plain data and tensors are
        read, and a file that needs more is refused
    :raises ValueError: a file that needs unpickling (untrusted), or a normaliser that does not fit the model
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
    config = recorded_config(model_path, read_model_data(model_path))
    normalizer_state = read_arrays(normalizer_path, "a normaliser file", STATE_KEYS)
    mismatch = normalizer_mismatch(normalizer_state, config)
    if mismatch is not None:
        raise ValueError(f"{normalizer_path} is not the normaliser of {model_path}: {mismatch}")
    model = load_model(model_path, device=device, trusted=trusted)
    team_sizes = tuple(getattr(model, "team_sizes", None) or ())  # files saved before mixed teams: the config's
    trained = TrainedPolicy(model, config, normalizer_state, source=model_path, team_sizes=team_sizes)
    residual = getattr(model, "residual", None)  # a correction of a controller (a recipe's residual)
    # ResidualPolicy's config is a read-only property where TeamPolicy (controllers/base.py) declares a settable attribute
    policy: TeamPolicy = residual_policy(residual, trained) if residual else trained  # type: ignore[assignment]
    gains = read_safety_gains(getattr(model, "safety", None))  # trained behind the safety filter: it acts behind it
    return policy if gains is None else SafePolicy(policy, gains)
